"""Per-particle constraints: which directions of a particle's velocity are prescribed.

A pinned particle's velocity is prescribed in all three directions (``prescribed``:
its pin velocity, zero for a fixed pin); an implicit step's contact prescribes the
components along the contact normals (``kernels/contact.py``). The integrators step
free particles and move pinned ones with their prescribed velocity. The implicit
solve runs on the unconstrained directions only (Baraff and Witkin's filtered CG):
every CG vector is filtered by S_i (``constrain``): the identity for a free
particle, zero for a pinned one, I - sum e e^T over the orthonormalised contact
normals e of a particle in contact; the iterate starts at the prescribed velocity in
the constrained directions, so A's columns of those directions enter the right-hand
side and Eq. 15 holds exactly on the free directions with the prescribed ones given.

Arrays read, each only when its switch is on: ``dev.free`` (n,) int32, 1 for free
particles (``cfg.fixed``: the model has pins); ``dev.pin_velocity`` (n,) vec3 m/s,
zero but at pins (``cfg.moving_pins``); ``dev.contacts`` (n,) int32 (non-zero in
contact), ``dev.cfilter`` (n,) 3x3 S_i and ``dev.cvel`` (n,) vec3 m/s, the prescribed
velocity in the constrained directions (``cfg.contact_filter``: implicit steps
with colliders).
"""

import taichi as ti


@ti.func
def is_pinned(i, dev, cfg: ti.template()):
    """Whether particle i is pinned (all three directions prescribed)."""
    out = False
    if ti.static(cfg.fixed):
        out = dev.free[i] == 0
    return out


@ti.func
def is_free(i, dev, cfg: ti.template()):
    """Whether no direction of particle i's velocity is prescribed."""
    out = True
    if ti.static(cfg.fixed):
        out = dev.free[i] != 0
    if ti.static(cfg.contact_filter):
        if dev.contacts[i] != 0:
            out = False
    return out


@ti.func
def constrain(i, dev, cfg: ti.template(), vec):
    """S_i vec: ``vec`` without its prescribed directions (zero for a pinned particle)."""
    out = vec
    if ti.static(cfg.fixed):
        if dev.free[i] == 0:
            out = ti.Vector.zero(cfg.real, 3)
    if ti.static(cfg.contact_filter):
        if dev.contacts[i] != 0:
            out = dev.cfilter[i] @ vec
    return out


@ti.func
def projector(i, dev, cfg: ti.template()):
    """S_i as a 3x3 matrix: the orthogonal projector onto particle i's free directions
    (I if free, 0 if pinned)."""
    out = ti.Matrix.identity(cfg.real, 3)
    if ti.static(cfg.fixed):
        if dev.free[i] == 0:
            out = ti.Matrix.zero(cfg.real, 3, 3)
    if ti.static(cfg.contact_filter):
        if dev.contacts[i] != 0:
            out = dev.cfilter[i]
    return out


@ti.func
def prescribed(i, dev, cfg: ti.template()):
    """The velocity (m/s) prescribed for particle i's constrained directions: the pin
    velocity of a pinned particle (0 for fixed pins), the contact velocity of a particle
    in contact (zero in its free directions)."""
    out = ti.Vector.zero(cfg.real, 3)
    if ti.static(cfg.moving_pins):
        out = dev.pin_velocity[i]
    if ti.static(cfg.contact_filter):
        if dev.contacts[i] != 0:
            out = dev.cvel[i]
    return out


@ti.func
def pin_adjoint(i, dev, cfg: ti.template(), adj, h):
    """For a pinned particle i, at the start of a step's adjoint (``massspring.gradients``):
    adds h dL/dx' + dL/dv' of the step's end state to ``adj.gp[i]``, the gradient in its
    pin velocity vp (x' = x + h vp, v' = vp, as the explicit and implicit steps move a pin)."""
    if is_pinned(i, dev, cfg):
        adj.gp[i] = adj.gp[i] + h * adj.lx[i] + adj.lv[i]
