"""Non-finite tests and the per-step divergence check, fused into the kernels
that write a new state.

Each stepping kernel reduces, over the new state's particles, the three sums of
``state_sums``: kinetic energy sum(m |v|^2 / 2) [J], sum(m g . x) [J] with g the
sum of the uniform accelerations (``terms.uniform_acceleration``: gravity and any
other ``uniform`` term; minus its initial value this is the work they have done),
and sum(|x|^2 + |v|^2), which is finite exactly when every position and velocity
is. ``verdict`` classifies the state against the bound

    kinetic <= factor * (base + max(0, sum(m g . x) - gx0))

where ``dev.check = (base, gx0, factor)`` comes from ``Simulation`` (base: initial
kinetic + spring energy plus a floor derived from the scene's size; gx0: initial
sum(m g . x), ``Model.external_work``). For the physical, damped system kinetic <=
base - floor + work of the uniform forces, so a state above ``factor`` times that
bound is numerical runaway.
"""

import taichi as ti

OK, NONFINITE, RUNAWAY = 0, 1, 2
CAUSES = ("ok", "non-finite", "runaway")
_EXPONENT = 0x7FF0000000000000  # float64 exponent bits: all ones for NaN and +-Inf


@ti.func
def is_finite(x):
    """True unless ``x`` (a float scalar) is NaN or +-Inf, tested on its float64 bits.

    Comparisons cannot do this in kernels: Taichi compiles with fast math, under
    which ``x == x`` and ``x < inf`` are folded to True before they run.
    """
    bits = ti.bit_cast(ti.cast(x, ti.f64), ti.u64)
    return (bits & ti.u64(_EXPONENT)) != ti.u64(_EXPONENT)


@ti.func
def state_sums(x, v, m, g, with_uniform: ti.template()):
    """One particle's (m|v|^2/2, m g.x, |x|^2 + |v|^2) in float64 (``g`` a float64 vec3)."""
    x64 = ti.cast(x, ti.f64)
    v64 = ti.cast(v, ti.f64)
    m64 = ti.cast(m, ti.f64)
    work = 0.0
    if ti.static(with_uniform):
        work = m64 * g.dot(x64)
    return ti.Vector([0.5 * m64 * v64.dot(v64), work, x64.dot(x64) + v64.dot(v64)], ti.f64)


@ti.func
def verdict(sums, check):
    """(code, kinetic energy J, bound J) of a new state, a float64 vec3: ``code`` is OK,
    NONFINITE or RUNAWAY for its summed ``state_sums`` (float64 vec3) against
    ``check = (base, gx0, factor)``, and ``bound`` the kinetic energy that state was
    allowed (it depends on the state: the uniform forces' work is measured to its positions)."""
    code = OK
    bound = check[2] * (check[0] + ti.max(sums[1] - check[1], 0.0))
    if not (is_finite(sums[0]) and is_finite(sums[2])):
        code = NONFINITE
    elif sums[0] > bound:
        code = RUNAWAY
    return ti.Vector([code, sums[0], bound], ti.f64)


NONFINITE_VERDICT = (NONFINITE, float("inf"), float("nan"))  # a solve that overflowed before any state
