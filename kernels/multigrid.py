"""Kernels of the smoothed-aggregation multigrid preconditioner (``massspring.solvers.multigrid``).

Level 0 is the particles with the matrix-free operator of Eq. 15 (``operator``):
A_ii = ``diagonal_block``, A_ij = -S_e for adjacency entry e. Coarse levels
1..L-1 hold 6 unknowns per node and are stored together (nodes of level l at
``[base_l, base_l + n_l)``; ``g.c_diag`` (6x6 per node) and off-diagonal blocks
``g.c_off`` in CSR ``g.c_rows``/``g.c_cols``, global node indices). The index lists
come from ``massspring.solvers.aggregation`` (see ``Level`` there).

Per step (values only, patterns fixed):
* ``tentative0`` / ``tentativec``: T, per aggregate an orthonormal basis of its
  members' rigid motions at the current positions (level 0) or of their candidate
  blocks (coarser levels), and R, the next level's candidates (``g.c_cand``);
* ``fine_inverse``: D^-1 of level 0 (inverse 3x3 diagonal blocks, zero where pinned);
* ``smooth_p0`` / ``smooth_pc``: P = T - (omega / rho) D^-1 A T in P's pattern;
* ``ap0`` / ``apc``: A P; ``galerkin0`` / ``galerkinc``: the upper blocks of P^T (A P),
  ``mirror``: the lower ones. On level 0 both take A's kept couplings only
  (``g.s0_entry``; P's smoothing those flagged in ``g.s0_smooth``) and the diagonal
  blocks of those (``kept_block``): the weak couplings ``aggregation.filter_fine``
  leaves out;
* ``coarse_inverse``: D^-1 of a coarse level (6x6, by Cholesky); ``lanczos_start``,
  ``lanczos_apply`` and ``lanczos_next``: Lanczos on D^-1 A (self-adjoint in the D
  inner product) for the estimate of rho(D^-1 A) its smoothing uses;
  ``factor_coarsest``: dense Cholesky of the last level.

Per CG iteration, the V(nu, nu)-cycle: Chebyshev smoothing in D^-1 A on
[rho / CHEB_RATIO, rho] and the restriction P^T (``down0`` on level 0, ``downc`` on
coarse levels), the coarse cycle, the prolongation P and the same smoothing again
(``up0``, ``upc``; so the cycle is a symmetric positive definite preconditioner),
and the direct solve on the coarsest level (``solve_coarsest``). On level 0 every vector is filtered by the
constraints (``constraints.constrain``): z = S V(S r).

Every kernel takes ``serial`` (a template flag) to run its loops in one thread:
small systems, where a parallel launch costs more than the work. Each loop
iteration owns the entries it writes, so updates are written ``a[k] = a[k] + b``:
``+=`` on a field compiles to an atomic add, a compare-and-swap loop per f64 entry
that made parallel setup slower than serial.
"""

import taichi as ti

from .blocks import BLOCK, block_count, block_end, ordered_sum
from .constraints import constrain, is_free, is_pinned, projector
from .operator import apply_row, diagonal_block, entry_block, entry_times
from .pair_penalty import pair_diagonal

BS = 6  # unknowns per coarse node


# ------------------------------------------------------------------ small dense algebra


@ti.func
def idle_pivot(scale, real: ti.template()):
    """The largest Cholesky pivot still taken for zero, relative to ``scale``, the largest
    diagonal entry of the unknown's 6x6 node block: a mode the block hardly resists
    (round-off of a dependent column, or a rigid mode the constraints filtered out)."""
    eps = ti.cast(1e-4, real) if ti.static(real == ti.f32) else ti.cast(1e-8, real)
    return eps * scale


@ti.func
def block_scale(a: ti.template(), k, real: ti.template()):
    """The largest diagonal entry of the 6x6 block a[k]."""
    out = ti.cast(0, real)
    for j in range(BS):
        out = ti.max(out, ti.abs(a[k][j, j]))
    return out


@ti.func
def invert6(src: ti.template(), dst: ti.template(), k, real: ti.template()):
    """dst[k] = src[k]^-1 for a symmetric positive definite 6x6 block, by Cholesky with
    loops at run time (unrolled 6x6 algebra compiles for seconds); zero if it is not SPD.
    Returns whether it was. A pivot below ``idle_pivot`` of the block's scale is an idle
    unknown and is decoupled (pivot 1, column 0): a dropped candidate, or a rigid mode
    of an aggregate that the constraints filtered out of P (a cloth lying on a plane
    loses its aggregates' normal translation and tilts); kept, its near-zero pivot made
    the inverse huge and, by round-off, indefinite."""
    lower = ti.Matrix.zero(real, BS, BS)
    ok = True
    tiny = idle_pivot(block_scale(src, k, real), real)
    for j in range(BS):
        s = src[k][j, j]
        for m in range(j):
            s -= lower[j, m] * lower[j, m]
        if not s > tiny:
            if s < -tiny:
                ok = False
            lower[j, j] = ti.cast(1, real)  # idle: unknown j is decoupled
        else:
            d = ti.sqrt(s)
            lower[j, j] = d
            for i in range(j + 1, BS):
                t = src[k][i, j]
                for m in range(j):
                    t -= lower[i, m] * lower[j, m]
                lower[i, j] = t / d
    for col in range(BS):  # column col of the inverse: L L^T y = e_col
        y = ti.Vector.zero(real, BS)
        for r in range(BS):
            s = ti.cast(1 if r == col else 0, real)
            for m in range(r):
                s -= lower[r, m] * y[m]
            y[r] = s / lower[r, r]
        for step in range(BS):
            r = BS - 1 - step
            s = y[r]
            for m in range(r + 1, BS):
                s -= lower[m, r] * y[m]
            y[r] = s / lower[r, r]
        for r in range(BS):
            dst[k][r, col] = y[r] if ok else ti.cast(0, real)
    return ok


@ti.func
def add_product(dst: ti.template(), di, a: ti.template(), ai, b: ti.template(), bi, scale,
                transpose_a: ti.template()):
    """dst[di] += scale * a[ai] @ b[bi] (a[ai]^T with ``transpose_a``), 6-column blocks:
    a loop over dst's rows at run time, each row's sums unrolled."""
    for r in range(dst.n):
        row = ti.Vector([a[ai][c, r] if ti.static(transpose_a) else a[ai][r, c] for c in ti.static(range(b.n))])
        for col in ti.static(range(BS)):
            acc = row[0] * b[bi][0, col]
            for c in ti.static(range(1, b.n)):
                acc += row[c] * b[bi][c, col]
            dst[di][r, col] = dst[di][r, col] + scale * acc


@ti.func
def block_vector(a: ti.template(), ai, v, real: ti.template()):
    """a[ai] @ v for a 6x6 block and a 6-vector, rows looped at run time."""
    out = ti.Vector.zero(real, BS)
    for r in range(BS):
        acc = a[ai][r, 0] * v[0]
        for c in ti.static(range(1, BS)):
            acc += a[ai][r, c] * v[c]
        out[r] = acc
    return out


@ti.func
def block_t_vector(a: ti.template(), ai, v, real: ti.template()):
    """a[ai]^T @ v for a (rows x 6) block and a rows-vector."""
    out = ti.Vector.zero(real, BS)
    for c in range(BS):
        acc = a[ai][0, c] * v[0]
        for r in ti.static(range(1, a.n)):
            acc += a[ai][r, c] * v[r]
        out[c] = acc
    return out


@ti.func
def loops(serial: ti.template()):
    ti.loop_config(serialize=serial)


# ------------------------------------------------------------------------- setup


@ti.func
def orthonormalize(t: ti.template(), members: ti.template(), lo, hi, cand: ti.template(), a, drop,
                   real: ti.template()):
    """Modified Gram-Schmidt on the 6 columns of the stacked blocks t[members[lo:hi]]
    (a thin QR, in place: they become Q), R into ``cand[a]``. A column whose remainder
    is at most ``drop`` times its norm becomes zero, and so does R's diagonal entry."""
    for j in range(BS):
        norm0 = ti.cast(0, real)
        for k in range(lo, hi):
            for r in ti.static(range(t.n)):
                norm0 += t[members[k]][r, j] * t[members[k]][r, j]
        for p in range(j):
            d = ti.cast(0, real)
            for k in range(lo, hi):
                for r in ti.static(range(t.n)):
                    d += t[members[k]][r, p] * t[members[k]][r, j]
            for k in range(lo, hi):
                m = members[k]
                for r in ti.static(range(t.n)):
                    t[m][r, j] = t[m][r, j] - d * t[m][r, p]
            cand[a][p, j] = d
        norm2 = ti.cast(0, real)
        for k in range(lo, hi):
            for r in ti.static(range(t.n)):
                norm2 += t[members[k]][r, j] * t[members[k]][r, j]
        live = norm2 > drop * drop * norm0
        scale = ti.cast(0, real)
        if live:
            scale = ti.cast(1, real) / ti.sqrt(norm2)
        for k in range(lo, hi):
            m = members[k]
            for r in ti.static(range(t.n)):
                t[m][r, j] = t[m][r, j] * scale
        cand[a][j, j] = norm2 * scale
        for i in range(j + 1, BS):
            cand[a][i, j] = ti.cast(0, real)


@ti.func
def mean_point(points: ti.template(), members: ti.template(), lo, hi, real: ti.template()):
    """The mean of points[members[k]] for k in [lo, hi): an aggregate's centre (m)."""
    centre = ti.Vector.zero(real, 3)
    for k in range(lo, hi):
        centre += points[members[k]]
    return centre / ti.cast(ti.max(hi - lo, 1), real)


@ti.kernel
def tentative0(dev: ti.template(), cfg: ti.template(), g: ti.template(), count: ti.i32, drop: ti.f64,
               serial: ti.template()):
    """Level 0's T (``g.t0``), level 1's candidates (``g.c_cand``) and centres
    (``g.c_centre``), aggregates [0, count): each member's block [I | e_k x r]
    (translations and rotations about the aggregate's centre, r = x_i - centre, m),
    orthonormalized per aggregate."""
    dr = ti.cast(drop, cfg.real)
    loops(serial)
    for a in range(count):
        lo, hi = g.agg0_rows[a], g.agg0_rows[a + 1]
        centre = mean_point(dev.x, g.agg0_members, lo, hi, cfg.real)
        for k in range(lo, hi):
            m = g.agg0_members[k]
            r = dev.x[m] - centre
            g.t0[m] = ti.Matrix([[1, 0, 0, 0, r[2], -r[1]],
                                 [0, 1, 0, -r[2], 0, r[0]],
                                 [0, 0, 1, r[1], -r[0], 0]], cfg.real)
        orthonormalize(g.t0, g.agg0_members, lo, hi, g.c_cand, a, dr, cfg.real)
        g.c_centre[a] = centre


@ti.kernel
def tentativec(cfg: ti.template(), g: ti.template(), begin: ti.i32, end: ti.i32, drop: ti.f64,
               serial: ti.template()):
    """A coarse level's T (``g.tc`` of its nodes) and the next level's candidates and
    centres, for the next level's nodes [begin, end) (global): each member's candidates
    with their rotations moved to the aggregate's centre (a rotation about the member's
    centre c_m is the one about the aggregate's centre c plus the translation
    e_k x (c_m - c)), orthonormalized per aggregate."""
    dr = ti.cast(drop, cfg.real)
    loops(serial)
    for a in range(begin, end):
        lo, hi = g.aggc_rows[a], g.aggc_rows[a + 1]
        centre = mean_point(g.c_centre, g.aggc_members, lo, hi, cfg.real)
        for k in range(lo, hi):
            m = g.aggc_members[k]
            d = g.c_centre[m] - centre
            for r in range(BS):
                row = ti.Vector([g.c_cand[m][r, c] for c in ti.static(range(BS))])
                g.tc[m][r, 3] = row[3] - row[1] * d[2] + row[2] * d[1]   # + row[:3] . (e_x x d)
                g.tc[m][r, 4] = row[4] + row[0] * d[2] - row[2] * d[0]   # e_y x d
                g.tc[m][r, 5] = row[5] - row[0] * d[1] + row[1] * d[0]   # e_z x d
                for c in ti.static(range(3)):
                    g.tc[m][r, c] = row[c]
        orthonormalize(g.tc, g.aggc_members, lo, hi, g.c_cand, a, dr, cfg.real)
        g.c_centre[a] = centre


@ti.kernel
def fine_inverse(dev: ti.template(), cfg: ti.template(), serial: ti.template()) -> ti.f64:
    """``dev.minv`` = D_i^+: A_ii^-1 on free particles, zero on pinned ones, and on a
    particle in contact (S_i its projector onto the free directions) the inverse of
    S_i A_ii S_i on those directions, S_i (S_i A_ii S_i + I - S_i)^-1 S_i, so the
    smoother is block-Jacobi of the filtered operator S A S (whose spectrum relative to
    it keeps the bound below). Returns a bound on rho(D^+ A): the largest row sum of
    the infinity norms of D_i^+ A_ij."""
    bound = 0.0
    loops(serial)
    for i in range(dev.size[0]):
        inverse = ti.Matrix.zero(cfg.real, 3, 3)
        if not is_pinned(i, dev, cfg):
            block = diagonal_block(i, dev, cfg)
            if is_free(i, dev, cfg):
                inverse = ti.cast(block.inverse(), cfg.real)
            else:
                proj = projector(i, dev, cfg)
                filtered = proj @ block @ proj + ti.Matrix.identity(cfg.real, 3) - proj
                inverse = proj @ ti.cast(filtered.inverse(), cfg.real) @ proj
            row = ti.cast(_inf_norm(inverse @ block), ti.f64)
            if ti.static(cfg.has_springs):
                for e in range(dev.offsets[i], dev.offsets[i + 1]):
                    row += ti.cast(_inf_norm(inverse @ entry_block(e, dev, cfg)), ti.f64)
            ti.atomic_max(bound, row)
        dev.minv[i] = inverse
    return bound


@ti.func
def kept_block(i, dev, cfg: ti.template(), g: ti.template(), smoothing: ti.template()):
    """Level 0's diagonal block with the kept couplings only (``g.s0_entry``; those that
    smooth P, ``g.s0_smooth``, with ``smoothing``): A_ii less the blocks of the springs
    left out."""
    block = dev.diag[i] * ti.Matrix.identity(cfg.real, 3)
    if ti.static(cfg.has_springs):
        for k in range(g.s0_rows[i], g.s0_rows[i + 1]):
            if ti.static(not smoothing) or g.s0_smooth[k] != 0:
                block += entry_block(g.s0_entry[k], dev, cfg)
    if ti.static(cfg.self_pairs):
        block += pair_diagonal(i, dev, cfg)
    return block


@ti.kernel
def smooth_p0(dev: ti.template(), cfg: ti.template(), g: ti.template(), scale: ti.f64, serial: ti.template()):
    """Level 0's P = S (T - scale D^+ A' T) (scale = omega / rho; A' the operator of the kept
    couplings, ``kept_block``), row by row: S filters the constrained directions (pins,
    contact normals) out of P's rows, so that the Galerkin operators P^T A' P are those
    of the filtered operator S A' S."""
    s = ti.cast(scale, cfg.real)
    loops(serial)
    for i in range(dev.size[0]):
        for k in range(g.p0_rows[i], g.p0_rows[i + 1]):
            g.p0[k] = ti.Matrix.zero(cfg.real, 3, BS)
        slot = g.t0_slot[i]
        if slot >= 0:
            block = kept_block(i, dev, cfg, g, True)
            g.p0[slot] = g.p0[slot] + block @ g.t0[i]
        if ti.static(cfg.has_springs):
            for k in range(g.s0_rows[i], g.s0_rows[i + 1]):
                target = g.e0_slot[k]
                if target >= 0:
                    e = g.s0_entry[k]
                    g.p0[target] = g.p0[target] - entry_times(e, dev, cfg, g.t0[dev.other[e]])
        for k in range(g.p0_rows[i], g.p0_rows[i + 1]):
            g.p0[k] = -s * (dev.minv[i] @ g.p0[k])
        if slot >= 0:
            g.p0[slot] = g.p0[slot] + g.t0[i]
        if not is_free(i, dev, cfg):  # P's rows filtered: the coarse levels see S A' S
            projection = projector(i, dev, cfg)
            for k in range(g.p0_rows[i], g.p0_rows[i + 1]):
                g.p0[k] = projection @ g.p0[k]


@ti.kernel
def ap0(dev: ti.template(), cfg: ti.template(), g: ti.template(), serial: ti.template()):
    """Level 0's A' P, row by row: A'_ii P_i. then -S_e P_j. for each kept entry e = (i, j),
    in the order of ``g.apt0_ap`` (the A' P block each product goes to)."""
    loops(serial)
    for i in range(dev.size[0]):
        for k in range(g.ap0_rows[i], g.ap0_rows[i + 1]):
            g.ap0[k] = ti.Matrix.zero(cfg.real, 3, BS)
        t = g.apt0_rows[i]
        block = kept_block(i, dev, cfg, g, False)
        for k in range(g.p0_rows[i], g.p0_rows[i + 1]):
            target = g.apt0_ap[t]
            g.ap0[target] = g.ap0[target] + block @ g.p0[k]
            t += 1
        if ti.static(cfg.has_springs):
            for s in range(g.s0_rows[i], g.s0_rows[i + 1]):
                e = g.s0_entry[s]
                j = dev.other[e]
                for k in range(g.p0_rows[j], g.p0_rows[j + 1]):
                    target = g.apt0_ap[t]
                    g.ap0[target] = g.ap0[target] - entry_times(e, dev, cfg, g.p0[k])
                    t += 1


@ti.kernel
def galerkin0(cfg: ti.template(), g: ti.template(), count: ti.i32, serial: ti.template()):
    """The upper blocks of level 1's P^T A P from level 0's P and A P."""
    loops(serial)
    for b in range(count):
        acc = ti.Matrix.zero(cfg.real, BS, BS)
        for k in range(g.gal0_rows[b], g.gal0_rows[b + 1]):
            acc += g.p0[g.gal0_p[k]].transpose() @ g.ap0[g.gal0_ap[k]]
        target = g.gal0_block[b]
        if target < 0:
            g.c_diag[-1 - target] = acc
        else:
            g.c_off[target] = acc


@ti.kernel
def mirror(cfg: ti.template(), g: ti.template(), begin: ti.i32, end: ti.i32, serial: ti.template()):
    """Lower off-diagonal blocks of a coarse level (entries ``g.lower[begin:end]``) from their
    upper transposes."""
    loops(serial)
    for k in range(begin, end):
        e = g.lower[k]
        g.c_off[e] = g.c_off[g.c_mirror[e]].transpose()


@ti.kernel
def coarse_inverse(cfg: ti.template(), g: ti.template(), begin: ti.i32, end: ti.i32,
                   serial: ti.template()) -> ti.i32:
    """``g.c_dinv`` = inverse diagonal blocks of coarse nodes [begin, end); returns how many
    blocks were not positive definite (their inverse is set to zero)."""
    bad = 0
    loops(serial)
    for node in range(begin, end):
        if not invert6(g.c_diag, g.c_dinv, node, cfg.real):
            bad += 1
    return bad


@ti.func
def ordered_range_sum(partial: ti.template(), count):
    total = ti.Vector.zero(ti.f64, 2)
    ti.loop_config(serialize=True)
    for b in range(count):
        total += partial[b]
    return total


@ti.kernel
def lanczos_start(cfg: ti.template(), g: ti.template(), begin: ti.i32, end: ti.i32,
                  serial: ti.template()) -> ti.f64:
    """The start vector w of Lanczos on D^-1 A for nodes [begin, end) (a fixed
    pseudo-random vector, in ``g.c_res``), v_old = 0 (``g.c_d``); returns w^T D w."""
    count = (end - begin + BLOCK - 1) // BLOCK
    loops(serial)
    for blk in range(count):
        acc = 0.0
        for node in range(begin + blk * BLOCK, ti.min(end, begin + (blk + 1) * BLOCK)):
            w = ti.Vector.zero(cfg.real, BS)
            for c in ti.static(range(BS)):
                h = ((node * BS + c) * 7919 + 12345) % 10007  # a fixed pseudo-random sequence
                w[c] = ti.cast(h / 10007 - 0.5, cfg.real)
            g.c_res[node] = w
            g.c_d[node] = ti.Vector.zero(cfg.real, BS)
            acc += ti.cast(w.dot(block_vector(g.c_diag, node, w, cfg.real)), ti.f64)
        g.c_partial[blk] = ti.Vector([acc, 0.0], ti.f64)
    return ordered_range_sum(g.c_partial, count)[0]


@ti.kernel
def lanczos_apply(cfg: ti.template(), g: ti.template(), begin: ti.i32, end: ti.i32, inv_beta: ti.f64,
                  serial: ti.template()) -> ti.f64:
    """One Lanczos step, first half: v_old = v; v = w / beta; A v (into ``g.c_b``);
    returns alpha = v^T A v."""
    ib = ti.cast(inv_beta, cfg.real)
    count = (end - begin + BLOCK - 1) // BLOCK
    loops(serial)
    for blk in range(count):
        acc = 0.0
        for node in range(begin + blk * BLOCK, ti.min(end, begin + (blk + 1) * BLOCK)):
            g.c_d[node] = g.c_x[node]
            v = ib * g.c_res[node]
            g.c_x[node] = v
            av = ib * coarse_row(g, node, g.c_res, cfg.real)
            g.c_b[node] = av
            acc += ti.cast(v.dot(av), ti.f64)
        g.c_partial[blk] = ti.Vector([acc, 0.0], ti.f64)
    return ordered_range_sum(g.c_partial, count)[0]


@ti.kernel
def lanczos_next(cfg: ti.template(), g: ti.template(), begin: ti.i32, end: ti.i32, alpha: ti.f64, beta: ti.f64,
                 serial: ti.template()) -> ti.f64:
    """Second half: w = D^-1 A v - alpha v - beta v_old (into ``g.c_res``); returns w^T D w."""
    a = ti.cast(alpha, cfg.real)
    b = ti.cast(beta, cfg.real)
    count = (end - begin + BLOCK - 1) // BLOCK
    loops(serial)
    for blk in range(count):
        acc = 0.0
        for node in range(begin + blk * BLOCK, ti.min(end, begin + (blk + 1) * BLOCK)):
            w = block_vector(g.c_dinv, node, g.c_b[node], cfg.real) - a * g.c_x[node] - b * g.c_d[node]
            g.c_res[node] = w
            acc += ti.cast(w.dot(block_vector(g.c_diag, node, w, cfg.real)), ti.f64)
        g.c_partial[blk] = ti.Vector([acc, 0.0], ti.f64)
    return ordered_range_sum(g.c_partial, count)[0]


@ti.func
def _inf_norm(m):
    out = ti.abs(m[0, 0]) * 0
    for r in ti.static(range(m.n)):
        s = ti.abs(m[r, 0]) * 0
        for c in ti.static(range(m.m)):
            s += ti.abs(m[r, c])
        out = ti.max(out, s)
    return out


@ti.kernel
def smooth_pc(cfg: ti.template(), g: ti.template(), begin: ti.i32, end: ti.i32, scale: ti.f64,
              serial: ti.template()):
    """A coarse level's P = T - scale D^-1 A T, rows = nodes [begin, end)."""
    s = ti.cast(scale, cfg.real)
    loops(serial)
    for node in range(begin, end):
        for k in range(g.pc_rows[node], g.pc_rows[node + 1]):
            g.apc_tmp[k] = ti.Matrix.zero(cfg.real, BS, BS)
        slot = g.tc_slot[node]
        if slot >= 0:
            add_product(g.apc_tmp, slot, g.c_diag, node, g.tc, node, 1, False)
        for k in range(g.c_rows[node], g.c_rows[node + 1]):
            target = g.ec_slot[k]
            if target >= 0:
                add_product(g.apc_tmp, target, g.c_off, k, g.tc, g.c_cols[k], 1, False)
        for k in range(g.pc_rows[node], g.pc_rows[node + 1]):
            g.pc[k] = ti.Matrix.zero(cfg.real, BS, BS)
            add_product(g.pc, k, g.c_dinv, node, g.apc_tmp, k, -s, False)
        if slot >= 0:
            g.pc[slot] = g.pc[slot] + g.tc[node]


@ti.kernel
def apc(cfg: ti.template(), g: ti.template(), begin: ti.i32, end: ti.i32, serial: ti.template()):
    """A coarse level's A P, rows = nodes [begin, end): the diagonal block times the node's
    P row, then each off-diagonal block times its column node's P row (``g.aptc_ap`` order)."""
    loops(serial)
    for node in range(begin, end):
        for k in range(g.apc_rows[node], g.apc_rows[node + 1]):
            g.apc[k] = ti.Matrix.zero(cfg.real, BS, BS)
        t = g.aptc_rows[node]
        for k in range(g.pc_rows[node], g.pc_rows[node + 1]):
            add_product(g.apc, g.aptc_ap[t], g.c_diag, node, g.pc, k, 1, False)
            t += 1
        for e in range(g.c_rows[node], g.c_rows[node + 1]):
            j = g.c_cols[e]
            for k in range(g.pc_rows[j], g.pc_rows[j + 1]):
                add_product(g.apc, g.aptc_ap[t], g.c_off, e, g.pc, k, 1, False)
                t += 1


@ti.kernel
def galerkinc(cfg: ti.template(), g: ti.template(), begin: ti.i32, end: ti.i32, serial: ti.template()):
    """Upper blocks of the next level's P^T A P: Galerkin blocks [begin, end) (global)."""
    loops(serial)
    for b in range(begin, end):
        g.gal_tmp[b] = ti.Matrix.zero(cfg.real, BS, BS)
        for k in range(g.galc_rows[b], g.galc_rows[b + 1]):
            add_product(g.gal_tmp, b, g.pc, g.galc_p[k], g.apc, g.galc_ap[k], 1, True)
        target = g.galc_block[b]
        if target < 0:
            g.c_diag[-1 - target] = g.gal_tmp[b]
        else:
            g.c_off[target] = g.gal_tmp[b]


@ti.kernel
def factor_coarsest(cfg: ti.template(), g: ti.template(), base: ti.i32, nodes: ti.i32) -> ti.i32:
    """Dense Cholesky L L^T of the coarsest level (nodes [base, base + nodes)) into
    ``g.chol`` (row-major, ``nodes * 6`` per row; lower triangle). Returns 0, or 1 + the
    failing column if the level's operator is not positive definite."""
    size = nodes * BS
    failed = 0
    ti.loop_config(serialize=True)
    for _ in range(1):
        for r in range(size * size):
            g.chol[r] = ti.cast(0, cfg.real)
        for node in range(nodes):
            for a in range(BS):
                for b in range(BS):
                    g.chol[(node * BS + a) * size + node * BS + b] = g.c_diag[base + node][a, b]
            for k in range(g.c_rows[base + node], g.c_rows[base + node + 1]):
                other = g.c_cols[k] - base
                for a in range(BS):
                    for b in range(BS):
                        g.chol[(node * BS + a) * size + other * BS + b] = g.c_off[k][a, b]
        for j in range(size):
            if failed == 0:
                s = g.chol[j * size + j]
                for k in range(j):
                    s -= g.chol[j * size + k] * g.chol[j * size + k]
                tiny = idle_pivot(block_scale(g.c_diag, base + j // BS, cfg.real), cfg.real)
                if s < -tiny:
                    failed = j + 1
                elif not s > tiny:  # an idle unknown (see invert6): decoupled
                    g.chol[j * size + j] = ti.cast(1, cfg.real)
                    for i in range(j + 1, size):
                        g.chol[i * size + j] = ti.cast(0, cfg.real)
                else:
                    d = ti.sqrt(s)
                    g.chol[j * size + j] = d
                    for i in range(j + 1, size):
                        t = g.chol[i * size + j]
                        for k in range(j):
                            t -= g.chol[i * size + k] * g.chol[j * size + k]
                        g.chol[i * size + j] = t / d
    return failed


# -------------------------------------------------------------------------- cycle
# One kernel per level and direction: ``down0``/``downc`` (pre-smoothing, then the
# restriction to the next level), ``up0``/``upc`` (the prolongation, then
# post-smoothing): 7 launches per cycle of 4 levels instead of 32. Each phase is
# still its own parallel loop (a pass over the level), but the launch's own cost
# (Python arguments, runtime context) is paid once per level and direction.

MAX_DEGREE = 8  # Chebyshev degrees the cycle kernels take
COEF = ti.types.vector(1 + 2 * MAX_DEGREE, ti.f64)  # 1 / theta, then (c1, c2) per step
COEF_ZERO = (0.0,) * (1 + 2 * MAX_DEGREE)


@ti.func
def cheb_start0(dev: ti.template(), cfg: ti.template(), first: ti.template(), inv_theta,
                serial: ti.template()):
    """Level 0, start of a smoothing: with ``first`` the pre-smoothing from x = 0 (residual =
    the input r); else the post-smoothing from the current x (residual = r - A x). Then
    d = D^-1 res / theta. Vectors: ``dev.mg_x``, ``mg_res``, ``mg_d``; input ``dev.r``
    (CG's, read in the cycle's precision ``cfg.real``: ``Narrowed``)."""
    it = ti.cast(inv_theta, cfg.real)
    loops(serial)
    for i in range(dev.size[0]):
        res = ti.cast(dev.r[i], cfg.real)
        if ti.static(first):
            dev.mg_x[i] = ti.Vector.zero(cfg.real, 3)
        else:
            res = constrain(i, dev, cfg, res - apply_row(i, dev, cfg, dev.mg_x))
        dev.mg_res[i] = res
        dev.mg_d[i] = constrain(i, dev, cfg, it * (dev.minv[i] @ res))


@ti.func
def cheb_step0(dev: ti.template(), cfg: ti.template(), src: ti.template(), dst: ti.template(), c1, c2,
               last: ti.template(), serial: ti.template()):
    """Level 0, one Chebyshev step: x += d, res -= A d, d' = c1 d + c2 D^-1 res (into ``dst``)."""
    a = ti.cast(c1, cfg.real)
    b = ti.cast(c2, cfg.real)
    loops(serial)
    for i in range(dev.size[0]):
        d = src[i]
        dev.mg_x[i] = dev.mg_x[i] + d
        res = dev.mg_res[i] - constrain(i, dev, cfg, apply_row(i, dev, cfg, src))
        dev.mg_res[i] = res
        if ti.static(not last):
            dst[i] = a * d + constrain(i, dev, cfg, b * (dev.minv[i] @ res))


@ti.func
def smooth0(dev: ti.template(), cfg: ti.template(), first: ti.template(), coef, degree: ti.template(),
            serial: ti.template()):
    """Level 0's Chebyshev smoothing of ``degree`` steps with coefficients ``coef``
    (``COEF``), the directions alternating between ``dev.mg_d`` and ``dev.mg_d2``."""
    cheb_start0(dev, cfg, first, coef[0], serial)
    for k in ti.static(range(degree)):
        cheb_step0(dev, cfg, ti.static((dev.mg_d, dev.mg_d2)[k % 2]), ti.static((dev.mg_d2, dev.mg_d)[k % 2]),
                   coef[1 + 2 * k], coef[2 + 2 * k], k == degree - 1, serial)


@ti.kernel
def down0(dev: ti.template(), cfg: ti.template(), g: ti.template(), coef: COEF, degree: ti.template(),
          coarse: ti.template(), nodes: ti.i32, serial: ti.template()):
    """Level 0's pre-smoothing from x = 0, then (``coarse``) level 1's right-hand side
    c_b = P0^T res on its ``nodes`` nodes."""
    smooth0(dev, cfg, True, coef, degree, serial)
    if ti.static(coarse):
        loops(serial)
        for node in range(nodes):
            acc = ti.Vector.zero(cfg.real, BS)
            for k in range(g.pt0_rows[node], g.pt0_rows[node + 1]):
                acc += block_t_vector(g.p0, g.pt0_block[k], dev.mg_res[g.pt0_fine[k]], cfg.real)
            g.c_b[node] = acc


@ti.kernel
def up0(dev: ti.template(), cfg: ti.template(), g: ti.template(), coef: COEF, degree: ti.template(),
        coarse: ti.template(), serial: ti.template()) -> ti.f64:
    """(``coarse``) level 0's x += P0 e (e: level 1's solution in ``g.c_x``), filtered;
    the post-smoothing; z = S x (the cycle's output) into ``dev.z``. Returns r . z,
    summed in fixed blocks (``kernels/blocks.py``: the same bits for any thread count)."""
    if ti.static(coarse):
        loops(serial)
        for i in range(dev.size[0]):
            acc = ti.Vector.zero(cfg.real, 3)
            for k in range(g.p0_rows[i], g.p0_rows[i + 1]):
                acc += g.p0[k] @ ti.cast(g.c_x[g.p0_cols[k]], cfg.real)
            dev.mg_x[i] = dev.mg_x[i] + constrain(i, dev, cfg, acc)
    smooth0(dev, cfg, False, coef, degree, serial)
    n = dev.size[0]
    loops(serial)
    for blk in range(block_count(n)):
        acc = ti.Vector.zero(ti.f64, 3)
        for i in range(blk * BLOCK, block_end(blk, n)):
            dev.z[i] = constrain(i, dev, cfg, dev.mg_x[i])
            acc[0] += ti.cast(dev.r[i].dot(dev.z[i]), ti.f64)  # z as stored: CG's precision
        dev.partial[blk] = acc
    return ordered_sum(dev.partial, block_count(n))[0]


@ti.func
def coarse_row(g, node, x: ti.template(), real: ti.template()):
    """(A x)_node on a coarse level (off-diagonal pattern plus the diagonal block)."""
    out = block_vector(g.c_diag, node, x[node], real)
    for k in range(g.c_rows[node], g.c_rows[node + 1]):
        out += block_vector(g.c_off, k, x[g.c_cols[k]], real)
    return out


@ti.func
def cheb_startc(cfg: ti.template(), g: ti.template(), begin, end, first: ti.template(), inv_theta,
                serial: ti.template()):
    """A coarse level's start of smoothing (as ``cheb_start0``), nodes [begin, end); input ``g.c_b``."""
    it = ti.cast(inv_theta, cfg.real)
    loops(serial)
    for node in range(begin, end):
        res = g.c_b[node]
        if ti.static(first):
            g.c_x[node] = ti.Vector.zero(cfg.real, BS)
        else:
            res = g.c_b[node] - coarse_row(g, node, g.c_x, cfg.real)
        g.c_res[node] = res
        g.c_d[node] = it * block_vector(g.c_dinv, node, res, cfg.real)


@ti.func
def cheb_stepc(cfg: ti.template(), g: ti.template(), src: ti.template(), dst: ti.template(), begin, end,
               c1, c2, last: ti.template(), serial: ti.template()):
    """A coarse level's Chebyshev step (as ``cheb_step0``), nodes [begin, end)."""
    a = ti.cast(c1, cfg.real)
    b = ti.cast(c2, cfg.real)
    loops(serial)
    for node in range(begin, end):
        d = src[node]
        g.c_x[node] = g.c_x[node] + d
        res = g.c_res[node] - coarse_row(g, node, src, cfg.real)
        g.c_res[node] = res
        if ti.static(not last):
            dst[node] = a * d + b * block_vector(g.c_dinv, node, res, cfg.real)


@ti.func
def smoothc(cfg: ti.template(), g: ti.template(), begin, end, first: ti.template(), coef,
            degree: ti.template(), serial: ti.template()):
    """A coarse level's smoothing (as ``smooth0``), directions in ``g.c_d`` and ``g.c_d2``."""
    cheb_startc(cfg, g, begin, end, first, coef[0], serial)
    for k in ti.static(range(degree)):
        cheb_stepc(cfg, g, ti.static((g.c_d, g.c_d2)[k % 2]), ti.static((g.c_d2, g.c_d)[k % 2]), begin, end,
                   coef[1 + 2 * k], coef[2 + 2 * k], k == degree - 1, serial)


@ti.kernel
def downc(cfg: ti.template(), g: ti.template(), begin: ti.i32, end: ti.i32, first: ti.template(), coef: COEF,
          degree: ti.template(), next_begin: ti.i32, next_end: ti.i32, serial: ti.template()):
    """A coarse level's pre-smoothing, nodes [begin, end): from x = 0 (``first``), else
    from the current ``c_x``; then the next level's c_b = P^T res, its nodes
    [next_begin, next_end) (global indices)."""
    smoothc(cfg, g, begin, end, first, coef, degree, serial)
    loops(serial)
    for node in range(next_begin, next_end):
        acc = ti.Vector.zero(cfg.real, BS)
        for k in range(g.ptc_rows[node], g.ptc_rows[node + 1]):
            acc += block_t_vector(g.pc, g.ptc_block[k], g.c_res[g.ptc_fine[k]], cfg.real)
        g.c_b[node] = acc


@ti.kernel
def upc(cfg: ti.template(), g: ti.template(), begin: ti.i32, end: ti.i32, coef: COEF, degree: ti.template(),
        serial: ti.template()):
    """x += P e on a coarse level, nodes [begin, end) (global; e: the next level's c_x),
    then its post-smoothing."""
    loops(serial)
    for node in range(begin, end):
        acc = ti.Vector.zero(cfg.real, BS)
        for k in range(g.pc_rows[node], g.pc_rows[node + 1]):
            acc += block_vector(g.pc, k, g.c_x[g.pc_cols[k]], cfg.real)
        g.c_x[node] = g.c_x[node] + acc
    smoothc(cfg, g, begin, end, False, coef, degree, serial)


@ti.kernel
def solve_coarsest(cfg: ti.template(), g: ti.template(), base: ti.i32, nodes: ti.i32):
    """c_x = A^-1 c_b on the coarsest level by the Cholesky factor in ``g.chol``."""
    size = nodes * BS
    ti.loop_config(serialize=True)
    for _ in range(1):
        for r in range(size):  # L y = b
            s = g.c_b[base + r // BS][r % BS]
            for k in range(r):
                s -= g.chol[r * size + k] * g.chol_y[k]
            g.chol_y[r] = s / g.chol[r * size + r]
        for step in range(size):  # L^T x = y
            r = size - 1 - step
            s = g.chol_y[r]
            for k in range(r + 1, size):
                s -= g.chol[k * size + r] * g.chol_y[k]
            g.chol_y[r] = s / g.chol[r * size + r]
        for r in range(size):
            g.c_x[base + r // BS][r % BS] = g.chol_y[r]


# ------------------------------------------------------------- mixed precision


@ti.kernel
def narrow(dev: ti.template(), cfg: ti.template(), fine: ti.template(), g: ti.template(), fine_g: ti.template(),
           coarse: ti.template(), serial: ti.template()):
    """After the setup: ``fine``, the f32 copy of what level 0's part of the cycle reads
    (``massspring.solvers.multigrid_f32``), from the run's fields (``cfg``: the run's
    switches): d_i (kg), the coefficients (n, a, b) in adjacency order (and the lagged
    (m, c)), the contact filters S_i, D^-1 (1/kg); with ``coarse``, P0 into ``fine_g``."""
    loops(serial)
    for i in range(dev.size[0]):
        fine.diag[i] = ti.cast(dev.diag[i], ti.f32)
        fine.minv[i] = ti.cast(dev.minv[i], ti.f32)
        if ti.static(cfg.contact_filter):
            fine.cfilter[i] = ti.cast(dev.cfilter[i], ti.f32)
        if ti.static(cfg.has_springs):
            for e in range(dev.offsets[i], dev.offsets[i + 1]):
                fine.coef[e] = ti.cast(dev.coef[e], ti.f32)
                if ti.static(cfg.lagged):
                    fine.lag_coef[e] = ti.cast(dev.lag_coef[e], ti.f32)
        if ti.static(coarse):
            for k in range(g.p0_rows[i], g.p0_rows[i + 1]):
                fine_g.p0[k] = ti.cast(g.p0[k], ti.f32)
