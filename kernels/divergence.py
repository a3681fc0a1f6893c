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

import taichi as ti

OK, NONFINITE, RUNAWAY = 0, 1, 2
CAUSES = ("ok", "non-finite", "runaway")


@ti.func
def state_sums(x, v, m, g, real: ti.template()):
    """One particle's contribution (m|v|^2/2, m g.x, |x|^2 + |v|^2) to the check's sums."""
    return ti.Vector([0.5 * m * v.dot(v), m * ti.cast(g, real).dot(x), x.dot(x) + v.dot(v)], real)


def divergence_code(kinetic, gravity_sum, norm_sum, base, gx0, factor):
    """OK, NONFINITE or RUNAWAY for a state's sums (see the module docstring).

    Plain Python that is also valid Taichi code: ``check_code`` is its ``ti.func``,
    so the kernels and the Python drivers apply the same rule.
    """
    code = OK
    if not (norm_sum == norm_sum) or norm_sum > 1e308 or not (kinetic == kinetic) or kinetic > 1e308:
        code = NONFINITE
    else:
        work = gravity_sum - gx0
        if work < 0.0:
            work = 0.0
        if kinetic > factor * (base + work):
            code = RUNAWAY
    return code


check_code = ti.func(divergence_code)
