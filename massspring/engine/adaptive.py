"""Error-controlled steps: a local error estimate from a run's own accepted states
(Milne's device) and a PI step-size controller (``Simulation(tol=...)``).

The estimate. An integrator of order p makes a local error C h^(p+1) y^(p+1) per step
(C: its ``traits.error_constant``, exact on the linear test equation y' = lambda y; y
the state (x, v)). The (p+1)-th derivative of the solution is read off the accepted
states themselves: the divided difference of order p + 1 through the new state and the
p + 1 before it, y[t_(n+1), ..., t_(n-p)] ~ y^(p+1) / (p+1)!, for any step sizes. That is
the difference between the new state and the polynomial through the p + 1 before it
extrapolated to t_(n+1) (Milne's predictor-corrector device, as CVODE's BDF estimate),
so it costs no force evaluation and no solve, only vector arithmetic on states the run
makes anyway; it serves the second- and fourth-order integrators (midpoint, BDF2, RK4).
While fewer states are at hand (the first steps, and after the history is dropped at a
kink) the estimate takes the highest order they allow, q < p, which overestimates the
error and so only makes the first steps short. The first-order integrators (explicit,
symplectic, linearised implicit, backward Euler), and every integrator's first step,
take the mismatch of the step's positions with the trapezoidal rule on its velocities,
x' - x - h (v + v') / 2 = -+h^2 a / 2, their position error, from the step alone: their
history-based estimate made the step sizes zigzag (a first-order run's global error
jumps with its step size, and the divided differences read the jumps as curvature:
docs/solvers.md, "Error-controlled steps").

The norm. The error the study reports is the RMS over the moving particles of the
position error, over the scene's size L (``analysis.study``). The estimate is measured
the same way, the positions' only; a step is accepted when it is at most tol h / H (H,
the ``horizon``: the run's duration; error per unit step: the local errors of a run of
duration H then add up to about tol, so the error at its end falls in proportion to
``tol``, where error per step would give tol^(p/(p+1))). Velocities count through the
positions they make: weighting their own estimate by L / H (as CVODE weighs every
component alike) made the stiff chain resolve the axial vibrations that hold no
position error (docs/solvers.md).

Impacts. A particle that may have hit or left a collider within a step
(``Estimator._contacts``) has its velocity changed by the contact response in that one
step, first order whatever the integrator: it counts no smooth error in any estimate
spanning the step, and its impact's timing error, h |v' - v| / 2, is bounded by tol
itself (``Estimator.error``). One in contact at both ends of a step (resting, sliding)
keeps its estimate.

Stability. An explicit integrator's steps stay at most its ``suggest_dt`` of the model
unless ``max_dt`` is given (``stable_bound``): the estimate sees an instability only once
it has grown. So do the linearised implicit step's (a frame, 1/60 s): the estimate sees
backward Euler's error, not that of solving its equations linearised once, which
grows with the step (``flag`` at tol 0.1: 1.1-2.8 times the bound at steps of 0.039-0.17 s
against a converged backward-Euler step from the same state, where the estimate stayed
below it, until a step of 0.52 s ended in a state the next steps diverged from).

Batches. Held there, an explicit run's estimate is often a tiny fraction of its bound
(the stability limit, not the error, sets the step), and a try's own work (the state
read back, the estimate, the controller: about 0.4 ms) costs hundreds of times the
step itself. After ``CALM_TRIES`` accepted steps in a row at ``max_dt`` with estimates
at most ``CALM`` of their bound, and without colliders, passes or a gradient's record,
the run takes its next steps at ``max_dt`` in one launch (``BATCH_FIRST`` steps, twice
as many each batch after, at most ``BATCH_MOST`` and ``BATCH_SPAN`` of the horizon,
never past the next landing), then ``order`` single steps that refill the estimate's
history with the states it would have held, then a step tried and judged as any: the
next batch follows only if it is calm too (``Simulation._batch``). A batch's steps are
the steps the controller would have taken (it holds a step at ``max_dt`` while its
estimate stays below about 0.8 of the bound) unless the error grew more than
twofold within one, and a batch spans at most 1/32 of the horizon: were its estimates
even four times their bound, it would add about tol / 8 to the end error.

The controller (a PI controller, Hairer and Wanner II, IV.2, with their DOPRI5 gains):
with r the ratio of the estimate to its bound and k = q the estimate's order in h (error
per unit step), an accepted step proposes h r^(-alpha) r_prev^beta times ``SAFETY``,
beta = 0.2 / k, alpha = 1 / k - 0.75 beta (Gustafsson's PI.3.4, r^(-0.3/k) (r_prev /
r)^(0.4/k), grew the step too slowly for runs of a few dozen steps),
within [1 / ``GROWTH``, ``GROWTH``] of h; a rejected one retries with
max(``SHRINK``, ``SAFETY`` r^(-1/k)) h and may not grow on the step after. A step
whose solve failed (Newton or CG missed its tolerance) or that the divergence check
refused retries at ``FAILURE_SHRINK`` h. Below ``min_dt`` the run stops
(``StepSizeError``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np

from massspring.support import validate
from massspring.support.errors import DivergenceError
from massspring.support.text import format_seconds

SAFETY = 0.9
GROWTH = 5.0  # the largest growth of the step from one step to the next
SHRINK = 0.2  # the smallest factor on a step whose error was too large
FAILURE_SHRINK = 0.25  # the factor on a step whose solve failed or that diverged
PI_BETA = 0.2  # the PI controller's beta times the estimate's order (Hairer's DOPRI5: 0.04 at order 5)
DROP_AFTER = 3  # rejections of one step in a row after which the history is dropped (a kink)
STRETCH = 1.1  # a step this much longer lands on the next end time (no sliver of a step before it)
CALM = 0.3  # a step held at max_dt whose estimate is at most this fraction of its bound is calm
CALM_TRIES = 8  # calm steps in a row after which an explicit run steps in batches (``Simulation``)
BATCH_FIRST, BATCH_MOST = 16, 4096  # steps of the first batch after a calm stretch, and of any
BATCH_SPAN = 1 / 32  # the longest batch, as a fraction of the horizon
CONTACT_MARGIN = 1e-9  # a particle this close (times the scene's size) to a collider is in contact with it
MIN_TOL = 1e-14  # tolerances below this are round-off in f64
DEFAULT_HORIZON = 1.0  # s
MIN_DT_FRACTION = 1e-9  # default min_dt: this times the horizon
NEWTON_FRACTION = 0.1  # Newton's velocity error: this fraction of the step's velocity error bound
CG_FRACTION = 0.1  # the linearised step's CG error: this fraction of it
TOL_RANGE = {"newton_tol": (1e-10, 0.1), "cg_tol": (1e-12, 1e-2)}


def scene_size(model) -> float:
    """Largest side (m) of the bounding box of the initial positions (1 if 0): the length
    the study's errors and an error-controlled run's tolerance are relative to."""
    extent = float(np.max(np.ptp(model.positions, axis=0))) if model.n_particles else 0.0
    return extent if extent > 0 else 1.0


class StepSizeError(DivergenceError):
    """An error-controlled run's step would fall below ``min_dt`` (s): ``time`` (s) it
    stopped at, ``dt`` the step it would have taken, ``cause`` why the last try failed."""

    def __init__(self, step, time, dt, min_dt, cause, integrator, horizon=None):
        """``horizon`` (s): given where min_dt is its default, ``MIN_DT_FRACTION`` of it."""
        self.step, self.time, self.dt, self.min_dt, self.cause = int(step), float(time), float(dt), float(min_dt), cause
        self.integrator = integrator
        self.energy = self.kinetic = self.bound = math.nan
        self.measured = "error estimate"
        default = ("" if horizon is None else
                   f" (by default {MIN_DT_FRACTION:g} of the horizon, {horizon:g} s: give min_dt for smaller steps)")
        RuntimeError.__init__(self, f"{integrator} stopped at t = {self.time:.6g} s (step {self.step}): the step "
                                    f"would fall to {format_seconds(self.dt)}, below min_dt "
                                    f"{format_seconds(self.min_dt)}{default} ({cause}); the state at t = "
                                    f"{self.time:.6g} s is kept")


@dataclass(frozen=True)
class Tolerance:
    """An error-controlled run's settings: ``tol`` (the error the study reports, RMS
    position error over the scene's size, wanted at the end of ``horizon`` s), the
    bounds ``min_dt``, ``max_dt`` (s) on its steps."""

    tol: float
    min_dt: float
    max_dt: float
    horizon: float

    @classmethod
    def of(cls, tol, min_dt=None, max_dt=None, horizon=None):
        """Checked settings (ValueError naming the argument); None: the defaults (horizon
        ``DEFAULT_HORIZON``, min_dt ``MIN_DT_FRACTION`` of it, max_dt the horizon)."""
        tol = validate.positive_float("tol", tol)
        if tol < MIN_TOL:
            raise ValueError(f"tol: {tol:g} is below {MIN_TOL:g}, the round-off of an f64 run")
        horizon = DEFAULT_HORIZON if horizon is None else validate.positive_float("horizon", horizon)
        min_dt = MIN_DT_FRACTION * horizon if min_dt is None else validate.positive_float("min_dt", min_dt)
        max_dt = horizon if max_dt is None else validate.positive_float("max_dt", max_dt)
        if min_dt > max_dt:
            raise ValueError(f"min_dt: {min_dt:g} s is above max_dt {max_dt:g} s")
        return cls(tol, min_dt, max_dt, horizon)


def stable_bound(tolerance: Tolerance, integrator_class, model) -> Tolerance:
    """``tolerance`` with max_dt at most the dt ``integrator_class`` suggests for ``model``
    (never below min_dt): an explicit integrator's (half its stability limit predicted at
    the initial state, ``engine.spectrum``), whose error estimate does not see an
    instability until it has grown (a free fall, integrated exactly, lets the steps grow
    past the limit); the linearised step's (a frame), whose estimate does not see its
    linearisation's error (module docstring, "Stability"). Another integrator's
    ``tolerance`` is returned as it is."""
    from massspring.engine.spectrum import predict

    traits = integrator_class.traits
    if not (traits.stability_limited or traits.linearised):
        return tolerance
    bound = integrator_class.suggest_dt(predict(model) if traits.stability_limited else None)
    return replace(tolerance, max_dt=max(min(tolerance.max_dt, bound), tolerance.min_dt))


class Estimator:
    """The local error of each step from the accepted states (module docstring):
    ``order`` p and ``constant`` C of the integrator, ``moving`` the particles whose
    error counts (inner numbering), ``size`` L (m), ``horizon`` H (s)."""

    def __init__(self, order, constant, moving, size, horizon, colliders=()):
        self.order, self.constant = int(order), float(constant)
        self.moving = np.asarray(moving)
        self.size, self.horizon = float(size), float(horizon)
        self.colliders = tuple(colliders)
        # (t, y (k, 6), d (k,) or None, touched (k,) or None) of accepted states, oldest
        # first, at most order + 1: d the distance to the nearest collider, touched whether
        # the particle may have touched one in the step that ended there
        self.points = []
        self._tried = None

    def reset(self, t, x, v):
        """Start the history afresh at the state (t, x, v)."""
        self.points = [(float(t), self._y(x, v), self._distance(t, x), None)]

    def _y(self, x, v):
        return np.concatenate([x[self.moving], v[self.moving]], axis=1).astype(np.float64)

    def _distance(self, t, x):
        """(k,) distance (m) of each moving particle to the nearest collider at time t (s);
        None without colliders."""
        if not self.colliders:
            return None
        points = x[self.moving]
        return np.min([c.at(t).signed_distance(points) for c in self.colliders], axis=0)

    def _contacts(self, start, t, y, d):
        """((k,) whether each moving particle may have hit or left a collider in the step
        from the accepted point ``start`` to (t, y, d), (k,) whether it was in contact at
        both ends), or (None, None) without colliders. Hit or left: it began or ended
        within the distance its speed carries it in the step (h (|v| + |v'| + |v' - v|),
        m) of one, and was not in contact at both ends (within ``CONTACT_MARGIN`` times the
        scene's size: resting or sliding)."""
        if d is None:
            return None, None
        t0, y0, d0, _ = start
        h = t - t0
        speed = np.linalg.norm(y0[:, 3:], axis=1) + np.linalg.norm(y[:, 3:], axis=1)
        speed += np.linalg.norm(y[:, 3:] - y0[:, 3:], axis=1)
        margin = CONTACT_MARGIN * self.size
        staying = (d0 <= margin) & (d <= margin)
        return (np.minimum(d0, d) <= h * speed + margin) & ~staying, staying

    def error(self, t, x, v, moved=None):
        """(the weighted RMS of the estimate of the step to (t, x, v), its order in h).

        Contact (``_contacts``). A particle that may have hit or left a collider in any of
        the steps the estimate spans counts no error of a smooth solution: the contact
        response changes its velocity within one step, a kink no such estimate describes,
        and is first order in the step whatever the integrator (``kernels/contact.py``).
        Its error is that of the impact's timing instead: up to half the step times its
        velocity change, h |v' - v| / 2 for the particles hitting or leaving one in this
        step, which the run bounds by ``tol`` itself, not by tol h / H: an impact happens
        once, its error does not add up step after step. A particle in contact at both
        ends of the step (resting, sliding) moves by the first-order response every step,
        whose error accumulates with a smooth trajectory a higher-order estimate cannot
        see: it counts the trapezoidal companion's estimate, as the first-order
        integrators do. Either is of order 1 in h, which the estimate is where they are
        the larger part; the impact's is returned in the units of the others (times h / H).

        ``moved``: the particles (inner numbering) a pass changed the velocities of at the
        end of this step (``Pass.moved``: the self-collision pass's impulses) count no
        error in any estimate spanning it. The pass's response is not an integration error
        that a shorter step makes smaller: it moves a close pair apart within the step by
        a fraction of its gap, whatever the step's size, so its velocity change grows as
        1 / h (counted as an impact, h |v' - v| / 2 does not shrink with h: the steps of
        ``sheets`` fell below min_dt as its upper sheet landed, each shorter step's
        impulses putting in more energy, until the divergence check refused them)."""
        y, d = self._y(x, v), self._distance(t, x)
        t0, y0 = self.points[-1][:2]
        h = t - t0
        if y.size == 0:
            return 0.0, 1
        touched, staying = self._contacts(self.points[-1], t, y, d)
        passed = None if moved is None or not len(moved) else np.isin(self.moving, moved)
        if passed is not None and touched is None:
            touched, staying = np.zeros_like(passed), np.zeros_like(passed)
        record = touched if passed is None else touched | passed
        self._tried = (float(t), y, d, record)  # what ``push`` adds if the step is accepted
        if self.order == 1 or len(self.points) == 1 or touched is not None:
            companion = y[:, :3] - y0[:, :3] - 0.5 * h * (y[:, 3:] + y0[:, 3:])
        if self.order == 1 or len(self.points) == 1:
            q, e, spanned = 1, companion, ()  # spanned: the accepted points whose steps it spans besides this one
        else:
            q = min(self.order, len(self.points) - 1)
            times = [p[0] for p in self.points[-(q + 1):]] + [float(t)]
            table = [p[1] for p in self.points[-(q + 1):]] + [y]
            for m in range(1, q + 2):
                table = [(table[j + 1] - table[j]) / (times[j + m] - times[j]) for j in range(len(table) - 1)]
            constant = self.constant if q == self.order else 0.5
            e = constant * math.factorial(q + 1) * h ** (q + 1) * table[0][:, :3]
            spanned = self.points[-q:]
        squares = np.sum(e * e, axis=1)
        if touched is None:
            return math.sqrt(float(np.mean(squares))) / self.size, q
        if passed is not None:
            touched, staying = touched & ~passed, staying & ~passed
        jump = np.sum((y[touched, 3:] - y0[touched, 3:]) ** 2, axis=1)
        impact = 0.5 * h * math.sqrt(float(np.sum(jump)) / len(y)) / self.size * h / self.horizon
        touched = record
        for p in spanned:
            if p[3] is not None:
                touched = touched | p[3]
        sliding = staying & ~touched
        squares[touched | staying] = 0.0
        smooth = math.sqrt(float(np.mean(squares))) / self.size
        first = math.sqrt(float(np.sum(companion[sliding] ** 2)) / len(y)) / self.size
        estimate = math.sqrt(smooth * smooth + first * first + impact * impact)
        return estimate, (1 if max(first, impact) > smooth else q)

    def push(self, t, x, v):
        """Add the accepted state (t, x, v): the one ``error`` was last asked about, or another."""
        if self._tried is not None and self._tried[0] == float(t):
            point = self._tried
        else:
            y, d = self._y(x, v), self._distance(t, x)
            point = (float(t), y, d, self._contacts(self.points[-1], t, y, d)[0] if self.points else None)
        if point[3] is None and point[2] is not None:
            point = point[:3] + (np.zeros(len(point[2]), dtype=bool),)
        self._tried = None
        self.points.append(point)
        del self.points[:-max(self.order + 1, 2)]

    def state(self) -> dict:
        """The accepted states it estimates from, as arrays (``load`` takes them back):
        "est_t" (p,) s, "est_y" (p, k, 6) positions and velocities of the k moving
        particles, "est_d" (p, k) m and "est_touched" (p, k) 0/1 (zeros where a point has
        none), "est_has" (p, 2) 0/1: whether the point has a distance and a touched row."""
        k, p = len(self.moving), len(self.points)
        out = {"est_t": np.array([q[0] for q in self.points], dtype=np.float64),
               "est_y": np.zeros((p, k, 6)), "est_d": np.zeros((p, k)), "est_touched": np.zeros((p, k)),
               "est_has": np.zeros((p, 2))}
        for i, (_, y, d, touched) in enumerate(self.points):
            out["est_y"][i] = y
            for j, (name, rows) in enumerate((("est_d", d), ("est_touched", touched))):
                if rows is not None:
                    out[name][i], out["est_has"][i, j] = rows, 1.0
        return out

    def load(self, state):
        """Take back a ``state()`` of a run of the same model (ValueError naming the
        key if its shapes do not fit)."""
        k = len(self.moving)
        times = np.asarray(state["est_t"], dtype=np.float64)
        p = times.shape[0] if times.ndim == 1 else -1
        shapes = {"est_t": (p,), "est_y": (p, k, 6), "est_d": (p, k), "est_touched": (p, k), "est_has": (p, 2)}
        for name, shape in shapes.items():
            if np.shape(state[name]) != shape or not 0 <= p <= max(self.order + 1, 2):
                raise ValueError(f"control[{name!r}]: expected shape {shape} (at most {max(self.order + 1, 2)} "
                                 f"points of {k} moving particles), got {np.shape(state[name])}")
        has = np.asarray(state["est_has"]) != 0
        self.points = [(float(times[i]), np.array(state["est_y"][i], dtype=np.float64),
                        np.array(state["est_d"][i], dtype=np.float64) if has[i, 0] else None,
                        (np.asarray(state["est_touched"][i]) != 0) if has[i, 1] else None) for i in range(p)]
        self._tried = None

    def velocity_change(self) -> float:
        """RMS (m/s) of the last accepted step's velocity change over its moving particles
        (0 before one)."""
        if len(self.points) < 2 or self.points[-1][1].size == 0:
            return 0.0
        dv = self.points[-1][1][:, 3:] - self.points[-2][1][:, 3:]
        return math.sqrt(float(np.mean(np.sum(dv * dv, axis=1))))


# Simulation.control_state()'s keys: the controller's state, the calm batches', the estimator's
CONTROL_KEYS = ("controller", "batching", "est_t", "est_y", "est_d", "est_touched", "est_has")
# Controller.state(): what each of its numbers is
CONTROLLER_FIELDS = ("dt", "previous_ratio", "after_rejection", "in_a_row", "last_try_t", "last_try_h",
                     "last_try_ratio", "kinks", "accepted", "batched", "rejected_error", "rejected_solver",
                     "rejected_divergence", "smallest_dt", "largest_dt")


class Controller:
    """The step-size controller of an error-controlled run (module docstring): ``dt`` is
    the next step's size; ``judge`` an attempt's outcome; ``size`` L (m). Keeps its
    statistics."""

    def __init__(self, tolerance: Tolerance, first_dt: float, size: float):
        self.tolerance, self.size = tolerance, float(size)
        self.dt = min(max(float(first_dt), tolerance.min_dt), tolerance.max_dt)
        self.previous_ratio = None  # r of the last accepted step
        self.after_rejection = False
        self.in_a_row = 0  # rejections of the step being tried
        self.last_try = None  # (t, h, ratio) of the last step rejected for its error
        self.kinks = 0  # steps accepted at a kink
        self.accepted = 0
        self.batched = 0  # accepted without an estimate (``accept_unjudged``)
        self.rejected = {"error": 0, "solver": 0, "divergence": 0}
        self.smallest, self.largest = math.inf, 0.0

    def state(self) -> np.ndarray:
        """Its state, numbers in the order of ``CONTROLLER_FIELDS`` (float64; ``load``
        takes it back): the next step, the PI memory, the last rejected try, and the
        statistics. None and infinity are written as 0 (a ratio kept is at least 1e-10, a
        try's h > 0, the smallest step is read only once one was accepted)."""
        t, h, ratio = self.last_try or (0.0, 0.0, 0.0)
        return np.array([self.dt, self.previous_ratio or 0.0, self.after_rejection, self.in_a_row, t, h, ratio,
                         self.kinks, self.accepted, self.batched, *self.rejected.values(),
                         self.smallest if self.accepted else 0.0, self.largest], dtype=np.float64)

    def load(self, state):
        """Take back a ``state()`` (ValueError if it is not one)."""
        state = np.asarray(state, dtype=np.float64)
        if state.shape != (len(CONTROLLER_FIELDS),) or not np.all(np.isfinite(state)) or not state[0] > 0:
            raise ValueError(f"control['controller']: expected {len(CONTROLLER_FIELDS)} finite numbers (a "
                             f"Controller.state()), got shape {state.shape}")
        (self.dt, ratio, after, in_a_row, t, h, try_ratio, kinks, accepted, batched, *rejected, smallest,
         self.largest) = state.tolist()
        self.previous_ratio = ratio or None
        self.after_rejection, self.in_a_row = bool(after), int(in_a_row)
        self.last_try = (t, h, try_ratio) if h > 0 else None
        self.kinks, self.accepted, self.batched = int(kinks), int(accepted), int(batched)
        self.rejected = dict(zip(self.rejected, map(int, rejected)))
        self.smallest = smallest if self.accepted else math.inf

    def bound(self, h) -> float:
        """The estimate's bound for a step of h (s): tol h / H (error per unit step)."""
        return self.tolerance.tol * h / self.tolerance.horizon

    def judge(self, h, estimate=None, order=1, failure=None, t=0.0) -> bool:
        """Whether the step of h (s) from time t is accepted, from its error ``estimate``
        (weighted RMS) of ``order`` in h, or its ``failure`` ("solver" or "divergence"):
        sets ``dt``. A step too large for its error is accepted all the same where it lies
        within the last step so rejected, is shorter, and its ratio to the bound shrank by
        less than its order predicts, as h^(order - 1/2) rather than h^order: a kink
        (an impact, a contact made or released), where the estimate of a smooth solution
        does not hold and no step would meet it (a velocity jump is an O(h) position error,
        as its bound is), so the run steps across it (its error there, ratio x tol h / H, is
        small with h) instead of closing in on it forever; the next step keeps h."""
        if failure is not None:
            self.rejected[failure] += 1
            self.in_a_row += 1
            self.after_rejection = True
            self.dt = FAILURE_SHRINK * h
            return False
        ratio = estimate / self.bound(h)
        kink = False
        if ratio > 1.0 and self.last_try is not None:
            start, before_h, before_ratio = self.last_try
            within = start <= t and t + h <= start + before_h * (1 + 1e-9)
            kink = within and h < before_h and ratio > before_ratio * (h / before_h) ** (order - 0.5)
        if ratio > 1.0 and not kink:
            self.last_try = (t, h, ratio)
            self.rejected["error"] += 1
            self.in_a_row += 1
            self.after_rejection = True
            self.dt = h * max(SHRINK, SAFETY * ratio ** (-1.0 / order))
            return False
        if ratio == 0.0:
            factor = GROWTH
        else:
            beta = PI_BETA / order if self.previous_ratio else 0.0
            factor = SAFETY * ratio ** -(1.0 / order - 0.75 * beta) * (self.previous_ratio or 1.0) ** beta
        factor = min(max(factor, 1.0 / GROWTH), 1.0 if self.after_rejection else GROWTH)
        if kink:
            self.kinks += 1
            factor = 1.0
            ratio = 1.0
        self.previous_ratio = max(ratio, 1e-10)
        if kink or (self.last_try is not None and t >= sum(self.last_try[:2])):
            self.last_try = None  # stepped past it
        self.after_rejection = False
        self.in_a_row = 0
        self.accepted += 1
        self.smallest, self.largest = min(self.smallest, h), max(self.largest, h)
        self.dt = min(h * factor, self.tolerance.max_dt)
        return True

    def accept_unjudged(self, h, count):
        """Count ``count`` steps of h (s) taken without an estimate (a batch of calm steps at
        ``max_dt``); the next step's size stays."""
        if count:
            self.accepted += count
            self.batched += count
            self.smallest, self.largest = min(self.smallest, h), max(self.largest, h)

    def stats(self) -> dict:
        """Accepted steps (``batched``: of them, those taken in calm batches without an
        estimate), rejections by cause, steps accepted at a kink (``judge``), the smallest
        and largest accepted step (s) and the next step (s)."""
        return {"accepted": self.accepted, "batched": self.batched, "rejected": dict(self.rejected),
                "kinks": self.kinks,
                "smallest_dt": self.smallest if self.accepted else None,
                "largest_dt": self.largest if self.accepted else None, "next_dt": self.dt}

    def solver_tolerance(self, name, velocity_change) -> float | None:
        """Newton's or CG's stopping tolerance (``name``: "newton_tol" or "cg_tol"), both
        relative to the step's velocity change: a velocity error dv moves the step's
        positions by h dv, so the step's position error bound tol L h / H allows
        dv = tol L / H; a fraction of that (``NEWTON_FRACTION``, ``CG_FRACTION``, as
        CVODE stops Newton at 0.1 of its error test) over the velocity change the last
        step made (``velocity_change``, m/s RMS), within ``TOL_RANGE``; None before a
        step has been made (the option's default then)."""
        if velocity_change <= 0.0:
            return None
        fraction = NEWTON_FRACTION if name == "newton_tol" else CG_FRACTION
        low, high = TOL_RANGE[name]
        speed = self.tolerance.tol * self.size / self.tolerance.horizon
        return min(max(fraction * speed / velocity_change, low), high)
