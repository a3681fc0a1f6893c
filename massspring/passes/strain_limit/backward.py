"""The strain limit run backwards in a gradient's run (``massspring.gradients`` asks the
pass for it: ``StrainLimitPass.adjoint``).

As the run goes forward, each step whose pass moved particles is recorded: the state
the step's integrator left (before the pass: x_c, v_c, (n, 3)), the time the step ended
at and its size. Before the integrator's adjoint of such a step, the pass's Jacobi
iterations are run again from x_c, v_c on the adjoint bundle's own fields
(``kernels/strain_limit.py``'s ``strain_limit_iteration``, the kernel of the pass: the
same bits), each iteration's start positions kept on the host, and the result checked
against the state the run kept after the step. Then the iterations are run backwards,
the last first (``strain_limit_adjoint``: the transpose of one iteration's Jacobian with
its active set frozen), turning dL/d(the state after the pass) into dL/d(x_c, v_c) and
adding the rest lengths' and masses' shares to their accumulators (``gl0``, ``gm``).
x_c, v_c then go to the history in place of the pass's state, for the integrator's
adjoint of the step.

Frozen active set: which springs each iteration shortens, how many meet at each
particle (the shares K), which colliders' projections act, and how many iterations the
pass takes are those of the run as taken. Within them the pass is smooth and this is
its exact Jacobian; where one of them switches (a spring reaching the limit, another
iteration), the run is not differentiable and none is claimed. What the pass does not
depend on: the step's start state (its whole share goes through x_c)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from massspring.device import State
from massspring.kernels import state as state_kernels
from massspring.passes.base import keep_in_history
from massspring.passes.strain_limit.forward import ITERATIONS, TOLERANCE
from massspring.support.errors import StrainLimitGradientError

REPLAY_TOLERANCE = 1e-9  # of the largest rest length (m), and that over dt (m/s): the iterations run again against the pass
RECORD_BYTES = 48  # a recorded step's x_c, v_c per particle (f64 vec3s)
ITERATE_BYTES = 24  # an iteration's start positions per particle, kept while a step runs backwards


def host_bytes(n, checkpoint) -> int:
    """Bytes on the host of the strain limit's run backwards for ``n`` particles: a record
    of each of a stretch's ``checkpoint`` steps and one step's iterations (at most
    ``ITERATIONS`` + 1 and its start)."""
    return n * (RECORD_BYTES * checkpoint + ITERATE_BYTES * (ITERATIONS + 2))


@dataclass(frozen=True)
class Record:
    """A step whose pass moved particles: the state before the pass ``x``, ``v`` (n, 3,
    m and m/s), the time ``t`` the step ended at and its size ``dt`` (s)."""

    x: np.ndarray
    v: np.ndarray
    t: float
    dt: float


class PassSteps:
    """The steps of a gradient's run in which the strain limit moved particles
    (``StrainLimitPass.watch`` hands them in), from ``start``'s on, run backwards before
    the integrator's adjoint of each (``before``)."""

    def __init__(self, sim, adj, owner):
        self.sim, self.adj, self.owner = sim, adj, owner
        self.n, self.stride = sim.model.n_particles, int(adj.stride[None])
        self.scratch = State(adj.sl_x, adj.sl_v)
        rest = sim.model.rest_lengths
        self.tolerance = REPLAY_TOLERANCE * float(rest.max(initial=0.0))
        self.records, self.first = {}, 0
        owner.watch(self)

    def start(self, first):
        """Keep the records of step ``first`` on (those before are dropped)."""
        self.records, self.first = {}, first

    def __call__(self, state, t, dt):
        """A step whose pass moved particles (``StrainLimitPass.watch``): ``state`` as the
        pass left it. An integrator that stored the step's state in the history before the
        pass (``records_history``) gets it replaced by the pass's."""
        k, integrator = self.sim.steps, self.sim.stepper
        keep_in_history(integrator, state, self.n, k)
        if k >= self.first:
            dev = integrator.dev
            self.records[k] = Record(dev.read("x_sl_before"), dev.read("v_sl_before"), float(t), float(dt))

    def any_in(self, low, high) -> bool:
        """Whether a step from ``low`` to ``high`` has a record."""
        return any(low <= k <= high for k in self.records)

    def before(self, k, slot):
        """Before step k's adjoint (kept at ``slot``): if the pass moved particles in it,
        dL/d(the state the pass left) in ``adj.lx``, ``adj.lv`` turned into dL/d(the state
        the step's integrator left), which goes to the history at ``slot + 1``. Returns
        None (nothing for ``after``)."""
        record = self.records.get(k)
        if record is None:
            return None
        from massspring.kernels.strain_limit import strain_limit_adjoint

        n, adj, integrator = self.n, self.adj, self.sim.stepper
        starts = self._iterate(k, record, slot)
        dev, cfg, limit = integrator.dev, integrator.cfg, self.owner.limit
        for x in reversed(starts):
            state_kernels.load_vectors(adj.sl_x, x)
            strain_limit_adjoint(dev, cfg, adj, limit, TOLERANCE, record.dt, record.t)
        state_kernels.write_state(adj.hx, adj.hv, record.x, record.v, n, slot + 1, self.stride)
        return None

    def _iterate(self, k, record, slot):
        """The pass of step k run again from ``record``'s state: the start positions of
        each iteration that moved particles (a list of (n, 3)), checked against the state
        kept at ``slot + 1``."""
        from massspring.kernels.strain_limit import strain_limit_iteration

        n, adj, integrator = self.n, self.adj, self.sim.stepper
        dev, cfg, limit = integrator.dev, integrator.cfg, self.owner.limit
        state_kernels.load_vectors(adj.sl_x, record.x)
        state_kernels.load_vectors(adj.sl_v, record.v)
        starts, x = [], record.x
        for _ in range(ITERATIONS + 1):  # as the pass's launches
            if strain_limit_iteration(dev, cfg, self.scratch, limit, TOLERANCE, record.dt, record.t, 0) <= limit:
                break
            starts.append(x)
            x = adj.read("sl_x", n)
        xs, vs = np.empty((1, n, 3)), np.empty((1, n, 3))
        state_kernels.read_states(adj.hx, adj.hv, np.array([slot + 1], dtype=np.int32), xs, vs, n, self.stride)
        error = max(np.max(np.abs(x - xs[0]), initial=0.0),
                    record.dt * np.max(np.abs(adj.read("sl_v", n) - vs[0]), initial=0.0))
        if not error <= self.tolerance:
            raise StrainLimitGradientError(k, self.sim.integrator, f"its iterations run again from the step's state "
                                           f"end {error:.3g} m from the state the run kept")
        return starts

    def after(self, acted, wants):
        """Nothing: ``before`` did it all."""

    def add_gradients(self, grads):
        """Nothing: the rest lengths' and masses' shares went to their accumulators."""
