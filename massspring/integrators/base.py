"""The integrator protocol, and ``Traits``: what an integrator can do, which the rest of
the code asks instead of its name."""

from __future__ import annotations

import dataclasses

import numpy as np

from massspring.device import Config
from massspring.kernels import state as state_kernels


@dataclasses.dataclass(frozen=True)
class Traits:
    """An integrator class's capabilities (``Integrator.traits``), read as
    ``cls.traits.<name>`` or ``integrator.traits.<name>``; a subclass that changes some
    declares ``traits = dataclasses.replace(Parent.traits, ...)``.

    ``order``: of accuracy. ``has_stats``: steps one at a time, each with solver
    statistics. ``linear_solver``: solves a linear system each step with CG and a
    preconditioner. ``newton``: solves nonlinear equations each step by Newton's method
    (takes ``newton_tol`` and ``newton_max_iter``). ``differentiable``: has ``adjoint``,
    ``massspring.gradient`` can run it backwards. ``keyframed_pins``: moves pins with a
    velocity that changes between steps (``Controls.pin_targets``). ``checked_energy``:
    what its steps' divergence check holds to the bound (``kernels/divergence.py``).
    ``extra_bytes``, ``spring_extra_bytes``: bytes per particle and per spring beyond the
    linearised step's (``memory.run_bytes``). ``grows_undamped``: unstable for undamped
    oscillation at every dt (damping alone can make it stable). ``limit_reference``: its
    measured stability limit is the one the others' are relative to (the stability
    ladder's reference, the integrator ``run`` suggests after such a growth).
    ``error_constant``: C of its local error C h^(order+1) y^(order+1) on the linear test
    equation y' = lambda y, which an error-controlled run's estimate (``engine.adaptive``)
    scales by. ``stability_limited``: explicit, stable only below a step size set by the
    stiffest mode, which an error estimate does not see until the instability has grown:
    an error-controlled run keeps its steps at most its ``suggest_dt`` (half the limit
    predicted at the initial state) unless given ``max_dt``. ``linearised``: solves each
    step's equations linearised once (Eq. 15: one Newton iteration of backward Euler),
    whose error grows with the step and which the error estimate does not see: an
    error-controlled run keeps its steps at most its ``suggest_dt`` (a frame) unless given
    ``max_dt``.
    """

    order: int = 1
    has_stats: bool = False
    linear_solver: bool = False
    newton: bool = False
    differentiable: bool = False
    keyframed_pins: bool = True
    checked_energy: str = "kinetic energy"
    extra_bytes: int = 0
    spring_extra_bytes: int = 0
    grows_undamped: bool = False
    limit_reference: bool = False
    error_constant: float = 0.5
    stability_limited: bool = False
    linearised: bool = False


class Integrator:
    """Advances a simulation's bundle ``dev`` by steps of ``settings.dt``.

    Class attributes: ``name`` (the registry key), ``description`` (one line for the
    CLI), ``traits`` (its capabilities: ``Traits``), ``options`` (its solver's options,
    ``options.Option`` records: ``integrators.OPTIONS``). What the stability ladder and
    the study do with it is theirs (``analysis.hints``). ``serial`` (from
    ``settings.loops``):
    run whole steps or solves in one launch with serial loops (small systems), else
    one parallel launch per phase.
    """

    name = ""
    description = ""
    traits = Traits()
    options = ()  # options.Option records: the solver's Simulation arguments (none by default)

    def __init__(self, dev, model, settings):
        self.dev = dev
        self.settings = settings
        self.serial = settings.loops == "serial"
        self.cfg = self.config(model, settings)
        self.state = dev.state
        self.steps = 0  # good steps taken: the current state is at time steps * dt (moving colliders need it)
        self.dt = settings.dt  # the next step's size (s); an error-controlled run changes it between steps
        self.clock = None  # an error-controlled run's time (s) of the current state; None: steps * dt
        self.cg_tol = getattr(settings, "cg_tol", None)  # the next step's tolerances (error control sets them)
        self.newton_tol = getattr(settings, "newton_tol", None)

    @property
    def time(self) -> float:
        """Simulated time (s) of the current state."""
        return self.steps * self.dt if self.clock is None else self.clock

    def time_after(self) -> float:
        """Simulated time (s) after the step being taken: (steps + 1) dt with a fixed dt."""
        return (self.steps + 1) * self.dt if self.clock is None else self.clock + self.dt

    def count(self, done):
        """Count ``done`` good steps (the clock, where it runs, advanced by dt for each)."""
        if self.clock is not None:
            for _ in range(done):
                self.clock = self.clock + self.dt
        self.steps += done

    @classmethod
    def config(cls, model, settings) -> Config:
        """The compile-time switches of this integrator's kernels for ``model``."""
        return Config.of(model, settings.precision)

    @classmethod
    def finest_f32(cls, model, precision) -> bool:
        """Whether ``preconditioner="auto"`` takes multigrid with its finest level in f32
        (``multigrid-f32``) where it takes multigrid (none by default)."""
        return False

    @classmethod
    def pairs_in_solve(cls, model) -> bool:
        """Whether self-collision pairs enter this integrator's solve (none by default)."""
        return False

    @classmethod
    def declare(cls, layout, model, settings):
        """Add the work fields this integrator needs to ``layout`` (a ``device.Layout``)."""

    def advance(self, steps):
        """Up to ``steps`` steps, each checked (``kernels/divergence.py``).

        Returns (good steps done, ``divergence.verdict`` of the last state computed:
        (code, kinetic energy J, bound J) with code OK, or that of the first failed
        step). A failed step's state is never the current one.
        """
        raise NotImplementedError

    # (adj bundle, first step k) while a gradient's run records into its history
    # (``massspring.gradients``), whose slot j holds the state after step k + j: ``advance``
    # stores each new state there where ``records_history``, and what else the adjoint
    # needs of a step that the state does not hold (the implicit step's solve with friction)
    history = None
    records_history = False

    def settle(self):
        """Make ``dev.state`` the current state (it is, unless the integrator swaps states:
        ``SwappingStates``)."""

    def changed(self):
        """The current state was changed after a step (a strain limit's or the self-collision
        pass's positions and velocities): update what the integrator keeps of it (nothing by default)."""

    def carried(self, rows=None) -> dict:
        """The arrays of ``carried_names`` at the current state (numpy, a row per particle):
        those of ``carried_fields`` from ``rows`` (name -> the field's values as read
        already, e.g. with the state: ``kernels.state.read_state``) or read here, with
        ``carried_values``."""
        names = self.carried_names()
        out = {}
        for name, field in self.carried_fields().items():
            values = self.dev.read(field) if rows is None else rows[name]
            out[name] = values.astype(names[name][0])
        return {**out, **self.carried_values()}

    def carried_fields(self) -> dict:
        """Of ``carried_names``, those a field holds as they are: name -> the field's name
        in the bundle (all of them by default)."""
        return {name: name for name in self.carried_names()}

    def carried_values(self) -> dict:
        """Of ``carried_names``, those the integrator holds in Python, as arrays (none by default)."""
        return {}

    def carried_names(self) -> dict:
        """What this run carries from step to step besides x and v: name -> (numpy dtype,
        trailing shape) of arrays with a row per particle (none by default)."""
        return {}

    def load_state(self, positions, velocities, carried=None):
        """Make ``positions`` and ``velocities`` ((n, 3) float64 numpy, checked by the
        caller) the current state, as if the last step had produced them; ``carried``
        (checked by the caller): the arrays of ``carried_names`` (None: start them afresh)."""
        state_kernels.load_vectors(self.state.x, positions)
        state_kernels.load_vectors(self.state.v, velocities)
        for name, values in (carried or {}).items():
            field = getattr(self.dev, name)
            if values.ndim == 2:
                state_kernels.load_vectors(field, values.astype(np.float64))
            else:
                state_kernels.load_integers(field, values.astype(np.int32))

    @classmethod
    def declare_adjoint(cls, layout, model, stride, rows):
        """Add the fields this integrator's ``adjoint`` needs beyond the gradient's own to
        ``layout`` (float64) for ``model``; ``stride``: the history's rows per state,
        ``rows`` its rows in all (none by default)."""

    @classmethod
    def kept_bytes(cls, model) -> int:
        """Bytes a particle that ``keep`` stores with a state besides its x and v (none by default)."""
        return 0

    def keep(self, adj, slot):
        """Keep the current state in ``adj``'s history at ``slot`` (``massspring.gradients``),
        with what the adjoint of the step from it needs besides x and v."""
        state_kernels.save_state(adj.hx, adj.hv, self.state, self.dev.n, slot, int(adj.stride[None]))

    def at_step(self, k, clock=None, size=None, before=None):
        """Make the step from step ``k`` the one to take or run backwards (a gradient's
        backward pass): from time k dt; of a replayed run (``Simulation.replay``), from
        ``clock`` (s) with size ``size`` (s), the step before it of size ``before`` (s,
        None for the first)."""
        self.steps = k
        if clock is not None:
            self.clock, self.dt = clock, size

    def adjoint(self, adj, slot, wants):
        """Run a step backwards (``massspring.gradient``) from the state kept at ``slot``
        of ``adj``'s history (made the current state): ``adj`` (its bundle) holds dL/dx', dL/dv' of the step's end state on entry and
        dL/dx, dL/dv of the current state on exit, with the step's share of each
        parameter gradient added; ``wants``: ``gradients.Wants``. Only where ``traits.differentiable``.
        Returns the ``SolverStats`` of a step's adjoint solve, None where it has none."""
        raise NotImplementedError

    def adjoint_steps(self, adj, slot, count, wants) -> bool:
        """``adjoint`` of ``count`` steps in a row, from the one kept at ``slot`` down to
        ``slot - count + 1``, in one launch where the integrator can (then True; the
        current step count is not read), else False: the caller steps one at a time."""
        return False

    @property
    def stats(self):
        """The last step's solver outcome (implicit integrators), else None."""
        return None

    @staticmethod
    def stability_limit(prediction):
        """The largest dt (s) the prediction (``engine.spectrum.Prediction``) lets this
        integrator take (inf: none), or None if it has no such limit (the study then starts
        its ladder at the scene's dt)."""
        return None

    @staticmethod
    def suggest_dt(prediction) -> float:
        """A default dt (s) for a scene without one, from ``engine.spectrum.Prediction``."""
        raise NotImplementedError

    def release(self):
        """Hand back resources other than the simulation's bundle (none by default)."""


class SwappingStates(Integrator):
    """An integrator that steps from ``state`` into ``spare`` and swaps the two (explicit,
    symplectic, RK4). ``settle`` copies the current state back into ``dev.state``, so that
    what reads or changes the state between steps (``positions``, the self-collision pass,
    a gradient's history and adjoint) compiles its kernels for one pair of fields, not two."""

    def __init__(self, dev, model, settings):
        super().__init__(dev, model, settings)
        self.spare = dev.states["spare"]
        self.states = (self.state, self.spare)  # the serial kernels' fixed order (one compile)

    @classmethod
    def declare(cls, layout, model, settings):
        layout.state("spare", layout.real)

    def settle(self):
        if self.state is not self.dev.state:
            state_kernels.copy_state(self.dev.state, self.state, self.dev.n, self.serial)
            self.state, self.spare = self.dev.state, self.state
