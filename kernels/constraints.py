"""Per-particle constraints: which directions of a particle's velocity are prescribed.

A pinned particle's velocity is prescribed in all three directions (``prescribed``:
its pin velocity, zero for a fixed pin). The integrators step free particles and
move pinned ones with their prescribed velocity. The implicit solve runs on the
unconstrained directions only (Baraff and Witkin's filtered CG): every CG vector is
filtered by S_i (``constrain``), the identity for a free particle and zero for a
pinned one, and the iterate starts at the prescribed velocity there, so A's columns
of the constrained directions enter the right-hand side and Eq. 15 holds exactly on
the free directions with the prescribed ones given. Adding a kind of constraint
(contact normals: S_i = I - n n^T) means extending these functions and the arrays
they read.

Arrays read, each only when its switch is on: ``dev.free`` (n,) int32, 1 for free
particles (``cfg.fixed``: the model has pins); ``dev.pin_velocity`` (n,) vec3 m/s,
zero but at pins (``cfg.moving_pins``).
"""

import taichi as ti


@ti.func
def is_free(i, dev, cfg: ti.template()):
    """Whether no direction of particle i's velocity is prescribed."""
    out = True
    if ti.static(cfg.fixed):
        out = dev.free[i] != 0
    return out


@ti.func
def constrain(i, dev, cfg: ti.template(), vec):
    """S_i vec: ``vec`` without its prescribed directions (zero for a pinned particle)."""
    out = vec
    if ti.static(cfg.fixed):
        if dev.free[i] == 0:
            out = ti.Vector.zero(cfg.real, 3)
    return out


@ti.func
def prescribed(i, dev, cfg: ti.template()):
    """The velocity (m/s) prescribed for particle i's constrained directions: the pin
    velocity of a pinned particle (0 for fixed pins)."""
    out = ti.Vector.zero(cfg.real, 3)
    if ti.static(cfg.moving_pins):
        out = dev.pin_velocity[i]
    return out
