"""The adjoint of the self-collision pass (repulsion and displacement bounds), with its
active set frozen.

The pass (``kernels/self_collision.py``) turns the state an integrator's step left,
positions x and velocities v (n, 3), into x', v', given the step's start positions x0
(n, 3), the masses (n,) and dt = h (s). Each listed pair of particles ``idx`` (4,) has
signed weights w (4,) of its closest points at x0 (sum_k w_k x0_k = g, its distance
L = |g|, normal n = g / L), its particles' sides s_k (+1: A, -1: B) and the distance each
may move towards the other side, a = GAMMA max(L - OFFSET thickness, 0).

Step 2, repulsion, of each pair closer than the thickness:

    r = sum_k w_k (x_k - x0_k) / h, vn = r . n, S = sum_k w_k^2 / m_k (free k),
    dvn = min(0.1 (thickness - L) / h - vn, max(-vn, 0) + h k_r (thickness - L) S),
    t = r - vn n, c = dvn n - min(mu dvn, |t|) t / |t|, dv_k = w_k c / (S m_k) (free k).

Step 3, displacement bounds, in rounds: the pairs set to bound their own particles in
the first round push each particle k that moves towards the other side by more than a,
by toward_k = -s_k n . (x_k - x0_k), back by (toward_k - a) along s_k n, as the velocity
change dv_k = (toward_k - a) s_k n / h; then in every round a particle that still moves
towards the other side of a pair set in that round by more than a + BOUND_SLACK
thickness has its displacement scaled by sigma = a / toward_k, the smallest over such
pairs: x' = x0 + sigma (x - x0), v' = sigma (x - x0) / h.

A step's velocity changes (repulsion, then the first round's push) are averaged per
particle over the pairs that touch it (du), then x' = x + h du, v' = v + du, each
coordinate clipped to the particle's path box (from x0 to the step's candidate x) grown
by thickness / 2 (v' changed with x'). The weights are the closest points' on the region
of the two primitives where they lie (a triangle's face, edge or corner; each edge's
inside or end), where they are smooth functions of x0: the least-squares solution over
the region's free parameters.

Frozen active set: which pairs repel, the min and max above, sticking or sliding, the
round in which each pair is set to bound its particles, which particles are pushed,
which pair sets each scale, which coordinates are clipped and each closest point's
region are those of the step as taken; within them the pass is smooth and this is its
exact Jacobian, transposed. Where one of them switches, a derivative is not defined and
none is claimed.

Each pair's Jacobian of its velocity changes (12 values) in its inputs (x0 and x of its
particles, for the repulsion also their masses and k_r), and each scale's in its pair's
x0 and its particle's x, is taken by complex-step differentiation of the formulas above
(f(z + i e) imaginary part / e with e = 1e-30: exact to round-off, no difference
quotient), vectorised over the pairs; the averaging, the clip and the scaling are
linear in those and done by hand. Host arrays (numpy), a step at a time:
``Replay.backward``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from massspring.kernels.self_collision import (BOUND_SLACK, DV_LIMIT, EDGE_EDGE, GAMMA, OFFSET, POINT_TRIANGLE, SCALE,
                                               SEPARATION)

STEP = 1e-30  # the complex step
REPLAY_TOLERANCE = 1e-9  # of the thickness (m) and the thickness a step (m/s): the replay against the pass
NEAR = 1e-9  # of the thickness: the pairs the replay's repulsion looks at are this near it, to round-off


@dataclass(frozen=True)
class Record:
    """What the backward pass needs of a step in which the pass acted, besides the states
    before and after it: the step's candidate state ``x``, ``v`` (n, 3; before the pass),
    the pass's listed pairs ``idx`` (P, 4) int, ``w`` (P, 4) (signed weights at x0),
    ``kind`` (P,) (1: edge-edge, -1: point-triangle) and ``rounds`` (P,) int: the round of
    step 3 in which each pair was set to bound its own particles (-1: never)."""

    x: np.ndarray
    v: np.ndarray
    idx: np.ndarray
    w: np.ndarray
    kind: np.ndarray
    rounds: np.ndarray


class ReplayError(RuntimeError):
    """The pass replayed on the host does not give the pass's x', v' (by ``error`` m), or
    meets a pair it cannot run backwards (``why``)."""

    def __init__(self, error=np.nan, why=None):
        super().__init__(why or f"the self-collision pass replayed on the host differs from the pass by {error:.3g} m")
        self.error = float(error)


def fixed_point(values):
    """``values`` as the pass sums them (``kernels/self_collision.py``'s ``fixed_point``):
    clipped to +-DV_LIMIT and rounded to multiples of 1 / SCALE, so that the replay's sums
    are the pass's (the rounding's derivative is taken as 1)."""
    return np.round(np.clip(values, -DV_LIMIT, DV_LIMIT) * SCALE) / SCALE


def regions(w, kind):
    """The closest points' regions from their weights ((P, 4), signed; ``kind`` (P,)):
    ``(w0, E)``, w = w0 + E theta with theta (P, 2) the free parameters (a column of E
    zero where there are fewer). A point-triangle pair's triangle weights b = -w[1:] are
    free on their support (b > 0): a face has two parameters, an edge one, a corner none;
    an edge-edge pair's s = w[1] and t = -w[3] are free strictly inside (0, 1)."""
    p = len(w)
    w0 = np.zeros((p, 4))
    e = np.zeros((p, 4, 2))
    edge = kind == 1
    # point-triangle: b = e_j0 + sum_c theta_c (e_jc - e_j0) on the support S = (j0, j1, j2)
    b = -w[:, 1:]
    support = b > 0
    order = np.argsort(~support, axis=1, kind="stable")
    count = support.sum(axis=1)
    rows = np.arange(p)
    w0[:, 0] = 1.0
    w0[rows, 1 + order[:, 0]] = -1.0
    for c in range(2):
        on = (count >= c + 2) & ~edge
        e[rows[on], 1 + order[on, 0], c] = 1.0
        e[rows[on], 1 + order[on, c + 1], c] = -1.0
    # edge-edge: (1 - s, s) = (1, 0) + s (-1, 1), (-(1 - t), -t) = (-1, 0) + t (1, -1)
    s, t = w[edge, 1], -w[edge, 3]
    free_s, free_t = (s > 0) & (s < 1), (t > 0) & (t < 1)
    w0[edge] = np.stack([np.where(free_s, 1.0, 1 - s), np.where(free_s, 0.0, s),
                         np.where(free_t, -1.0, t - 1), np.where(free_t, 0.0, -t)], axis=1)
    e[edge] = 0.0
    e[edge, 0, 0], e[edge, 1, 0] = -1.0 * free_s, 1.0 * free_s
    e[edge, 2, 1], e[edge, 3, 1] = 1.0 * free_t, -1.0 * free_t
    return w0, e


def closest(x0, w0, e):
    """(w, g, L, n): each pair's weights (P, 4) solved on their region at ``x0`` (P, 4, 3),
    gap vector g = sum_k w_k x0_k (P, 3), distance L (P,) and normal n = g / L (P, 3);
    real or complex."""
    a = np.einsum("pk,pkc->pc", w0, x0)
    bmat = np.einsum("pkj,pkc->pcj", e, x0)
    gram = np.einsum("pcj,pcl->pjl", bmat, bmat) + np.eye(2) * (~e.any(axis=1))[:, None, :]
    theta = np.linalg.solve(gram, -np.einsum("pcj,pc->pj", bmat, a)[..., None])[..., 0]
    w = w0 + np.einsum("pkj,pj->pk", e, theta)
    g = a + np.einsum("pcj,pj->pc", bmat, theta)
    length = np.sqrt(np.sum(g * g, axis=1))
    return w, g, length, g / np.where(length.real > 0, length, 1.0)[:, None]


def relative_motion(x0, x, masses, free, w0, e, h):
    """(w, L, n, r, S, vn) of each pair (module docstring, step 2): its closest points'
    weights, distance and normal at ``x0``, relative velocity r over the step, S and the
    normal speed vn; real or complex."""
    w, _, length, normal = closest(x0, w0, e)
    rel = np.einsum("pk,pkc->pc", w, x - x0) / h
    inverse = np.sum(np.where(free, w * w / masses, 0.0), axis=1)
    return w, length, normal, rel, inverse, np.sum(rel * normal, axis=1)


def repulsion_changes(x0, x, masses, k_r, free, w0, e, h, thickness, mu, branches=None):
    """Each pair's repulsion dv (P, 4, 3) by the module docstring's formulas: ``x0``,
    ``x`` (P, 4, 3), ``masses`` (P, 4) of its particles, ``k_r`` (P,) N/m, ``free`` (P, 4)
    bool, region ``w0``, ``e`` (``regions``); real or complex inputs. ``branches``: the
    frozen choices (from a real evaluation, which returns them as ``(dv, branches)``);
    pairs that do not act get dv = 0."""
    w, length, normal, rel, inverse, vn = relative_motion(x0, x, masses, free, w0, e, h)
    gap = thickness - length
    need = SEPARATION * gap / h - vn
    real = branches is None
    if real:
        branches = {"approach": vn.real < 0}
    cap = np.where(branches["approach"], -vn, 0.0) + h * k_r * gap * inverse
    if real:
        branches["need"] = need.real <= cap.real
    dvn = np.where(branches["need"], need, cap)
    tangent = rel - vn[:, None] * normal
    vt = np.sqrt(np.sum(tangent * tangent, axis=1))
    if real:
        branches.update(act=(length.real < thickness) & (length.real > 0) & (inverse.real > 0) & (dvn.real > 0),
                        moving=vt.real > 0, sliding=mu * dvn.real < vt.real)
    act, moving, sliding = branches["act"], branches["moving"], branches["moving"] & branches["sliding"]
    divisor = np.where(sliding & (vt != 0), vt, 1.0)  # (|t| at round-off: it sticks, or slides with mu = 0)
    coefficient = np.where(sliding, mu * dvn / divisor, np.where(moving, 1.0, 0.0))
    change = dvn[:, None] * normal - coefficient[:, None] * tangent
    impulse = change / np.where(act, inverse, 1.0)[:, None]
    mask = free & act[:, None]
    dv = np.where(mask[..., None], w[..., None] * impulse[:, None, :] / masses[..., None], 0.0)
    return (dv, branches) if real else dv


def penalty_friction_items(x0, x, masses, k_r, free, w0, e, h, thickness, branches=None):
    """With the linearised implicit step's pairs in its solve (``kernels/pair_penalty.py``),
    the friction of their penalty impulse: each pair's items (P, 4, 4) for its free
    particles k, (J |w_k| u_k, J |w_k|) with the impulse J = h k_r max(thickness - L -
    h vn, 0) and the velocity u_k = -w_k t / (S m_k) that stops the pair's tangential
    motion t; the pass sums them per particle (``penalty_friction_velocity``). Inputs
    and ``branches`` ("pressed": J > 0 of a pair closer than the thickness) as
    ``repulsion_changes``'s."""
    w, length, normal, rel, inverse, vn = relative_motion(x0, x, masses, free, w0, e, h)
    impulse = h * k_r * (thickness - length - h * vn)
    real = branches is None
    if real:
        branches = {"pressed": (length.real < thickness) & (length.real > 0) & (inverse.real > 0)
                    & (impulse.real > 0)}
    pressed = branches["pressed"]
    tangent = rel - vn[:, None] * normal
    weight = impulse[:, None] * np.sign(w.real) * w
    want = -w[..., None] / (np.where(pressed, inverse, 1.0)[:, None, None] * masses[..., None]) * tangent[:, None, :]
    items = np.concatenate([weight[..., None] * want, weight[..., None]], axis=2)
    items = np.where((free & pressed[:, None])[..., None], items, 0.0)
    return (items, branches) if real else items


def penalty_friction_velocity(sums, weight, masses, mu, clamped):
    """A particle's velocity change from its summed items (``penalty_friction_items``):
    ``sums`` (n, 3), ``weight`` (n,) > 0, ``masses`` (n,): u = sums / weight, scaled to the
    Coulomb bound mu weight / m where it exceeds it (``clamped`` (n,) bool, frozen)."""
    want = sums / weight[:, None]
    size = np.sqrt(np.sum(want * want, axis=1))
    limit = mu * weight / masses
    return np.where(clamped[:, None], want * (limit / np.where(clamped, size, 1.0))[:, None], want)


def sides(kind):
    """Each pair's particles' sides (P, 4): ``POINT_TRIANGLE`` or ``EDGE_EDGE``."""
    return np.where((kind == 1)[:, None], np.array(EDGE_EDGE, float), np.array(POINT_TRIANGLE, float))


def allowed_distance(length, far, thickness):
    """a = GAMMA (L - OFFSET thickness) where ``far`` (the frozen choice L > OFFSET
    thickness), else 0: how far a pair's particles may move towards the other side."""
    return GAMMA * np.where(far, length - OFFSET * thickness, 0.0)


def allowance(x0, x, kind, w0, e, thickness, far=None):
    """(toward (P, 4), a (P,), n (P, 3), far (P,), L (P,)): how far each particle of each
    pair moved towards the other side, how far it may, the pair's normal, the choice
    L > OFFSET thickness (``far``: frozen, else from this real evaluation) and its distance
    (step 3)."""
    _, _, length, normal = closest(x0, w0, e)
    toward = -sides(kind) * np.einsum("pc,pkc->pk", normal, x - x0)
    if far is None:
        far = length.real > OFFSET * thickness
    return toward, allowed_distance(length, far, thickness), normal, far, length


def push_changes(x0, x, kind, w0, e, h, thickness, branches=None):
    """Each pair's first-round push as velocity changes dv (P, 4, 3) (step 3): each
    particle that moves towards the other side by more than it may goes back to it along
    the normal; ``branches`` as ``repulsion_changes``'s: ``far`` (L > OFFSET thickness)
    and ``pushed`` (P, 4) (the caller leaves pinned particles out of it)."""
    real = branches is None
    toward, allowed, normal, far, _ = allowance(x0, x, kind, w0, e, thickness, None if real else branches["far"])
    if real:
        branches = {"far": far, "pushed": toward.real > allowed.real[:, None]}
    excess = (toward - allowed[:, None]) * sides(kind)
    dv = np.where(branches["pushed"][..., None], excess[..., None] * normal[:, None, :] / h, 0.0)
    return (dv, branches) if real else dv


def scale_of(x0, xi, kind, w0, e, k, thickness, far):
    """sigma = a / toward (P,) of particle ``k`` (P,) of each pair at position ``xi`` (P, 3)."""
    _, _, length, normal = closest(x0, w0, e)
    rows = np.arange(len(x0))
    toward = -sides(kind)[rows, k] * np.sum(normal * (xi - x0[rows, k]), axis=1)
    return allowed_distance(length, far, thickness) / toward


class Replay:
    """The pass of one model: ``masses`` (n,) kg, ``free`` (n,) bool (not pinned), dt
    ``h`` (s), ``thickness`` (m), friction ``mu``, repulsion stiffness ``k_r`` (N/m), in
    the device's particle numbering; ``rounded``: each pair's velocity changes rounded
    as the pass's fixed-point sums round them (False: exact, for differences of the
    replay itself; the pass's scales can lift that rounding, 1e-12 m, to 4e-11 m);
    ``penalty``: the pass follows a linearised implicit step whose solve held the pairs
    (``penalty_friction_items``: their friction joins the repulsion's changes)."""

    def __init__(self, masses, free, h, thickness, mu, k_r, rounded=True, penalty=False):
        self.masses, self.free = np.asarray(masses, dtype=np.float64), np.asarray(free, dtype=bool)
        self.h, self.thickness, self.mu, self.k_r = float(h), float(thickness), float(mu), float(k_r)
        self.rounded, self.penalty = rounded, penalty

    def forward(self, record, x0):
        """The pass of ``record``'s step from start positions ``x0`` (n, 3), replayed:
        ``(x', v', tape)``, ``tape`` its stages in order, what ``backward`` needs of them."""
        idx, kind, h, thickness = record.idx, record.kind, self.h, self.thickness
        w0, e = regions(record.w, kind)
        starts = x0[idx]
        gaps = np.einsum("pk,pkc->pc", record.w, starts)  # (the pairs the pass found within the thickness)
        near = np.flatnonzero(np.sum(gaps * gaps, axis=1) < (thickness * (1 + NEAR)) ** 2)
        inputs = (starts[near], record.x[idx[near]], self.masses[idx[near]], np.full(len(near), self.k_r))
        fixed = (self.free[idx[near]], w0[near], e[near], h, thickness, self.mu)
        dv, branches = repulsion_changes(*inputs, *fixed)
        if self.rounded:
            dv = fixed_point(dv)
        counted = self.free[idx[near]] & branches["act"][:, None]
        penalty = self._penalty_friction(idx[near], inputs, fixed[:-1]) if self.penalty else None
        x, v, spread = self._spread(record, x0, record.x, record.v, idx[near], dv, counted, penalty)
        tape = [dict(stage="repulsion", inputs=inputs, fixed=fixed, branches=branches, spread=spread,
                     penalty=penalty)]
        for r in range(int(record.rounds.max(initial=-1)) + 1):
            chosen = record.rounds == r
            pair = (idx[chosen], starts[chosen], kind[chosen], w0[chosen], e[chosen])
            if r == 0:
                inputs = (pair[1], x[pair[0]])
                fixed = (pair[2], pair[3], pair[4], h, thickness)
                dv, branches = push_changes(*inputs, *fixed)
                if self.rounded:
                    dv = fixed_point(dv * h) / h  # (the kernels sum the push's displacements)
                branches["pushed"] &= self.free[pair[0]]
                x, v, spread = self._spread(record, x0, x, v, pair[0], dv, branches["pushed"])
                tape.append(dict(stage="push", pair=pair, inputs=inputs, fixed=fixed, branches=branches,
                                 spread=spread))
            x_in = x
            x, v, scaled = self._scale(x0, x, v, pair)
            tape.append(dict(stage="scale", pair=pair, x=x_in, scaled=scaled))
        return x, v, tape

    def _penalty_friction(self, idx, inputs, fixed):
        """The friction of the solve's penalty impulses (``penalty_friction_items``) of the
        pairs ``idx`` (P, 4) with the repulsion's ``inputs`` and ``fixed``: per particle,
        whether it has any (``on``) and its velocity change ``du`` (n, 3)."""
        n = len(self.masses)
        items, branches = penalty_friction_items(*inputs, *fixed)
        if self.rounded:
            items = fixed_point(items)
        sums = np.zeros((n, 4))
        np.add.at(sums, idx, items)
        on = sums[:, 3] > 0
        want = sums[on, :3] / sums[on, 3, None]
        clamped = np.sqrt(np.sum(want * want, axis=1)) > self.mu * sums[on, 3] / self.masses[on]
        du = np.zeros((n, 3))
        du[on] = penalty_friction_velocity(sums[on, :3], sums[on, 3], self.masses[on], self.mu, clamped)
        return dict(inputs=inputs, fixed=fixed, branches=branches, sums=sums, on=on, clamped=clamped, du=du)

    def _spread(self, record, x0, x, v, idx, dv, counted, penalty=None):
        """x' = x + h du, v' = v + du, du the average of the pairs' ``dv`` (P, 4, 3) over
        the ``counted`` (P, 4) entries at each particle (``idx`` (P, 4)), plus ``penalty``'s
        (``_penalty_friction``), clipped to the path boxes (x0 to ``record.x``, grown by
        thickness / 2)."""
        n, h, half = len(x0), self.h, 0.5 * self.thickness
        hits = np.bincount(idx[counted], minlength=n).astype(np.float64)
        touched = (hits > 0) & self.free
        du = np.zeros((n, 3))
        np.add.at(du, idx[counted], dv[counted])
        du[touched] /= hits[touched, None]
        if penalty is not None:
            touched |= penalty["on"] & self.free
            du += penalty["du"]
        x1 = np.where(touched[:, None], x + h * du, x)
        v1 = np.where(touched[:, None], v + du, v)
        low = np.minimum(x0, record.x) - half
        high = np.maximum(x0, record.x) + half
        below, above = touched[:, None] & (x1 < low), touched[:, None] & (x1 > high)
        x2 = np.where(below, low, np.where(above, high, x1))
        v2 = v1 + (x2 - x1) / h
        from_start = np.where(below, x0 < record.x, x0 > record.x)
        return x2, v2, dict(idx=idx, counted=counted, hits=hits, touched=touched, clipped=below | above,
                            from_start=from_start)

    def _scale(self, x0, x, v, pair):
        """A round's scales (step 3) from the pairs set in it (``pair``: their particles,
        x0, kinds and regions): each particle's smallest a / toward, and which pair and
        which of its particles gave it."""
        idx, starts, kind, w0, e = pair
        n = len(x0)
        toward, allowed, _, far, length = allowance(starts, x[idx], kind, w0, e, self.thickness)
        if np.any(length == 0):
            raise ReplayError(why="a pair set to bound its particles has its primitives touching at the step's start")
        over = (toward > allowed[:, None] + BOUND_SLACK * self.thickness) & self.free[idx]
        ratio = np.where(over, allowed[:, None] / np.where(over, toward, 1.0), np.inf)
        best = np.ones(n)
        np.minimum.at(best, idx, ratio)
        scaled = best < 1
        hits = np.flatnonzero((ratio == best[idx]) & scaled[idx])  # flat (pair, k) entries giving a particle's scale
        particle = idx.reshape(-1)[hits]
        _, first = np.unique(particle, return_index=True)
        entries = hits[first]
        p_of, k_of = entries // 4, entries % 4
        s = best[:, None]
        x2 = np.where(scaled[:, None], x0 + s * (x - x0), x)
        v2 = np.where(scaled[:, None], s * (x - x0) / self.h, v)
        return x2, v2, dict(best=best, scaled=scaled, pair=p_of, k=k_of, particle=particle[first], far=far)

    def backward(self, record, x0, after_x, after_v, lx, lv):
        """dL/d(x, v) of the step's candidate state, dL/dx0, dL/d(masses) (n,) and
        dL/dk_r from dL/d(x', v') ``lx``, ``lv`` (n, 3) of the state after the pass, at
        ``x0`` (the step's start positions) with the pass's own ``after_x``, ``after_v``
        (n, 3), which the replay must give (``ReplayError`` if not)."""
        h = self.h
        x2, v2, tape = self.forward(record, x0)
        error = max(np.max(np.abs(x2 - after_x), initial=0.0), h * np.max(np.abs(v2 - after_v), initial=0.0))
        if not error <= REPLAY_TOLERANCE * self.thickness:
            raise ReplayError(error)
        gx, gv = lx.copy(), lv.copy()
        gx0, gxc, gm, gk = np.zeros_like(lx), np.zeros_like(lx), np.zeros(len(x0)), 0.0
        for stage in reversed(tape):
            if stage["stage"] == "scale":
                gx, gv, gs = self._scale_back(x0, stage["x"], stage["scaled"], gx, gv, gx0)
                if gs.size:
                    self._scale_sources(stage["pair"], stage["x"], stage["scaled"], gs, gx, gx0)
                continue
            gx, gv, gdv, gdu = self._spread_back(stage["spread"], gx, gv, gx0, gxc)
            branches, idx = stage["branches"], stage["spread"]["idx"]
            if stage["stage"] == "push":
                grad = self._pull(push_changes, stage["inputs"], stage["fixed"], branches, gdv)
                np.add.at(gx0, idx, grad[:, :12].reshape(-1, 4, 3))
                np.add.at(gx, idx, grad[:, 12:].reshape(-1, 4, 3))
                continue
            gxc += gx  # the repulsion changed the candidate state itself
            gk += self._pull_pairs(repulsion_changes, stage, np.flatnonzero(branches["act"]), idx, gdv, gx0, gxc, gm)
            if stage["penalty"] is not None:
                gk += self._penalty_friction_back(stage["penalty"], idx, gdu, gx0, gxc, gm)
        return gxc, gv, gx0, gm, gk

    def _penalty_friction_back(self, penalty, idx, gdu, gx0, gxc, gm):
        """``_penalty_friction`` backwards from dL/d(du) ``gdu`` (n, 3): its shares added to
        ``gx0``, ``gxc`` and ``gm``; returns dL/dk_r."""
        on, sums = penalty["on"], penalty["sums"]
        if not on.any():
            return 0.0
        jac = complex_jacobian(penalty_friction_velocity, (sums[on, :3], sums[on, 3], self.masses[on]),
                               (self.mu, penalty["clamped"]))
        grad = np.einsum("pc,pci->pi", gdu[on], jac)
        gsums = np.zeros((len(on), 4))
        gsums[on] = grad[:, :4]
        gm[on] += grad[:, 4]
        pressed = np.flatnonzero(penalty["branches"]["pressed"])
        return self._pull_pairs(penalty_friction_items, penalty, pressed, idx, gsums[idx], gx0, gxc, gm)

    def _pull_pairs(self, changes, stage, rows, idx, g, gx0, gxc, gm):
        """dL/d(the pairs' outputs) ``g`` (P, 4, c) of the pairs ``rows`` of a stage whose
        inputs are (x0, x, masses, k_r) of each pair (the repulsion's; ``stage``: its
        ``inputs``, ``fixed``, ``branches``) pulled back through ``changes``: the shares added
        to ``gx0``, ``gxc`` (the candidate's) and ``gm``; returns dL/dk_r."""
        if rows.size == 0:
            return 0.0
        grad = self._pull(changes, [a[rows] for a in stage["inputs"]],
                          tuple(f[rows] if isinstance(f, np.ndarray) else f for f in stage["fixed"]),
                          {key: b[rows] for key, b in stage["branches"].items()}, g[rows])
        np.add.at(gx0, idx[rows], grad[:, :12].reshape(-1, 4, 3))
        np.add.at(gxc, idx[rows], grad[:, 12:24].reshape(-1, 4, 3))
        np.add.at(gm, idx[rows], grad[:, 24:28])
        return float(grad[:, 28].sum())

    def _spread_back(self, spread, gx, gv, gx0, gxc):
        """``_spread`` backwards from dL/d(x', v'): dL/d(x, v) of the state it changed,
        dL/d(dv) (P, 4, 3), dL/d(du) (n, 3); the clipped coordinates' bounds' shares added
        to ``gx0`` and ``gxc`` (the candidate's)."""
        h, clipped, from_start = self.h, spread["clipped"], spread["from_start"]
        bound = np.where(clipped, gx + gv / h, 0.0)  # dL/d(the bound a clipped coordinate took)
        gx0 += np.where(from_start, bound, 0.0)
        gxc += np.where(from_start, 0.0, bound)
        gdu = np.where(spread["touched"][:, None] & ~clipped, h * gx + gv, 0.0)
        averaged = gdu / np.maximum(spread["hits"], 1.0)[:, None]
        gdv = np.where(spread["counted"][..., None], averaged[spread["idx"]], 0.0)
        return np.where(clipped, -gv / h, gx), gv, gdv, gdu

    def _scale_back(self, x0, x_in, scaled, gx, gv, gx0):
        """``_scale`` backwards: dL/d(x, v) before it, dL/d(sigma) of each scaled particle
        (in ``scaled["particle"]``'s order); x0's direct share added to ``gx0``."""
        h, s, on = self.h, scaled["best"][:, None], scaled["scaled"][:, None]
        through = gx + gv / h
        gs = np.sum(through * (x_in - x0), axis=1)[scaled["particle"]]
        gx0 += np.where(on, (1 - s) * gx - s * gv / h, 0.0)
        return np.where(on, s * through, gx), np.where(on, 0.0, gv), gs

    def _scale_sources(self, pair, x_in, scaled, gs, gx, gx0):
        """Each scale's share through its pair's x0 and its particle's position."""
        idx, starts, kind, w0, e = pair
        p, k, particle = scaled["pair"], scaled["k"], scaled["particle"]
        jac = complex_jacobian(scale_of, (starts[p], x_in[particle]),
                               (kind[p], w0[p], e[p], k, self.thickness, scaled["far"][p]))
        grad = gs[:, None] * jac
        np.add.at(gx0, idx[p], grad[:, :12].reshape(-1, 4, 3))
        np.add.at(gx, particle, grad[:, 12:])

    @staticmethod
    def _pull(changes, inputs, fixed, branches, gdv):
        """gdv (P, 4, 3) pulled back through ``changes(*inputs, *fixed, branches=...)``:
        (P, I), I the inputs' sizes per pair."""
        jac = complex_jacobian(changes, inputs, fixed, {"branches": branches})
        return np.einsum("pkc,pkci->pi", gdv, jac)


def complex_jacobian(function, inputs, fixed=(), keywords=None):
    """d function / d inputs by complex steps, all in one call: ``function(*inputs,
    *fixed, **keywords)`` of arrays (P, ...) per pair returns (P, ...) values; the
    result is (P, ..., I), I the inputs' sizes per pair. ``fixed`` and ``keywords``'
    arrays (a dict's values too) are per pair; the call sees I copies of every pair,
    copy j with input j moved by i e (e = ``STEP``)."""
    p = len(inputs[0])
    shapes = [a.shape[1:] for a in inputs]
    bounds = np.cumsum([0] + [int(np.prod(shape)) for shape in shapes])
    size = int(bounds[-1])
    z = np.repeat(np.concatenate([a.reshape(p, -1) for a in inputs], axis=1)[None].astype(np.complex128), size,
                  axis=0)
    z[np.arange(size), :, np.arange(size)] += 1j * STEP
    z = z.reshape(size * p, size)

    def copies(value):
        if isinstance(value, dict):
            return {key: copies(item) for key, item in value.items()}
        return np.tile(value, (size,) + (1,) * (value.ndim - 1)) if isinstance(value, np.ndarray) else value

    args = [z[:, a:b].reshape((size * p,) + shape) for a, b, shape in zip(bounds[:-1], bounds[1:], shapes)]
    out = function(*args, *(copies(value) for value in fixed), **copies(keywords or {})).imag / STEP
    return np.moveaxis(out.reshape((size, p) + out.shape[1:]), 0, -1)
