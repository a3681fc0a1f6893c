"""Self-collision pairs inside the linearised implicit solve (seed Eq. 15).

A pair of the mesh (point-triangle or edge-edge, ``kernels/self_collision.py``) closer
than the thickness t at the step's start x_n is a penalty spring on the gap between
its closest points: with signed weights w (side A positive, side B negative, so
p - q = sum_k w_k x_k = d n), its energy is E = k (t - d)^2 / 2 (k: the
``SelfCollision`` stiffness, N/m), its force on particle k is f_k = k (t - d) w_k n
(apart), and its stiffness, with the normal held (the Gauss-Newton part, positive
semi-definite), is -K = k (w w^T) (x) (n n^T). Eq. 15 then gains

    A += dt^2 k (w w^T) (x) (n n^T),   b += dt f,

and stays symmetric positive definite. The self-collision pass still follows the
step (repulsion of what the solve left approaching, displacement bounds, friction).

``collect`` runs (``self_collision_solve_pairs``) at the end of each full
self-collision pass, on the positions the step ends at (the next step's x_n), and at a
run's start or restart after ``self_collision_list``: the pass's list then holds every pair within t of them,
and a step that skips the pass moves no pair within t (nor any particle of a pair
already within t), so the pairs stay those of x_n. It gathers the pairs within t into
``sp_idx``/``sp_w``/``sp_nf`` and builds, per particle, its entries (pair, k) in CSR
form (``sp_first``, ``sp_entry``), each particle's entries sorted by the pair's
particles: ``pair_row`` then sums a particle's share in one fixed order, so A p is
the same bits for any thread count, without atomics. If the pairs overflow ``sp_idx``
(``SOLVE_PAIRS_PER_PARTICLE`` per particle), none enters the solve that step (which
would fit depends on the threads' order), the pass alone handles them, and
``sp_count[1]`` says how many there were. ``pair_penalty_read`` and
``pair_penalty_write`` copy a step's pairs out and back in (a gradient's adjoint solve
of that step runs with them: ``massspring.passes.self_collision.penalty_adjoint``).

Fields (``massspring/passes/self_collision/__init__.py``'s ``declare_solve``; n particles, P pair
capacity): ``sp_param`` (2,) real: t (m), k (N/m); ``sp_count`` (2,) i32: pairs in the
solve, pairs left out; ``sp_idx`` (P,) 4-vectors i32; ``sp_w`` (P,) 4-vectors;
``sp_nf`` (P,) 5-vectors (n, dt^2 k in kg, k (t - d) in N); ``sp_first`` (n + 1,),
``sp_fill`` (n,), ``sp_entry`` (4 P,) i32 (pair x 4 + k); ``sp_friction`` (n,) int64
4-vectors: the pass's friction sums for these pairs (``kernels/self_collision.py``).
"""

import taichi as ti

from .constraints import is_pinned
from .proximity import listed_pair


@ti.func
def before(dev, a, b):
    """Whether entry a sorts before entry b: by the pair's particles, then k."""
    pa = dev.sp_idx[a // 4]
    pb = dev.sp_idx[b // 4]
    out = 0
    decided = 0
    for c in ti.static(range(4)):
        if decided == 0 and pa[c] != pb[c]:
            decided = 1
            out = 1 if pa[c] < pb[c] else 0
    if decided == 0:
        out = 1 if a % 4 < b % 4 else 0
    return out


@ti.func
def collect(dev, cfg: ti.template(), pl, x, h):
    """The pairs of the pass's list ``pl`` within t at positions x into the solve's
    fields, and the per-particle entries (module docstring), for a step of h (s)."""
    n = dev.size[0]
    thick = dev.sp_param[0]
    k = dev.sp_param[1]
    cap = dev.sp_idx.shape[0]
    dev.sp_count[0] = 0
    dev.sp_count[1] = 0
    for i in range(n):
        dev.sp_fill[i] = 0
    for slot in range(dev.sc_tally[0]):
        idx = pl.pidx[slot]
        d, w = listed_pair(x, idx, pl.pkind[slot], cfg.real)
        if d < thick:
            gap = ti.Vector.zero(cfg.real, 3)
            for c in ti.static(range(4)):
                gap += w[c] * x[idx[c]]
            length = gap.norm()
            if length > 0:
                a = ti.atomic_add(dev.sp_count[0], 1)
                if a < cap:
                    normal = gap / length
                    dev.sp_idx[a] = idx
                    dev.sp_w[a] = w
                    dev.sp_nf[a] = ti.Vector([normal[0], normal[1], normal[2], h * h * k, k * (thick - d)],
                                             cfg.real)
    found = dev.sp_count[0]
    if found > cap:
        dev.sp_count[0] = 0
        dev.sp_count[1] = found
    pairs = dev.sp_count[0]
    for a in range(pairs):
        idx = dev.sp_idx[a]
        for c in ti.static(range(4)):
            if not is_pinned(idx[c], dev, cfg):
                ti.atomic_add(dev.sp_fill[idx[c]], 1)
    dev.sp_first[0] = 0
    ti.loop_config(serialize=True)
    for i in range(n):
        dev.sp_first[i + 1] = dev.sp_first[i] + dev.sp_fill[i]
        dev.sp_fill[i] = 0
    for a in range(pairs):
        idx = dev.sp_idx[a]
        for c in ti.static(range(4)):
            i = idx[c]
            if not is_pinned(i, dev, cfg):
                dev.sp_entry[dev.sp_first[i] + ti.atomic_add(dev.sp_fill[i], 1)] = 4 * a + c
    for i in range(n):  # insertion sort of each particle's few entries
        lo = dev.sp_first[i]
        for e in range(lo + 1, dev.sp_first[i + 1]):
            item = dev.sp_entry[e]
            j = e
            while j > lo and before(dev, item, dev.sp_entry[j - 1]) == 1:
                dev.sp_entry[j] = dev.sp_entry[j - 1]
                j -= 1
            dev.sp_entry[j] = item


@ti.func
def pair_row(i, dev, cfg: ti.template(), p):
    """Particle i's share of the pairs' dt^2 k (w w^T) (x) (n n^T) p (kg m/s for p in m/s)."""
    out = ti.Vector.zero(cfg.real, 3)
    for e in range(dev.sp_first[i], dev.sp_first[i + 1]):
        item = dev.sp_entry[e]
        a = item // 4
        idx = dev.sp_idx[a]
        w = dev.sp_w[a]
        nf = dev.sp_nf[a]
        normal = ti.Vector([nf[0], nf[1], nf[2]], cfg.real)
        gap = ti.Vector.zero(cfg.real, 3)
        for c in ti.static(range(4)):
            gap += w[c] * p[idx[c]]
        out += nf[3] * w[item % 4] * normal.dot(gap) * normal
    return out


@ti.func
def pair_diagonal(i, dev, cfg: ti.template()):
    """Particle i's diagonal block of the pairs' term: sum dt^2 k w_k^2 n n^T (kg)."""
    block = ti.Matrix.zero(cfg.real, 3, 3)
    for e in range(dev.sp_first[i], dev.sp_first[i + 1]):
        item = dev.sp_entry[e]
        nf = dev.sp_nf[item // 4]
        normal = ti.Vector([nf[0], nf[1], nf[2]], cfg.real)
        wk = dev.sp_w[item // 4][item % 4]
        block += nf[3] * wk * wk * normal.outer_product(normal)
    return block


@ti.func
def pair_force(i, dev, cfg: ti.template()):
    """The pairs' penalty force on particle i (N): sum k (t - d) w_k n."""
    f = ti.Vector.zero(cfg.real, 3)
    for e in range(dev.sp_first[i], dev.sp_first[i + 1]):
        item = dev.sp_entry[e]
        nf = dev.sp_nf[item // 4]
        f += nf[4] * dev.sp_w[item // 4][item % 4] * ti.Vector([nf[0], nf[1], nf[2]], cfg.real)
    return f


@ti.kernel
def pair_penalty_read(dev: ti.template(), idx: ti.types.ndarray(dtype=ti.i32, ndim=2),
                      w: ti.types.ndarray(dtype=ti.f64, ndim=2), nf: ti.types.ndarray(dtype=ti.f64, ndim=2),
                      first: ti.types.ndarray(dtype=ti.i32, ndim=1), entry: ti.types.ndarray(dtype=ti.i32, ndim=1)):
    """The solve's pairs as they stand (a gradient's record of a step): the first
    ``idx.shape[0]`` pairs' particles (P, 4), weights (P, 4), ``sp_nf`` (P, 5), the
    particles' ``sp_first`` (n + 1,) and the first ``entry.shape[0]`` entries."""
    for a in range(idx.shape[0]):
        for c in ti.static(range(4)):
            idx[a, c] = dev.sp_idx[a][c]
            w[a, c] = ti.cast(dev.sp_w[a][c], ti.f64)
        for c in ti.static(range(5)):
            nf[a, c] = ti.cast(dev.sp_nf[a][c], ti.f64)
    for i in range(first.shape[0]):
        first[i] = dev.sp_first[i]
    for e in range(entry.shape[0]):
        entry[e] = dev.sp_entry[e]


@ti.kernel
def pair_penalty_write(dev: ti.template(), count: ti.i32, entries: ti.i32,
                       idx: ti.types.ndarray(dtype=ti.i32, ndim=2), w: ti.types.ndarray(dtype=ti.f64, ndim=2),
                       nf: ti.types.ndarray(dtype=ti.f64, ndim=2),
                       first: ti.types.ndarray(dtype=ti.i32, ndim=1), entry: ti.types.ndarray(dtype=ti.i32, ndim=1)):
    """``pair_penalty_read``'s arrays back into the solve's fields (a gradient's adjoint
    solve of that step): ``count`` pairs, ``entries`` entries, ``sp_count`` = (count, 0);
    count 0 and ``first`` zero: no pairs."""
    dev.sp_count[0] = count
    dev.sp_count[1] = 0
    for a in range(count):
        for c in ti.static(range(4)):
            dev.sp_idx[a][c] = idx[a, c]
            dev.sp_w[a][c] = w[a, c]
        for c in ti.static(range(5)):
            dev.sp_nf[a][c] = nf[a, c]
    for i in range(first.shape[0]):
        dev.sp_first[i] = first[i]
    for e in range(entries):
        dev.sp_entry[e] = entry[e]
