"""The self-collision repulsion's adjoint (``massspring.passes.self_collision.adjoint``) against
central differences of its own replay, on pairs of every closest-point region (a
triangle's face, edge and corner; edges crossing inside and at an end), sliding and
sticking friction, both bounds on the normal impulse, clipped coordinates and a pinned
particle; the friction of the linearised step's penalty pairs in the pass, and those
pairs' share of the step's adjoint (``massspring.passes.self_collision.penalty_adjoint``). Host arrays
only: no kernel runs. The gradients through whole runs are in ``tests/test_gradient.py``."""

import numpy as np
import pytest

from massspring.passes.self_collision.penalty_adjoint import SolvePairs, kinds, penalty_adjoint
from massspring.passes.self_collision.adjoint import Record, Replay, ReplayError, regions

H, THICKNESS = 2e-3, 0.01


def closest_weights(x, idx, kind):
    """Signed weights of a pair's closest points at x, by brute force over a fine grid of
    each primitive's parameters refined by least squares: an independent reference for
    the regions the tests set up (face, edge, corner; inside, end)."""
    p = x[idx]
    if kind == 1:
        grid = np.linspace(0, 1, 401)
        s, t = np.meshgrid(grid, grid, indexing="ij")
        gaps = (p[0] + s[..., None] * (p[1] - p[0])) - (p[2] + t[..., None] * (p[3] - p[2]))
        i, j = np.unravel_index(np.argmin(np.sum(gaps ** 2, axis=-1)), s.shape)
        return np.array([1 - grid[i], grid[i], grid[j] - 1, -grid[j]])
    grid = np.linspace(0, 1, 401)
    u, v = np.meshgrid(grid, grid, indexing="ij")
    inside = u + v <= 1
    points = p[1] + u[..., None] * (p[2] - p[1]) + v[..., None] * (p[3] - p[1])
    d2 = np.where(inside, np.sum((p[0] - points) ** 2, axis=-1), np.inf)
    i, j = np.unravel_index(np.argmin(d2), u.shape)
    return np.array([1, -(1 - grid[i] - grid[j]), -grid[i], -grid[j]])


def pairs_case():
    """Particles and pairs: a point over a triangle's face, one beyond an edge, one beyond
    a corner (all within the thickness); two edges crossing inside, and two meeting at an
    end; their candidate positions moved from x0 towards each other (0.5 m/s) and sideways (1 m/s)."""
    tri = [[0, 0, 0], [0.2, 0, 0], [0, 0.2, 0]]
    x0 = np.array(tri + [[0.05, 0.06, 0.006],  # 3: over the face
                         [0.105, 0.105, 0.004],  # 4: beyond edge 1-2 (its projection outside, past the hypotenuse)
                         [-0.004, -0.003, 0.005],  # 5: beyond corner 0
                         [0.3, 0.0, 0.0], [0.5, 0.0, 0.0],  # 6-7: an edge
                         [0.38, -0.1, 0.007], [0.42, 0.1, 0.007],  # 8-9: crossing over it inside
                         [0.7, 0.0, 0.0], [0.9, 0.0, 0.0],  # 10-11: an edge
                         [0.903, -0.1, 0.006], [0.909, 0.1, 0.006]])  # 12-13: passing beyond its end 11
    rng = np.random.default_rng(7)
    sideways = np.where(np.arange(len(x0))[:, None] >= 12, [0.0, 2e-3, 0.0], [1.4e-3, -1.4e-3, 0.0])
    x = x0 + rng.normal(0, 4e-4, x0.shape) + (sideways + [0.0, 0.0, -1e-3]) * (x0[:, 2:] > 0)
    idx = np.array([[3, 0, 1, 2], [4, 0, 1, 2], [5, 0, 1, 2], [6, 7, 8, 9], [10, 11, 12, 13]])
    kind = np.array([-1, -1, -1, 1, 1])
    w = np.array([closest_weights(x0, i, k) for i, k in zip(idx, kind)])
    return x0, x, idx, kind, w


def refine(x0, idx, kind, w):
    """The weights on their regions solved exactly (the grid's closest points are within
    1/400 of them): what the pass's narrow phase gives."""
    w0, e = regions(w, kind)
    a = np.einsum("pk,pkc->pc", w0, x0[idx])
    bmat = np.einsum("pkj,pkc->pcj", e, x0[idx])
    gram = np.einsum("pcj,pcl->pjl", bmat, bmat) + np.eye(2) * (~e.any(axis=1))[:, None, :]
    theta = np.linalg.solve(gram, -np.einsum("pcj,pc->pj", bmat, a)[..., None])[..., 0]
    return w0 + np.einsum("pkj,pj->pk", e, theta)


def test_regions_are_read_from_the_weights():
    x0, _, idx, kind, w = pairs_case()
    w0, e = regions(w, kind)
    assert [int(np.count_nonzero(e[p].any(axis=0))) for p in range(5)] == [2, 1, 0, 2, 1]
    exact = refine(x0, idx, kind, w)
    np.testing.assert_allclose(exact, w, atol=5e-3)  # the grid's answer, refined on its region
    np.testing.assert_allclose(exact.sum(axis=1), 0.0, atol=1e-15)  # p - q: weights of each side sum to +-1


@pytest.mark.parametrize("mu, k_r, pinned, clip", [
    (0.05, 1e6, False, False),  # sliding; the impulse that separates at 0.1 (thickness - d) / dt
    (50.0, 1e6, False, False),  # sticking
    (0.05, 30.0, True, False),  # the spring's bound on the impulse; a pinned corner
    (0.05, 1e6, False, True),  # coordinates clipped to the path boxes
])
def test_adjoint_matches_differences_of_the_replay(mu, k_r, pinned, clip):
    x0, x, idx, kind, w = pairs_case()
    w = refine(x0, idx, kind, w)
    n = len(x0)
    rng = np.random.default_rng(1)
    v = rng.normal(0, 0.1, (n, 3))
    masses = rng.uniform(0.5, 1.5, n)
    free = np.ones(n, bool)
    if pinned:
        free[0] = False
    if clip:  # a heavy point thrown at a still triangle: its corners pushed beyond their boxes (+- thickness / 2)
        x = x0 + rng.normal(0, 1e-5, x0.shape)  # (still corners would sit on the kink of their boxes' min(x0, x))
        x[3] += [1e-4, 2e-4, -6e-3]
        masses[3] = 50.0
        idx, kind, w = idx[:1], kind[:1], w[:1]  # the point over the face alone (the others would share the hits)
    replay = Replay(masses, free, H, THICKNESS, mu, k_r, rounded=False)
    record = Record(x, v, idx, w, kind, np.full(len(idx), -1))
    x2, v2, tape = replay.forward(record, x0)
    branches = tape[0]["branches"]
    assert branches["act"].all()
    if not clip:  # (the clipped case's pair hardly moves sideways: it sticks)
        assert (branches["sliding"].all() if mu < 1 else not branches["sliding"].any())
    assert (branches["need"].all() if k_r > 1e3 else not branches["need"].any())
    assert tape[0]["spread"]["clipped"].any() == clip
    check_against_differences(replay, record, x0, rng)


def check_against_differences(replay, record, x0, rng):
    """``replay.backward`` of ``record`` at ``x0`` against central differences of
    ``replay.forward`` in x0, the candidate state, the masses and k_r, along random
    directions, for a random dL/d(x', v'), to 1e-6 relative."""
    n = len(x0)
    x2, v2, _ = replay.forward(record, x0)
    lx, lv = rng.normal(size=(n, 3)), rng.normal(size=(n, 3))
    gx, gv, gx0, gm, gk = replay.backward(record, x0, x2, v2, lx, lv)

    def objective(x0_, x_, v_, m_, k_):
        moved = Replay(m_, replay.free, replay.h, replay.thickness, replay.mu, k_, rounded=False,
                       penalty=replay.penalty)
        out_x, out_v, _ = moved.forward(Record(x_, v_, record.idx, record.w, record.kind, record.rounds), x0_)
        return np.sum(lx * out_x) + np.sum(lv * out_v)

    directions = [rng.normal(size=(n, 3)) for _ in range(3)] + [rng.normal(size=n), 1.0]
    base = [x0, record.x, record.v, replay.masses, replay.k_r]
    for slot, (direction, grad) in enumerate(zip(directions, [gx0, gx, gv, gm, gk])):
        eps = 1e-4 * replay.k_r if slot == 4 else 1e-7  # (k_r's derivative is small: round-off at 1e-7)

        def moved(sign):
            args = list(base)
            args[slot] = base[slot] + sign * eps * direction
            return objective(*args)

        numeric = (moved(1) - moved(-1)) / (2 * eps)
        exact = float(np.sum(grad * direction))
        assert abs(exact - numeric) <= 1e-6 * max(abs(numeric), 1e-3), (slot, exact, numeric)


def test_bounds_adjoint_matches_differences_of_the_replay():
    """Step 3 after the repulsion: every particle moving 2 mm down (the edge beyond the
    other's end 3.5 mm), more than the upper ones may towards the lower side (0.45 mm
    for the point over the face, 0.9 mm for the crossing edges, 1.6 mm for the edges
    beyond the end): the first two pairs are set to bound their particles in the first
    round (pushed back along their normals: none is left to scale), the third in the
    second (its upper edge's particles scaled)."""
    x0, x, idx, kind, w = pairs_case()
    w = refine(x0, idx, kind, w)
    n = len(x0)
    rng = np.random.default_rng(2)
    x = x + [0.0, 0.0, -1e-3]  # with the upper ones' 1 mm: 2 mm down in all
    x[12:14, 2] -= 1.5e-3  # the edge beyond the other's end 3.5 mm
    replay = Replay(rng.uniform(0.5, 1.5, n), np.arange(n) != 6, H, THICKNESS, 0.05, 30.0, rounded=False)
    record = Record(x, rng.normal(0, 0.1, (n, 3)), idx, w, kind, np.array([0, -1, -1, 0, 1]))
    _, _, tape = replay.forward(record, x0)
    assert [stage["stage"] for stage in tape] == ["repulsion", "push", "scale", "scale"]
    assert tape[1]["branches"]["pushed"].any() and not tape[2]["scaled"]["scaled"].any()
    assert np.flatnonzero(tape[3]["scaled"]["scaled"]).tolist() == [12, 13]
    check_against_differences(replay, record, x0, rng)


def test_a_replay_that_differs_from_the_pass_is_refused():
    x0, x, idx, kind, w = pairs_case()
    w = refine(x0, idx, kind, w)
    n = len(x0)
    replay = Replay(np.ones(n), np.ones(n, bool), H, THICKNESS, 0.2, 1e6)
    record = Record(x, np.zeros((n, 3)), idx, w, kind, np.full(len(idx), -1))
    x2, v2, _ = replay.forward(record, x0)
    replay.backward(record, x0, x2, v2, np.zeros((n, 3)), np.zeros((n, 3)))
    with pytest.raises(ReplayError, match="differs from the pass by"):
        replay.backward(record, x0, x2 + 1e-6, v2, np.zeros((n, 3)), np.zeros((n, 3)))


@pytest.mark.parametrize("mu, pinned", [(0.05, False), (50.0, False), (0.05, True)])
def test_penalty_friction_adjoint_matches_differences_of_the_replay(mu, pinned):
    """The pass after a linearised step whose solve held the pairs adds their penalty
    impulses' friction: each particle's summed items, scaled to the Coulomb bound where
    they exceed it (mu 0.05: all of them) or not (mu 50: none), with a pinned corner."""
    x0, x, idx, kind, w = pairs_case()
    w = refine(x0, idx, kind, w)
    n = len(x0)
    rng = np.random.default_rng(4)
    free = np.ones(n, bool)
    free[0] = not pinned
    replay = Replay(rng.uniform(0.5, 1.5, n), free, H, THICKNESS, mu, 1e4, rounded=False, penalty=True)
    record = Record(x, rng.normal(0, 0.1, (n, 3)), idx, w, kind, np.full(len(idx), -1))
    _, _, tape = replay.forward(record, x0)
    penalty = tape[0]["penalty"]
    weighted = np.zeros(n, bool)
    weighted[idx[w != 0]] = True  # (particle 10, beyond whose edge's end the other passes, has weight 0)
    assert penalty["branches"]["pressed"].all() and np.array_equal(penalty["on"], weighted & free)
    assert penalty["clamped"].all() if mu < 1 else not penalty["clamped"].any()
    check_against_differences(replay, record, x0, rng)


def test_kinds_are_read_from_the_weights():
    x0, _, idx, kind, w = pairs_case()
    assert kinds(refine(x0, idx, kind, w)).tolist() == kind.tolist()


def test_penalty_pairs_adjoint_matches_differences():
    """The solve's pairs' share of a linearised step's adjoint, d(mu . A v' - mu . b)/d(x,
    k, a pin's v'), against central differences of the same products with each pair's
    closest points found again by brute force at the moved positions (an independent
    reference for their derivatives); every region, a pinned corner."""
    x, _, idx, kind, w = pairs_case()
    n, k = len(x), 3e4
    rng = np.random.default_rng(6)
    v, mu = rng.normal(0, 0.1, (n, 3)), rng.normal(size=(n, 3))
    free = np.arange(n) != 1
    mu[~free] = 0.0

    def products(x_, k_, v_):
        total = 0.0
        for pair, kd in zip(idx, kind):
            weights = refine(x_, pair[None], kd[None], closest_weights(x_, pair, kd)[None])[0]
            gap = weights @ x_[pair]
            length = np.linalg.norm(gap)
            normal = gap / length
            pulled = np.where(free[pair], weights, 0.0) @ mu[pair] @ normal
            total += H * H * k_ * pulled * (weights @ v_[pair] @ normal) - H * k_ * (THICKNESS - length) * pulled
        return total

    w = refine(x, idx, kind, w)
    gaps = np.einsum("pk,pkc->pc", w, x[idx])
    lengths = np.linalg.norm(gaps, axis=1)
    nf = np.column_stack([gaps / lengths[:, None], np.full(len(idx), H * H * k), k * (THICKNESS - lengths)])
    pairs = SolvePairs(idx.astype(np.int32), w, nf, np.zeros(n + 1, np.int32), np.zeros(0, np.int32))
    gx, gk, gpin = penalty_adjoint(pairs, x, v, mu, free, H, THICKNESS, k)
    direction = rng.normal(size=(n, 3))
    eps = 1e-7
    numeric = (products(x + eps * direction, k, v) - products(x - eps * direction, k, v)) / (2 * eps)
    assert abs(float(np.sum(gx * direction)) + numeric) <= 1e-6 * abs(numeric)
    numeric = (products(x, k * (1 + 1e-6), v) - products(x, k * (1 - 1e-6), v)) / (2e-6 * k)
    assert abs(gk + numeric) <= 1e-9 * abs(numeric)
    pin = np.zeros((n, 3))
    pin[1] = rng.normal(size=3)
    numeric = (products(x, k, v + eps * pin) - products(x, k, v - eps * pin)) / (2 * eps)
    assert abs(float(np.sum(gpin * pin)) + numeric) <= 1e-6 * abs(numeric) and abs(numeric) > 0
    assert not gpin[free].any()
