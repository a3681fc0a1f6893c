"""The stiffest mode of a model and the step sizes it allows the explicit integrators.

``spectrum`` estimates the largest eigenvalue lambda_max = omega_max^2 of M^-1 K
(K the stiffness of seed Eq. 13 as written, no definiteness fix: that is the
Jacobian the explicit integrators see) at a state, by Lanczos on the symmetric
M^-1/2 (-K) M^-1/2 over the free degrees of freedom. K and D are applied
matrix-free by the implicit solver's own kernels (``massspring.engine.operators``); the
stiffest mode's damping rate is c = u^T M^-1/2 (-D) M^-1/2 u (springs' damping and air drag).

``predict`` turns (omega, c) into limits for the stiffest mode, x'' + c x' + omega^2 x = 0:

* symplectic Euler is stable while omega^2 dt^2 + 2 c dt < 4, i.e. for
  dt < (sqrt(c^2 + 4 omega^2) - c) / omega^2 (= 2 / omega without damping);
* explicit Euler multiplies the mode by rho(dt) per step, the spectral radius of
  [[1, dt], [-omega^2 dt, 1 - c dt]]: sqrt(1 - c dt + omega^2 dt^2) when complex,
  sqrt(1 + (omega dt)^2) undamped, so it grows at every dt unless dt < c / omega^2.
  ``doubling_dt`` is the dt at which rho^(2/dt) = 2: the stiffest mode's energy
  doubles within one second of simulated time.

An error-controlled run of an explicit integrator keeps its steps below these limits
(``engine.adaptive.stable_bound``); ``analysis.stability`` checks them with a ladder of runs.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from massspring.engine.operators import Jacobians
from massspring.model import Model


@dataclass(frozen=True)
class Spectrum:
    """lambda_max (1/s^2) of M^-1 K, omega_max = sqrt(lambda_max) (rad/s), the stiffest
    mode's damping rate c (1/s, = 2 zeta omega), Lanczos iterations and the Ritz
    residual ||M^-1/2 K M^-1/2 u - lambda u|| (1/s^2) of the estimate."""

    lambda_max: float
    omega_max: float
    damping_rate: float
    iterations: int
    residual: float


def spectrum(model: Model, positions=None, iterations=40, seed=0) -> Spectrum:
    """Estimate the stiffest mode of ``model`` at ``positions`` ((n, 3) m; default the
    model's) with ``iterations`` Lanczos steps (full reorthogonalisation, seeded)."""
    if isinstance(iterations, bool) or not isinstance(iterations, int) or iterations < 1:
        raise ValueError(f"iterations: expected a positive integer, got {iterations!r}")
    x = model.positions if positions is None else np.asarray(positions, dtype=np.float64)
    free = model.free_mask()
    if model.n_springs == 0 or not free.any():  # no stiffness: the fastest decay is drag on the lightest particle
        rate = model.drag / float(model.masses[free].min()) if free.any() else 0.0
        return Spectrum(0.0, 0.0, rate, 0, 0.0)
    jacobians = Jacobians(model, x)
    scale = np.where(free, 1.0 / np.sqrt(model.masses), 0.0)[:, None]

    def apply(product, u):
        """M^-1/2 (-K or -D) M^-1/2 u on the free DOFs, u of shape (n, 3)."""
        return -scale * product(scale * u)

    u = np.random.default_rng(seed).standard_normal(x.shape) * free[:, None]
    basis = [u / np.linalg.norm(u)]
    alphas, betas = [], []
    for _ in range(min(iterations, 3 * int(free.sum()))):
        w = apply(jacobians.stiffness, basis[-1])
        alphas.append(float(np.vdot(basis[-1], w)))
        for _pass in range(2):  # full reorthogonalisation, twice is enough
            for b in basis:
                w -= np.vdot(b, w) * b
        beta = float(np.linalg.norm(w))
        betas.append(beta)
        if beta <= 1e-12 * max(abs(a) for a in alphas) or not math.isfinite(beta):
            break
        basis.append(w / beta)
    k = len(alphas)
    tri = np.diag(alphas) + np.diag(betas[:k - 1], 1) + np.diag(betas[:k - 1], -1)
    values, vectors = np.linalg.eigh(tri)
    lam, y = float(values[-1]), vectors[:, -1]
    mode = sum(c * b for c, b in zip(y, basis[:k]))
    rate = float(np.vdot(mode, apply(jacobians.damping, mode))) if model.has_damping else 0.0
    rate += model.drag * float(np.vdot(mode, scale ** 2 * mode))  # drag: D = -drag I on every particle
    jacobians.close()
    return Spectrum(lam, math.sqrt(max(lam, 0.0)), rate, k, abs(betas[k - 1] * y[-1]))


def explicit_growth(omega, rate, dt):
    """Per-step amplification of explicit Euler on x'' + rate x' + omega^2 x = 0: the
    spectral radius of [[1, dt], [-omega^2 dt, 1 - rate dt]] (dimensionless)."""
    return math.exp(log_explicit_growth(omega, rate, dt))


def log_explicit_growth(omega, rate, dt):
    """log of ``explicit_growth``, accurate for tiny dt (no 1 + tiny round-off).

    The eigenvalues are 1 + dt (-rate +- sqrt(rate^2 - 4 omega^2)) / 2: complex
    with |lambda|^2 = 1 + dt (omega^2 dt - rate) when rate < 2 omega, else real.
    """
    disc = rate * rate - 4.0 * omega * omega
    if disc < 0:
        return 0.5 * math.log1p(dt * (omega * omega * dt - rate))
    root = math.sqrt(disc)
    return max(_log_abs_one_plus(0.5 * dt * (root - rate)), _log_abs_one_plus(-0.5 * dt * (root + rate)))


def _log_abs_one_plus(a):
    if a > -0.5:
        return math.log1p(a)
    return math.log(abs(1.0 + a)) if a != -1.0 else -math.inf


def symplectic_limit(omega, rate):
    """Largest stable dt (s) of symplectic Euler on the mode: omega^2 dt^2 + 2 rate dt = 4."""
    if omega == 0:
        return math.inf
    return (math.sqrt(rate * rate + 4.0 * omega * omega) - rate) / (omega * omega)


def explicit_stable_dt(omega, rate):
    """Largest dt (s) at which explicit Euler does not amplify the mode (rho <= 1).

    Jury's conditions on the 2x2 step matrix: det <= 1, i.e. dt <= rate / omega^2,
    and 4 - 2 rate dt + omega^2 dt^2 >= 0, which cuts in first for an overdamped
    mode (rate > 2 omega) at dt = (rate - sqrt(rate^2 - 4 omega^2)) / omega^2.
    """
    if omega == 0:
        return 2.0 / rate if rate > 0 else math.inf
    limit = rate / omega ** 2
    if rate > 2.0 * omega:
        limit = min(limit, (rate - math.sqrt(rate * rate - 4.0 * omega * omega)) / omega ** 2)
    return limit


def doubling_dt(omega, rate):
    """The smallest dt (s) at which explicit Euler doubles the mode's energy within one
    second: rho(dt)^(2/dt) >= 2. Found on a geometric grid of dt (factor 2^(1/4),
    from 2^-60 / omega up), then refined by bisection in the first bracketing interval."""
    if omega == 0:
        return math.inf

    def doubles(dt):
        return 2.0 * log_explicit_growth(omega, rate, dt) >= dt * math.log(2.0)

    low = 0.0
    for k in range(-240, 80):
        high = 2.0 ** (k / 4) / omega
        if doubles(high):
            break
        low = high
    else:
        return math.inf
    for _ in range(200):
        mid = 0.5 * (low + high)
        if mid in (low, high):
            break
        low, high = (mid, high) if not doubles(mid) else (low, mid)
    return high


@dataclass(frozen=True)
class Prediction:
    """Predicted limits for a model at a state (see the module docstring). dts in s."""

    omega_max: float
    damping_rate: float
    symplectic_dt: float
    symplectic_dt_undamped: float
    explicit_doubling_dt: float
    explicit_stable_dt: float
    lanczos_iterations: int
    lanczos_residual: float

    def explicit_growth(self, dt):
        """Predicted per-step growth factor of the stiffest mode under explicit Euler."""
        return explicit_growth(self.omega_max, self.damping_rate, dt)


def predict(model: Model, positions=None, iterations=40) -> Prediction:
    spec = spectrum(model, positions, iterations)
    w, c = spec.omega_max, spec.damping_rate
    return Prediction(omega_max=w, damping_rate=c, symplectic_dt=symplectic_limit(w, c),
                      symplectic_dt_undamped=2.0 / w if w else math.inf,
                      explicit_doubling_dt=doubling_dt(w, c),
                      explicit_stable_dt=explicit_stable_dt(w, c),
                      lanczos_iterations=spec.iterations, lanczos_residual=spec.residual)
