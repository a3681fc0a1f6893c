"""Reference solutions that runs are measured against: exact where one exists, else RK4.

* ``exact_spring``: one spring with one end fixed, moving along its own axis,
  is the continuous damped oscillator m u'' = -ks u - kd u' + m g_e of the
  displacement u = |x1 - x0| - l0 (seed Eq. 1-4 restricted to the axis e): solved in
  closed form.
* ``rk4``: any model, integrated by classical RK4 in float64 (the ``rk4``
  integrator) and cached on disk (``cache_dir``), keyed by a hash of the model's
  arrays, the save instants and the RK4 dt.

A reference is a :class:`Trajectory`: positions and velocities at the save instants.
"""

from __future__ import annotations

import hashlib
import math
import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from massspring.support import validate
from massspring.integrators import REFERENCE
from massspring.io.files import atomic_output
from massspring.model import Model

CACHE_ENV = "MASSSPRING_CACHE"
CACHE_FORMAT = b"massspring-rk4-v3"


@dataclass(frozen=True)
class Trajectory:
    """States at the save instants.

    times (k,) s; positions, velocities (k, n, 3) in m and m/s; ``method`` names how
    it was computed ("exact" or "rk4"), ``dt`` the RK4 step (s; None if exact).
    """

    times: np.ndarray
    positions: np.ndarray
    velocities: np.ndarray
    method: str
    dt: float | None = None


def cache_dir(override=None) -> Path:
    """Where RK4 references are cached: ``override``, else $MASSSPRING_CACHE, else
    $XDG_CACHE_HOME/massspring, else ~/.cache/massspring."""
    if override:
        return Path(override)
    if os.environ.get(CACHE_ENV):
        return Path(os.environ[CACHE_ENV])
    base = os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache"
    return Path(base) / "massspring"


def steps_between(times, dt, name="times") -> np.ndarray:
    """Whole numbers of ``dt`` steps from 0 to each instant of ``times`` (increasing, > 0).

    Raises ValueError naming ``name`` if an instant is not a multiple of dt (to 1e-9 relative).
    """
    times = np.asarray(times, dtype=np.float64)
    if times.ndim != 1 or times.size == 0 or not np.all(np.isfinite(times)) or times[0] <= 0 \
            or np.any(np.diff(times) <= 0):
        raise ValueError(f"{name}: expected increasing instants > 0, got {times!r}")
    counts = np.rint(times / dt)
    if np.any(np.abs(counts * dt - times) > 1e-9 * times):
        raise ValueError(f"{name}: every instant must be a whole number of steps of dt = {dt:g} s")
    return counts.astype(np.int64)


def exact_spring(model: Model, times) -> Trajectory | None:
    """The exact continuous motion of a one-spring model, or None if it has none here.

    Applies when the model has 2 particles, 1 spring, exactly one of the two fixed
    (and still), no air and no collider, the free particle's velocity and its uniform
    acceleration (``Model.external_acceleration``: gravity and any other such term)
    along the spring's axis (so the motion stays on the axis), and the spring keeps a
    positive length at every instant.
    """
    if model.n_particles != 2 or model.n_springs != 1 or model.fixed.size != 1 or model.has_drag \
            or model.has_colliders or model.has_moving_pins:
        return None
    pinned = int(model.fixed[0])
    moving = 1 - pinned
    d = model.positions[moving] - model.positions[pinned]
    length = float(np.linalg.norm(d))
    if length == 0.0:
        return None
    axis = d / length
    w0 = float(model.velocities[moving] @ axis)
    external = model.external_acceleration
    g = float(external @ axis)
    scale = 1e-12
    if np.linalg.norm(model.velocities[moving] - w0 * axis) > scale * (1 + abs(w0)) or \
            np.linalg.norm(external - g * axis) > scale * (1 + abs(g)):
        return None
    times = np.asarray(times, dtype=np.float64)
    u, w = damped_oscillator(length - model.rest_lengths[0], w0, model.masses[moving],
                             model.stiffness[0], model.damping[0], g, times)
    if np.any(model.rest_lengths[0] + u <= 0):
        return None
    k = times.size
    positions = np.broadcast_to(model.positions, (k, 2, 3)).copy()
    velocities = np.zeros((k, 2, 3))
    positions[:, moving] = model.positions[pinned] + (model.rest_lengths[0] + u)[:, None] * axis
    velocities[:, moving] = w[:, None] * axis
    return Trajectory(times, positions, velocities, "exact")


def damped_oscillator(u0, w0, m, ks, kd, g, t):
    """u(t), w(t) of m u'' = -ks u - kd u' + m g with u(0) = u0, u'(0) = w0 (closed form).

    All regimes: under-, critically and over-damped, and ks = 0. t is an array (s).
    """
    t = np.asarray(t, dtype=np.float64)
    if ks == 0:
        if kd == 0:
            return u0 + w0 * t + 0.5 * g * t * t, w0 + g * t
        c = kd / m
        terminal = g / c
        decay = np.exp(-c * t)
        return u0 + terminal * t + (w0 - terminal) * (1 - decay) / c, terminal + (w0 - terminal) * decay
    shift = m * g / ks  # equilibrium displacement
    s0 = u0 - shift
    disc = kd * kd - 4 * m * ks
    if disc < 0:
        alpha = kd / (2 * m)
        omega = math.sqrt(-disc) / (2 * m)
        c2 = (w0 + alpha * s0) / omega
        decay = np.exp(-alpha * t)
        cos, sin = np.cos(omega * t), np.sin(omega * t)
        s = decay * (s0 * cos + c2 * sin)
        w = decay * (w0 * cos - (alpha * c2 + omega * s0) * sin)
    elif disc == 0:
        r = -kd / (2 * m)
        growth = np.exp(r * t)
        c2 = w0 - r * s0
        s = (s0 + c2 * t) * growth
        w = (c2 + r * (s0 + c2 * t)) * growth
    else:
        root = math.sqrt(disc)
        r1, r2 = (-kd + root) / (2 * m), (-kd - root) / (2 * m)
        a = (w0 - r2 * s0) / (r1 - r2)
        b = s0 - a
        e1, e2 = np.exp(r1 * t), np.exp(r2 * t)
        s = a * e1 + b * e2
        w = a * r1 * e1 + b * r2 * e2
    return s + shift, w


def rk4(model: Model, times, dt, cache=None, use_cache=True) -> Trajectory:
    """Classical RK4 in float64 at step ``dt`` (s), states at ``times`` (multiples of dt).

    Cached under ``cache_dir(cache)`` (written atomically) unless ``use_cache`` is False.
    """
    dt = validate.positive_float("dt", dt)
    counts = steps_between(times, dt)
    times = np.asarray(times, dtype=np.float64)
    path = cache_dir(cache) / f"rk4-{_cache_key(model, times, dt)}.npz"
    if use_cache and path.is_file():
        try:
            with np.load(path) as data:
                positions, velocities = data["positions"], data["velocities"]
            if positions.shape == velocities.shape == (times.size, model.n_particles, 3):
                return Trajectory(times, positions, velocities, REFERENCE, dt)
        except (OSError, ValueError, KeyError):
            pass  # unreadable: recompute and overwrite
    positions, velocities = _integrate(model, counts, dt)
    if use_cache:
        path.parent.mkdir(parents=True, exist_ok=True)
        with atomic_output(path) as fh:
            np.savez(fh, times=times, positions=positions, velocities=velocities, dt=dt)
    return Trajectory(times, positions, velocities, REFERENCE, dt)


def _integrate(model, counts, dt):
    from massspring.engine.simulation import Simulation

    sim = Simulation(model, integrator=REFERENCE, dt=dt, precision="f64")
    positions, velocities = [], []
    for count in counts:
        sim.step(int(count - sim.steps))
        positions.append(sim.positions)
        velocities.append(sim.velocities)
    sim.close()
    return np.array(positions), np.array(velocities)


def _cache_key(model, times, dt):
    digest = hashlib.sha256(CACHE_FORMAT)
    digest.update(model.fingerprint().encode())
    digest.update(np.ascontiguousarray(times, dtype=np.float64).tobytes())
    digest.update(repr(float(dt)).encode())
    return digest.hexdigest()[:32]
