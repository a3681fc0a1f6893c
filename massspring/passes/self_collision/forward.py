"""The self-collision pass: what a step of a model with ``SelfCollision`` runs after its
integrator (``kernels/self_collision.py``), its fields, pair lists and restart state;
its adjoint is ``adjoint.py`` beside it (the implicit solve's pair term's,
``penalty_adjoint.py``)."""

from __future__ import annotations

import math

import numpy as np

from massspring.model.self_collision import mesh_edges
from massspring.passes.base import Pass

PAIRS_PER_PARTICLE = 8  # the pair list's first capacity per particle; a pass that finds more grows it
# The smallest pair list (3.7 MB): small meshes, whose pairs can outnumber 8 a particle where they
# fold, never grow it, so they compile the pass's kernels for one list.
PAIR_FLOOR = 65536
PAIR_BYTES = 16 + 4 * 8 + 4 + 4  # a listed pair: 4 particles, 4 weights (f64), its kind, its bound
# Bytes per particle of the pass's fields (``declare``), for ``memory.run_bytes``: start, anchor, free,
# end, end velocity, scale, impulses, hits, hash items (24 + 24 + 8 + 24 + 24 + 8 + 24 + 4 + 4); about
# 2 triangles (12 B) and 3 edges (8 + 4 B each, two hash tables of 8 B per slot, 2 slots per edge); the
# pair list's first capacity.
PASS_BYTES = 144 + 2 * 12 + 3 * (12 + 2 * 2 * 8) + PAIRS_PER_PARTICLE * PAIR_BYTES
CARRIED = {"sc_anchor": (np.float64, (3,)), "sc_free": (np.float64, ())}  # what a restart needs of the pass


def declare(layout, model):
    """Declare the fields of ``kernels/self_collision.py`` for ``model`` in ``layout`` (a
    ``device.Layout``): its triangles and edges (capacity classes like the springs'), the
    step's start positions, bounds, impulses and two hash tables of twice the edge capacity."""
    import taichi as ti

    from massspring.device import capacity

    tris = model.triangles.astype(np.int32)
    edges = mesh_edges(model.triangles).astype(np.int32)
    tri_cap, edge_cap = capacity(len(tris), 8192), capacity(len(edges), 12288)
    size = 2 * edge_cap  # the tables' capacity; the hash uses 2 slots per edge (sc_count[2])
    layout.vectors("sc_tris", ti.i32, tri_cap, values=tris)
    layout.vectors("sc_edges", ti.i32, edge_cap, values=edges, k=2)
    layout.add("sc_count", ti.i32, 3, values=np.array([len(tris), len(edges), max(2 * len(edges), 16)]))
    layout.vectors("sc_start", layout.real)
    layout.vectors("sc_anchor", layout.real)
    layout.add("sc_free", layout.real, "particle")
    layout.vectors("sc_end", layout.real)
    layout.vectors("sc_vend", layout.real)
    layout.add("sc_scale", layout.real, "particle")
    layout.vectors("sc_dv", ti.i64)
    layout.add("sc_hits", ti.i32, "particle")
    for table, items in (("v", "particle"), ("e", edge_cap)):
        layout.add(f"sc_{table}cell", ti.i32, size)
        layout.add(f"sc_{table}first", ti.i32, size + 1)
        layout.add(f"sc_{table}item", ti.i32, items)
    layout.add("sc_box", ti.f64, 10)
    layout.add("sc_tally", ti.i32, 5)


def pair_list(pairs, real):
    """A pair list for at least ``pairs`` pairs, at least ``PAIR_FLOOR`` (a capacity class,
    so lists are pooled and their kernels compiled once per class): a bundle of ``pidx`` (4 particles), ``pw`` (4
    weights), ``pkind`` (1: edge-edge, -1: point-triangle) and ``pbound`` (how the pass
    bounds its particles, ``kernels/self_collision.py``). ValueError if it would not
    fit in memory."""
    import taichi as ti

    from massspring.device import Layout, capacity

    cap = capacity(pairs, PAIR_FLOOR)
    layout = Layout(0, 0, real)
    layout.vectors("pidx", ti.i32, cap, k=4)
    layout.vectors("pw", real, cap, k=4)
    layout.add("pkind", ti.i32, cap)
    layout.add("pbound", ti.i32, cap)
    return layout.allocate(f"self-collision: a pair list of {cap:,} pairs ({pairs:,} within reach)")


SOLVE_PAIRS_PER_PARTICLE = 16  # capacity of the implicit solve's pairs per particle (``declare_solve``)
PAIR_RECORD_BYTES = 4 * 4 + 4 * 8 + 4 + 4  # a listed pair in a gradient's Record: idx, w, kind, rounds
SOLVE_PAIR_RECORD_BYTES = 4 * 4 + 4 * 8 + 5 * 8 + 4 * 4  # a solve's pair in SolvePairs: idx, w, nf, 4 entries
# Bytes per particle of ``declare_solve``: first, fill, friction; per pair 4 particles, 4 weights,
# 5 coefficients, 4 entries.
SOLVE_BYTES = 4 + 4 + 32 + SOLVE_PAIRS_PER_PARTICLE * (16 + 4 * 8 + 5 * 8 + 4 * 4)


def declare_solve(layout, model):
    """Declare the fields of ``kernels/pair_penalty.py`` for ``model`` in ``layout``: its
    thickness and stiffness, the pairs in the solve and each particle's entries."""
    import taichi as ti

    sc = model.self_collision
    n = layout.counts["particle"]
    cap = SOLVE_PAIRS_PER_PARTICLE * n
    layout.add("sp_param", layout.real, 2, values=np.array([sc.thickness, sc.repulsion_stiffness(model)]))
    layout.add("sp_count", ti.i32, 2)
    layout.vectors("sp_idx", ti.i32, cap, k=4)
    layout.vectors("sp_w", layout.real, cap, k=4)
    layout.vectors("sp_nf", layout.real, cap, k=5)
    layout.add("sp_first", ti.i32, n + 1)
    layout.add("sp_fill", ti.i32, "particle")
    layout.add("sp_entry", ti.i32, 4 * cap)
    layout.vectors("sp_friction", ti.i64, k=4)


class SelfCollisionPass(Pass):
    """The self-collision pass of one simulation around each step of its integrator
    (``kernels/self_collision.py``; the pass protocol: ``massspring.passes.base``):
    ``begin(state)`` before the step, ``end(state, t)`` after it; steps of ``dt`` (s); ``serial``: in serial loops, as the integrator runs
    (``Settings.loops``). ``end`` runs the full pass only when a particle left its free
    distance of its anchor (step 0 of the kernels' docstring). ``last``: the last full
    pass's (pairs within reach, pairs repelled, particles held back, the largest
    displacement in m, the smallest distance of a pair in m, the pair list's capacity,
    pairs set to bound their own particles);
    ``passes`` and ``steps``: full passes and steps so far; ``left_out``: pairs within
    the thickness the last pass left out of the implicit solve (beyond its capacity);
    ``grown``: times the pair list grew (a pass that finds more pairs than it holds is undone and run again with
    a larger one, so what a step does never depends on the list's size)."""

    name = "self-collision"
    term = "self-collision"
    stats_property = "self_collision_stats"
    carried = CARRIED
    differentiable = True

    @staticmethod
    def wanted(model) -> bool:
        return model.has_self_collision

    @staticmethod
    def bytes(model) -> tuple:
        return (PASS_BYTES, 0)

    declare = staticmethod(declare)

    @staticmethod
    def gradient_bytes(model, checkpoint, integrator) -> int:
        """Host bytes of its run backwards (``backward.PassSteps``): in each of a stretch's
        ``checkpoint`` steps, a ``Record`` (the candidate state, 48 bytes a particle, and
        56 a listed pair, counted at the pair list's first capacity, ``PAIRS_PER_PARTICLE``
        a particle: a list that grew holds more) and, with the pairs in the linearised
        step's solve, its ``SolvePairs`` (104 bytes a pair at that solve's capacity, 4 a
        particle)."""
        from massspring.integrators import INTEGRATORS

        n = model.n_particles
        step = n * (48 + PAIR_RECORD_BYTES * PAIRS_PER_PARTICLE)
        if getattr(INTEGRATORS[integrator], "pairs_in_solve", lambda _: False)(model):
            step += n * (4 + SOLVE_PAIR_RECORD_BYTES * SOLVE_PAIRS_PER_PARTICLE)
        return checkpoint * step

    def __init__(self, dev, cfg, model, serial, dt):
        super().__init__(dev, cfg, model, serial, dt)
        sc = model.self_collision
        self.parameters = (sc.thickness, sc.friction, sc.repulsion_stiffness(model))
        self.list = pair_list(PAIRS_PER_PARTICLE * model.n_particles, cfg.real)
        self.last = (0, 0, 0, 0.0, math.inf, self.capacity, 0)
        self.passes = self.steps = self.grown = self.left_out = 0
        self.fresh = True  # x0 and the anchors are not set yet
        self.pairs_dt = None  # the step size (s) the solve's pairs in the bundle were collected for
        self.recorder = None  # a gradient's run: the steps the pass acted in go to this (``watch``)
        self.solve_recorder = None  # ... and the steps whose implicit solve holds pairs to this
        self._moved = None  # an error-controlled run: the particles the last step's pass acted on (``moved``)

    @property
    def capacity(self) -> int:
        """Pairs the pair list holds."""
        return self.list.pidx.shape[0]

    def _grow(self, found):
        """A list for twice ``found`` pairs in place of the current one, which is kept if
        the new one does not fit in memory (ValueError naming the pair list)."""
        from massspring.device import POOL

        grown = pair_list(2 * found, self.cfg.real)  # each size compiles the pass's kernels once: few sizes
        POOL.give(self.list)
        self.list = grown
        self.grown += 1

    def _list(self, state):
        """List the state's pairs, and the implicit solve's from them."""
        from massspring.kernels.self_collision import self_collision_list

        found = self_collision_list(self.dev, self.cfg, self.list, state, self.parameters[0], self.serial)
        while found > self.capacity:
            self._grow(found)
            found = self_collision_list(self.dev, self.cfg, self.list, state, self.parameters[0], self.serial)
        self._solve_pairs(state)

    def _solve_pairs(self, state):
        """The implicit solve's pairs from the list (``cfg.self_pairs``)."""
        from massspring.kernels.self_collision import self_collision_solve_pairs

        if self.cfg.self_pairs:
            self_collision_solve_pairs(self.dev, self.cfg, self.list, state, self.dt, self.serial)
            self.pairs_dt = self.dt

    def begin(self, state):
        if self.fresh:
            from massspring.kernels.self_collision import self_collision_begin

            if self.cfg.self_pairs:  # the solve's pairs come from the list
                self._list(state)
            self_collision_begin(self.dev, state, True, self.serial)
            self.fresh = False
        elif self.cfg.self_pairs and self.pairs_dt != self.dt:  # penalties of h^2 k: collected for another step size
            self._solve_pairs(state)
        if self.solve_recorder is not None and int(self.dev.sp_count[0]) > 0:
            self.solve_recorder()

    def end(self, state, t):
        from massspring.kernels.self_collision import (BOUND_ROUNDS, OWN, self_collision_bound,
                                                       self_collision_check, self_collision_detect,
                                                       self_collision_restore)

        self.steps += 1
        watching = self._moved is not None
        if watching:
            self._moved = np.empty(0, np.int64)
        if self_collision_check(self.dev, state, self.serial) == 0:
            return
        self.passes += 1
        out = self_collision_detect(self.dev, self.cfg, self.list, state, self.dt, *self.parameters, self.serial)
        while not out[5]:
            self_collision_restore(self.dev, state, self.serial)
            self._grow(int(out[0]))
            out = self_collision_detect(self.dev, self.cfg, self.list, state, self.dt, *self.parameters, self.serial)
        recording = self.recorder is not None
        acted = recording and int(out[1]) > 0  # pairs repelled
        count = int(out[0])
        set_in = np.full(count if recording else 0, -1, np.int32)  # the round each pair was set in (-1: never)
        thickness, rounds, marked, bounded = self.parameters[0], 0, 1, 0
        while marked:  # each round sets more pairs to bound their own particles (step 3 of the kernels)
            marked, held = self_collision_bound(self.dev, self.cfg, self.list, state, self.dt, thickness,
                                                int(rounds == 0), int(rounds >= BOUND_ROUNDS), self.serial)
            bounded += int(marked)
            if recording and marked:  # pairs pushed, particles held back
                set_in[(self.pairs(count)[3] == OWN) & (set_in < 0)] = rounds
                acted = True
            rounds += 1
        moved = watching and (int(out[1]) > 0 or bounded)
        if acted or moved:
            pairs = self.pairs(count)
            if acted:
                self.recorder(state, *pairs[:3], set_in)
            if moved:
                self._moved = np.unique(pairs[0][pairs[0] >= 0])
        self._solve_pairs(state)
        self.last = (int(out[0]), int(out[1]), int(held), float(out[3]), float(out[4]), self.capacity, bounded)
        if self.cfg.self_pairs:
            self.left_out = int(self.dev.sp_count[1])

    def pairs(self, count):
        """The pair list's first ``count`` pairs: particles (count, 4) int32, weights
        (count, 4) float64, kinds and bounds (count,) int32 (``pidx``, ``pw``, ``pkind``,
        ``pbound`` of ``kernels/self_collision.py``)."""
        from massspring.kernels.self_collision import self_collision_read_pairs

        out = (np.empty((count, 4), np.int32), np.empty((count, 4)), np.empty(count, np.int32),
               np.empty(count, np.int32))
        if count:
            self_collision_read_pairs(self.list, count, *out)
        return out

    def moved(self):
        """The particles of the listed pairs, if the last step's pass repelled a pair or
        bounded one (``Pass.moved``); empty if it did neither."""
        return self._moved

    def watch_moves(self):
        self._moved = np.empty(0, np.int64)

    def watch(self, recorder, solve_recorder=None):
        """From now on (a gradient's run: ``massspring.gradients``), a step in which the
        pass acted calls ``recorder(state, idx, w, kind, rounds)`` at its end: its listed
        pairs (``pairs``) and the round of step 3 in which each was set to bound its own
        particles (int32 (pairs,), -1: never); with a ``solve_recorder``, a step whose
        implicit solve holds pairs calls ``solve_recorder()`` as it begins (the pairs in
        the device's ``sp_*`` fields)."""
        self.recorder, self.solve_recorder = recorder, solve_recorder

    def release(self):
        """Hand the pair list back to the pool."""
        from massspring.device import POOL

        if self.list is not None:
            POOL.give(self.list)
            self.list = None

    def stats(self) -> dict:
        """"steps", "passes" (steps that ran the full pass), "grown" (times its pair list
        grew) and "capacity" (pairs the list holds); of the last full pass: "pairs"
        (listed), "repelled" (closer than the thickness), "bounded" (closing too fast: set
        to bound their own particles), "held" (particles held back), "displacement"
        (largest, m), "closest" (smallest pair distance, m) and "left_out" (pairs within
        the thickness left out of the implicit solve because they passed its capacity; 0
        if none)."""
        pairs, repelled, held, displacement, closest, capacity, bounded = self.last
        return {"steps": self.steps, "passes": self.passes, "grown": self.grown, "capacity": capacity,
                "pairs": pairs, "repelled": repelled, "bounded": bounded, "held": held,
                "displacement": displacement, "closest": closest, "left_out": self.left_out}

    def counters(self) -> dict:
        return {name: getattr(self, name) for name in ("last", "passes", "steps", "grown", "left_out", "fresh")}

    def adjoint(self, sim, adj):
        """A gradient's record and replay of the steps this pass acted in (``backward.PassSteps``)."""
        from massspring.passes.self_collision.backward import PassSteps

        return PassSteps(sim, adj, self)

    def carried_state(self) -> dict:
        """The anchors (n, 3) and free distances (n,) in m, for a restart."""
        return {name: self.dev.read(name).astype(dtype) for name, (dtype, _) in CARRIED.items()}

    def load(self, state, carried=None):
        """Continue from ``state`` (just set by a restart) with ``carried`` (``carried()``
        of the saved run, checked by the caller; None: the next step runs the full pass)."""
        from massspring.kernels import state as state_kernels
        from massspring.kernels.self_collision import self_collision_begin

        self.fresh = carried is None
        if carried is not None:
            if self.cfg.self_pairs:
                self._list(state)
            state_kernels.load_vectors(self.dev.sc_anchor, carried["sc_anchor"].astype(np.float64))
            state_kernels.load_reals(self.dev.sc_free, carried["sc_free"].astype(np.float64), False)
            self_collision_begin(self.dev, state, False, self.serial)
