"""The per-step divergence check, fused into the kernels that write a new state.

Each stepping kernel reduces, over the new state's particles, the three sums of
``state_sums``: kinetic energy sum(m |v|^2 / 2) [J], sum(m g . x) [J] (minus its
initial value this is the work gravity has done), and sum(|x|^2 + |v|^2), which
is finite exactly when every position and velocity is. ``divergence_code`` then
classifies the state against the bound

    kinetic <= factor * (base + max(0, sum(m g . x) - gx0))

where ``check = (base, gx0, factor)`` comes from ``Simulation`` (base: initial
kinetic + spring energy plus a floor derived from the scene's size; gx0: initial
sum(m g . x)). For the physical, damped system kinetic <= base - floor + work of
gravity, so a state above ``factor`` times that bound is numerical runaway.
"""

import math

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
def state_sums(x, v, m, g, real: ti.template()):
    """One particle's contribution (m|v|^2/2, m g.x, |x|^2 + |v|^2) to the check's sums."""
    return ti.Vector([0.5 * m * v.dot(v), m * ti.cast(g, real).dot(x), x.dot(x) + v.dot(v)], real)


def classify(finite, kinetic, gravity_sum, base, gx0, factor):
    """OK, NONFINITE or RUNAWAY for a state's sums (see the module docstring);
    ``finite``: whether the sums are finite (``is_finite`` in kernels, ``math.isfinite``
    in Python). Plain Python that is also valid Taichi code: ``classify_func`` is
    its ``ti.func``, so the kernels and the Python drivers apply the same rule.
    """
    code = OK
    if not finite:
        code = NONFINITE
    else:
        work = gravity_sum - gx0
        if work < 0.0:
            work = 0.0
        if kinetic > factor * (base + work):
            code = RUNAWAY
    return code


classify_func = ti.func(classify)


def divergence_code(kinetic, gravity_sum, norm_sum, base, gx0, factor):
    """``classify`` of sums returned to Python by a kernel."""
    finite = math.isfinite(kinetic) and math.isfinite(norm_sum)
    return classify(finite, kinetic, gravity_sum, base, gx0, factor)


@ti.func
def check_code(kinetic, gravity_sum, norm_sum, base, gx0, factor):
    """``divergence_code`` inside a kernel."""
    return classify_func(is_finite(kinetic) and is_finite(norm_sum), kinetic, gravity_sum, base, gx0, factor)
