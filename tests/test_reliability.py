"""What a fuzzer found: non-finite checks under fast math, unbounded loops, wrapped
counts, and garbage accepted by the Model. Each test failed before its fix."""

import math
import subprocess
import sys
import textwrap

import numpy as np
import pytest
import taichi as ti

from conftest import FULL
import massspring as ms
from massspring.device import ensure_taichi
from massspring.kernels import divergence

LOOPS = ("serial", "parallel")


# ----------------------------------------------------------- non-finite checks in kernels


@pytest.fixture(scope="module")
def finite_probe():
    """A kernel reporting is_finite of values given in a field, and of 0/0, 1/0 and
    -1/0 computed at run time from that field's zeros (not foldable at compile time)."""
    ensure_taichi()
    values = ti.field(ti.f64, 8)
    singles = ti.field(ti.f32, 2)

    @ti.kernel
    def probe() -> ti.types.vector(12, ti.i32):
        zero = values[5]
        zero32 = singles[0]
        return ti.Vector([divergence.is_finite(values[k]) for k in ti.static(range(6))]
                         + [divergence.is_finite(values[6] / zero),            # 0/0: NaN computed
                            divergence.is_finite(1.0 / zero),                    # +Inf computed
                            divergence.is_finite(-1.0 / zero),                   # -Inf computed
                            divergence.is_finite(zero32 / singles[1]),           # f32 0/0
                            divergence.is_finite(values[0] * 1e300 * 1e300),     # overflow computed
                            divergence.verdict(ti.Vector([values[1], 0.0, 1.0]),  # a NaN kinetic energy
                                                  ti.Vector([1.0, 0.0, 100.0]))[0] == divergence.OK],
                         ti.i32)

    def run(given):
        values.from_numpy(np.array(list(given) + [0.0, 0.0, 0.0], dtype=np.float64)[:8])
        singles.from_numpy(np.zeros(2, dtype=np.float32))
        return probe().to_numpy()

    return run


def test_is_finite_in_a_kernel_with_nan_given_and_computed(finite_probe):
    given = [1.0, math.nan, math.inf, -math.inf, 5e-324]  # then a 0.0 at index 5
    result = finite_probe(given)
    assert list(result[:6]) == [1, 0, 0, 0, 1, 1]       # given: finite, NaN, +Inf, -Inf, denormal, 0
    assert list(result[6:11]) == [0, 0, 0, 0, 0]        # computed NaN, +Inf, -Inf, f32 NaN, overflow
    assert result[11] == 0                              # the verdict on a NaN kinetic energy is not OK


OVERFLOW_SCRIPT = textwrap.dedent("""
    import massspring as ms
    # Inputs within the Model's limits whose products overflow float64 in the kernels.
    cases = {{
        "heavy": ms.Model([[0, 0, 0]], [], masses=1e100, velocities=[[1e100, 0, 0]]),
        "far": ms.Model([[0, 0, 0], [1e99, 0, 0], [-1e99, 0, 0]], [[1, 2]], stiffness=1e100,
                        rest_lengths=0.0, gravity=(0, 0, 0)),
    }}
    for name, model in cases.items():
        for integrator in ("explicit", "symplectic", "implicit"):
            sim = ms.Simulation(model, integrator=integrator, loops="{loops}")
            try:
                sim.step(20)
                print(name, integrator, "no-error")
            except ms.DivergenceError as exc:
                import numpy as np
                finite = np.isfinite(sim.positions).all() and np.isfinite(sim.velocities).all()
                print(name, integrator, exc.cause, exc.step, finite)
""")


@FULL
@pytest.mark.parametrize("loops", LOOPS)
def test_overflow_ends_in_divergence_error_never_a_hang_or_nan_state(loops):
    # In a subprocess with a time limit: the bug was an endless loop inside a kernel.
    proc = subprocess.run([sys.executable, "-c", OVERFLOW_SCRIPT.format(loops=loops)],
                          capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0, proc.stderr
    lines = proc.stdout.split("\n")
    for name in ("heavy", "far"):
        for integrator in ("explicit", "symplectic", "implicit"):
            line = next(line for line in lines if line.startswith(f"{name} {integrator} "))
            words = line.split()
            if name == "heavy" and integrator != "implicit":
                continue  # free flight at 1e100 m/s: finite for 20 steps, no force to overflow
            assert words[2] == "non-finite" and words[4] == "True", line


def test_implicit_overflowing_right_hand_side_is_reported():
    sim = ms.Simulation(ms.Model([[0, 0, 0]], [], masses=1e100, velocities=[[1e100, 0, 0]]),
                        integrator="implicit")
    with pytest.raises(ms.DivergenceError) as info:
        sim.step(1)
    assert info.value.cause == "non-finite" and sim.steps == 0
    assert sim.solver_stats.reason == "non-finite" and not sim.solver_stats.converged
    assert np.array_equal(sim.positions, [[0.0, 0.0, 0.0]])


# ------------------------------------------------------------------- counts beyond int32


@pytest.mark.fast_sample(integrator=["symplectic"])
@pytest.mark.parametrize("n", [2**32 + 3, 2**31])
@pytest.mark.parametrize("integrator", ["explicit", "symplectic"])
def test_step_counts_beyond_int32_are_not_wrapped(n, integrator):
    # Far above the stability limit, the run must diverge within a few dozen steps: a
    # count wrapped to 3 (2**32 + 3) or to a negative number (2**31) would return quietly.
    from massspring.analysis import stability

    scene = ms.load_scene("stiffchain").with_params(count=6)
    sim = scene.simulation(integrator, dt=1.5 * stability.predict(scene.model()).symplectic_dt)
    with pytest.raises(ms.DivergenceError) as info:
        sim.step(n)
    assert 10 < info.value.step < 1000 and sim.steps == info.value.step - 1


def test_cg_max_iter_beyond_int32_refused():
    model = ms.Model([[0, 0, 0], [1, 0, 0]], [[0, 1]])
    with pytest.raises(ValueError, match="^cg_max_iter"):
        ms.Simulation(model, cg_max_iter=2**32 + 1)
    with pytest.raises(ValueError, match="^cg_max_iter"):
        ms.Simulation(model, cg_max_iter=2**31)


# ------------------------------------------------------------------- garbage in the Model

POS = [[0.0, 0.0, 0.0], [1.0, 0.0, 0.0]]


@pytest.mark.parametrize("name, kwargs", [
    ("positions", dict(positions=None)),
    ("positions", dict(positions=[[0, 0, 1j], [1, 0, 0]])),
    ("positions", dict(positions=[["0", "0", "0"], ["1", "0", "0"]])),
    ("positions", dict(positions=[[0, 0, 0], [1e308, 0, 0]])),
    ("positions", dict(positions=[[0, 0, 0], [1, 0]])),
    ("masses", dict(masses="2.5")),
    ("masses", dict(masses=True)),
    ("masses", dict(masses=5e-324)),
    ("masses", dict(masses=1e200)),
    ("stiffness", dict(stiffness=True)),
    ("stiffness", dict(stiffness=1e101)),
    ("damping", dict(damping=-1.0, springs=[])),
    ("rest_lengths", dict(rest_lengths=-1.0, springs=[])),
    ("velocities", dict(velocities=[[0, 0, 0], [2j, 0, 0]])),
    ("gravity", dict(gravity=("0", "0", "-9.81"))),
    ("gravity", dict(gravity=(0, 0, -1e200))),
], ids=lambda value: value if isinstance(value, str) else "")
def test_model_refuses_garbage_naming_the_argument(name, kwargs):
    args = dict(positions=POS, springs=[[0, 1]])
    args.update(kwargs)
    with pytest.raises(ValueError) as info:
        ms.Model(**args)
    assert str(info.value).startswith(name + ":"), str(info.value)
