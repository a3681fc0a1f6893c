"""The self-collision pass run backwards in a gradient's run (``massspring.gradients``
asks the pass for it: ``SelfCollisionPass.adjoint``): the steps in which the pass acted
are recorded as the run goes forward, and each is replayed backwards (``adjoint.Replay``)
before the integrator's adjoint of that step."""

from __future__ import annotations

import numpy as np

from massspring.kernels import state as state_kernels
from massspring.passes.base import keep_in_history
from massspring.passes.self_collision.adjoint import Record, Replay, ReplayError
from massspring.passes.self_collision.penalty_adjoint import SolvePairs, penalty_adjoint
from massspring.support.errors import SelfCollisionGradientError


class PassSteps:
    """The steps of a gradient's run in which the self-collision pass acted (``Pass.watch``
    hands them in): the ``Record`` of each step from ``start``'s on, run backwards by the
    pass's ``Replay`` (``massspring.passes.self_collision.adjoint``), and dL/d(the repulsion
    stiffness) so far (``k_r``). With the linearised implicit step (``penalty``), also the
    pairs its solve held in each step (``SolvePairs``), restored for the step's adjoint
    solve, and their share of its gradient (``massspring.passes.self_collision.penalty_adjoint``)."""

    def __init__(self, sim, adj, guard):
        self.sim, self.adj = sim, adj
        dev = sim.stepper.dev
        self.n, self.stride = sim.model.n_particles, int(adj.stride[None])
        self.free = dev.read("free") != 0 if sim.stepper.cfg.fixed else np.ones(self.n, bool)
        self.thickness, friction, self.repulsion = guard.parameters
        self.penalty = sim.stepper.cfg.self_pairs
        self.masses, self.friction = dev.read("mass"), friction
        self.records, self.solves, self.first, self.k_r = {}, {}, 0, 0.0
        self.sizes = {}  # step -> its size (s): an error-controlled or ``dts`` run's vary
        self.loaded = False  # the step whose solve's pairs the device holds (None: none; False: unknown)
        guard.watch(self, self.solve_pairs if self.penalty else None)

    def start(self, first):
        """Keep the records of step ``first`` on (those before are dropped)."""
        self.records, self.solves, self.sizes, self.first, self.loaded = {}, {}, {}, first, False

    def __call__(self, state, idx, w, kind, rounds):
        """A step in which the pass acted (``Pass.watch``): ``state`` as it left it, its
        listed pairs and the round each was set to bound its particles. An integrator that
        stored the step's state in the history before the pass (``records_history``) gets
        it replaced by the pass's; the others keep it after the step."""
        k, integrator = self.sim.steps, self.sim.stepper
        keep_in_history(integrator, state, self.n, k)
        if k >= self.first:
            dev = integrator.dev
            order = np.lexsort(idx.T[::-1])  # by their particles (the list's order depends on the threads')
            self.records[k] = Record(dev.read("sc_end"), dev.read("sc_vend"), idx[order], w[order], kind[order],
                                     rounds[order])
            self.sizes[k] = integrator.dt

    def solve_pairs(self):
        """A step whose implicit solve holds pairs, as it begins (``Pass.watch``)."""
        k = self.sim.steps
        if k >= self.first:
            self.solves[k] = SolvePairs.read(self.sim.stepper.dev, self.n)
            self.sizes[k] = self.sim.stepper.dt

    def any_in(self, low, high) -> bool:
        """Whether a step from ``low`` to ``high`` has a record."""
        return any(low <= k <= high for k in (*self.records, *self.solves))

    def before(self, k, slot):
        """Before step k's adjoint (kept at ``slot``): with the linearised implicit step,
        the solve's pairs of step k restored; if the pass acted in it, dL/d(the state the
        pass left) in ``adj.lx``, ``adj.lv`` turned into dL/d(the step's own), which goes to
        the history at ``slot + 1`` for the integrator's adjoint. Returns what ``after``
        needs (None: nothing)."""
        pairs = self.solves.get(k)
        if self.penalty and self.loaded != (k if pairs is not None else None):
            if pairs is None:
                SolvePairs.clear(self.sim.stepper.dev, self.n)
            else:
                pairs.write(self.sim.stepper.dev)
            self.loaded = k if pairs is not None else None
        record = self.records.get(k)
        if record is None:
            return None if pairs is None else (None, pairs, slot, k)
        n, adj = self.n, self.adj
        xs, vs = np.empty((2, n, 3)), np.empty((2, n, 3))
        state_kernels.read_states(adj.hx, adj.hv, np.array([slot, slot + 1], dtype=np.int32), xs, vs, n, self.stride)
        try:
            replay = Replay(self.masses, self.free, self.sizes[k], self.thickness, self.friction, self.repulsion,
                            penalty=self.penalty)
            shares = replay.backward(record, xs[0], xs[1], vs[1], adj.read("lx", n), adj.read("lv", n))
        except ReplayError as exc:
            raise SelfCollisionGradientError(k, self.sim.integrator, str(exc)) from None
        state_kernels.load_vectors(adj.lx, shares[0])
        state_kernels.load_vectors(adj.lv, shares[1])
        state_kernels.write_state(adj.hx, adj.hv, record.x, record.v, n, slot + 1, self.stride)
        return shares[2:], pairs, slot, k

    def after(self, acted, wants):
        """After the step's adjoint: ``before``'s share of dL/dx0, of the masses' and the
        repulsion stiffness's gradients added, and the solve's pairs' shares."""
        shares, pairs, slot, k = acted
        n, adj = self.n, self.adj
        lx = adj.read("lx", n)
        if shares is not None:
            gx0, gm, gk = shares
            lx += gx0
            if wants.masses:
                state_kernels.load_reals(adj.gm, adj.read("gm", n) + gm, False)
            self.k_r += gk
        if pairs is not None:
            x, _ = self._row(adj.hx, adj.hv, slot)
            _, v = self._row(adj.hw, adj.hw, slot) if wants.friction else self._row(adj.hx, adj.hv, slot + 1)
            try:
                gx, gk, gpin = penalty_adjoint(pairs, x, v, adj.read("w", n), self.free, self.sizes[k],
                                               self.thickness, self.repulsion)
            except ReplayError as exc:
                raise SelfCollisionGradientError(k, self.sim.integrator, str(exc)) from None
            lx += gx
            self.k_r += gk
            if wants.pins:
                state_kernels.load_vectors(adj.gp, adj.read("gp", n) + gpin)
        state_kernels.load_vectors(adj.lx, lx)

    def _row(self, xs, vs, slot):
        """Slot ``slot`` of history fields ``xs``, ``vs``: (n, 3) each (with friction, ``adj.hw``
        holds the solve's v' before friction changed it)."""
        x, v = np.empty((1, self.n, 3)), np.empty((1, self.n, 3))
        state_kernels.read_states(xs, vs, np.array([slot], dtype=np.int32), x, v, self.n, self.stride)
        return x[0], v[0]

    def add_gradients(self, grads):
        """Add what the pass's own parameters take to ``grads`` (name -> gradient, the
        user's numbering): dL/dk_r to "stiffness" (the springs' gradient) where
        the repulsion stiffness is the model's median spring stiffness (``SelfCollision``):
        to the median spring, shared equally among springs of the median's value (and half
        to each middle value of an even count)."""
        model = self.sim.model
        if "stiffness" not in grads or model.self_collision.stiffness is not None or self.k_r == 0.0:
            return
        stiffness = grads["stiffness"]
        values = model.stiffness[model.stiffness > 0]
        middle = np.sort(values)[[(len(values) - 1) // 2, len(values) // 2]]
        for value in middle:
            tied = model.stiffness == value
            stiffness[tied] += 0.5 * self.k_r / tied.sum()
