"""Explicit and symplectic Euler steps per second on the cloth scene, against peers.

massspring runs in f64 (the default) or f32, or both (``--precision f32 f64``);
every row is tagged with its "precision". Peers in the same run, on the same
model, from the same start state:

* numpy (f64 rows): a NumPy vectorised step (bincount scatter, which sums in f64).
* warp (if `warp-lang` is installed, 1.9.x: `pip install "warp-lang==1.9.*"`):
  hand-written Warp kernels of the same spring forces on Warp's CPU backend (an
  atomic scatter over springs, as warp.sim does), in the row's precision.
* warp.sim (symplectic f32 rows): Warp 1.9's own
  ``warp.sim.SemiImplicitIntegrator().simulate(model, state_in, state_out, dt)``
  on a ``warp.sim.ModelBuilder`` model of the same cloth, finalized on "cpu":
  the same positions, masses, springs (ks, kd, rest lengths) and gravity;
  pinned particles get zero mass and no PARTICLE_FLAG_ACTIVE, as warp.sim's
  ``add_cloth_grid`` pins them; no ground, particle or shape contacts, no
  triangles, bending, tetrahedra or bodies, so ``simulate`` launches only
  ``eval_springs`` and ``integrate_particles`` (checked before timing). Its
  spring damping, kd ((v_i - v_j) . d) along d = (x_i - x_j) / |x_i - x_j|, is
  massspring's kd ((v_j - v_i) . n) with n = -d. warp.sim is float32 only
  and has no explicit Euler, hence symplectic f32 rows only. It is
  deprecated in Warp 1.9 (its import warning is hidden here, and a note printed);
  if ``import warp.sim`` fails the peer is skipped with a message. Issue 10's
  target: massspring's symplectic cloth step at least 2x faster than this peer
  at 128^2 and 256^2, f32, springs only: a warp.sim ratio >= 2.

Each case is timed in ``--repeats`` rounds, every round timing massspring and each
peer once in turn (so the machine's drift hits all alike); steps/s come from the
median round, a peer's "ratio" is the median over the rounds of its time /
massspring's (> 1: massspring is faster), with their range. After the timed steps each peer's displacements from the start state
must agree with massspring's: to 1e-9 of the largest displacement in f64 rows,
to 1e-5 of it in f32 rows (TOLERANCE: two f32 runs that sum the spring forces in
different orders part by up to 2e-6 of it, measured with explicit Euler at 128^2). f32 peers are held to f32 massspring,
not to f64: at these small dt an f32 run loses a part of its displacement to
rounding (some 5% at 32^2), alike on both sides; what differs is the order in
which spring forces are summed (1e-10 to 2e-6), while a 0.1% change of g or kd
in the warp.sim model moves it by 1e-3 or more (32^2, 151 steps); a 0.1% change
of ks (8e-6) is below what f32 can tell apart here.

    python benchmarks/explicit_step.py --help
    python benchmarks/explicit_step.py --resolutions 32 64 128 --steps 200
    python benchmarks/explicit_step.py --precision f32 f64     # the table of docs/performance.md

(plot_performance.py tabulates every row with its precision and plots the f32 ones.)
"""

import argparse
import contextlib
import io
import statistics
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
import peers  # noqa: E402

import massspring as ms  # noqa: E402
from massspring.io.files import write_json  # noqa: E402
import output  # noqa: E402

TOLERANCE = {"f64": 1e-9, "f32": 1e-5}  # largest displacement difference / largest displacement
TARGET_RATIO = 2.0  # issue 10: warp.sim time per step / massspring's, symplectic f32


def time_step(resolution):
    """dt (s) well inside the explicit limit, which shrinks as 1 / resolution."""
    return 2e-4 / resolution


def parse_args(argv=None):
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--resolutions", type=int, nargs="+", default=[32, 64, 128, 256])
    p.add_argument("--integrators", nargs="+", default=["explicit", "symplectic"],
                   choices=["explicit", "symplectic"])
    p.add_argument("--precision", nargs="+", default=["f64"], choices=["f64", "f32"],
                   help="massspring's precision; several run each (rows tagged). "
                        "warp.sim runs in f32 rows only (default: f64)")
    p.add_argument("--steps", type=int, default=200, help="steps per timed run")
    p.add_argument("--repeats", type=int, default=5, help="interleaved rounds per case (medians reported)")
    p.add_argument("--no-warp", action="store_true", help="skip both Warp peers (warp and warp.sim)")
    output.add_json(p, "explicit_step")
    return p.parse_args(argv)


def interleaved(contestants, repeats):
    """Seconds of each of ``repeats`` rounds, per contestant (name -> callable), after one
    untimed round (a first call of a run of many steps may still compile): every round
    times each contestant once, in turn, so the machine's drift hits all alike."""
    seconds = {name: [] for name in contestants}
    for timed in [False] + [True] * repeats:
        for name, fn in contestants.items():
            t0 = time.perf_counter()
            fn()
            if timed:
                seconds[name].append(time.perf_counter() - t0)
    return seconds


class WarpEuler:
    """Explicit / symplectic Euler with hand-written Warp kernels on the CPU, in
    ``precision`` "f64" (float64) or "f32" (float32)."""

    def __init__(self, model, symplectic, precision):
        import warp as wp

        wp.config.quiet = True
        wp.init()
        self.wp = wp
        self.symplectic = symplectic
        self.model = model
        vec, real = (wp.vec3d, wp.float64) if precision == "f64" else (wp.vec3f, wp.float32)
        self.real = real
        dev = "cpu"
        self.x = wp.array(model.positions, dtype=vec, device=dev)
        self.v = wp.array(model.velocities, dtype=vec, device=dev)
        self.f = wp.zeros(model.n_particles, dtype=vec, device=dev)
        self.springs = wp.array(model.springs.astype(np.int32), dtype=wp.vec2i, device=dev)
        self.ks = wp.array(model.stiffness, dtype=real, device=dev)
        self.kd = wp.array(model.damping, dtype=real, device=dev)
        self.l0 = wp.array(model.rest_lengths, dtype=real, device=dev)
        self.inv_mass = wp.array(np.where(model.free_mask(), 1.0 / model.masses, 0.0), dtype=real, device=dev)
        self.mass = wp.array(model.masses, dtype=real, device=dev)
        self.g = vec(*model.gravity)
        self.kernels = _warp_kernels(wp, precision)

    def step(self, dt, steps):
        """``steps`` steps of ``dt`` seconds."""
        wp = self.wp
        springs_k, integrate_k = self.kernels
        for _ in range(steps):
            self.f.zero_()
            wp.launch(springs_k, dim=self.model.n_springs, device="cpu",
                      inputs=[self.x, self.v, self.springs, self.ks, self.kd, self.l0, self.f])
            wp.launch(integrate_k, dim=self.model.n_particles, device="cpu",
                      inputs=[self.x, self.v, self.f, self.mass, self.inv_mass, self.g, self.real(dt),
                              int(self.symplectic)])
        wp.synchronize()

    def positions(self):
        """(n, 3) float64 positions (m)."""
        return self.x.numpy().astype(np.float64)


_WARP_KERNELS = {}


def _warp_kernels(wp, precision):
    """(spring forces, integrate) kernels for vectors and scalars of ``precision``."""
    if precision in _WARP_KERNELS:
        return _WARP_KERNELS[precision]
    vec, real = (wp.vec3d, wp.float64) if precision == "f64" else (wp.vec3f, wp.float32)

    @wp.kernel
    def eval_springs(x: wp.array(dtype=vec), v: wp.array(dtype=vec), springs: wp.array(dtype=wp.vec2i),
                     ks: wp.array(dtype=real), kd: wp.array(dtype=real),
                     l0: wp.array(dtype=real), f: wp.array(dtype=vec)):
        s = wp.tid()
        i = springs[s][0]
        j = springs[s][1]
        d = x[j] - x[i]
        length = wp.length(d)
        if length > real(1e-12):
            n = d / length
            mag = ks[s] * (length - l0[s]) + kd[s] * wp.dot(v[j] - v[i], n)
            wp.atomic_add(f, i, mag * n)
            wp.atomic_sub(f, j, mag * n)

    @wp.kernel
    def integrate(x: wp.array(dtype=vec), v: wp.array(dtype=vec), f: wp.array(dtype=vec),
                  mass: wp.array(dtype=real), inv_mass: wp.array(dtype=real), g: vec,
                  dt: real, symplectic: int):
        i = wp.tid()
        if inv_mass[i] > real(0.0):
            v_new = v[i] + dt * inv_mass[i] * (f[i] + mass[i] * g)
            if symplectic == 1:
                x[i] = x[i] + dt * v_new
            else:
                x[i] = x[i] + dt * v[i]
            v[i] = v_new

    _WARP_KERNELS[precision] = (eval_springs, integrate)
    return _WARP_KERNELS[precision]


def import_warp_sim():
    """``warp.sim``, or None (with a message) if it cannot be imported.

    Warp 1.9 prints a DeprecationWarning on stdout when warp.sim is first
    imported; it is captured here and replaced by a one-line note."""
    try:
        import warp as wp

        wp.config.quiet = True
        with contextlib.redirect_stdout(io.StringIO()) as captured:
            import warp.sim as warp_sim
    except Exception as exc:  # ImportError, or warp.sim failing on import
        print(f"warp.sim unavailable ({type(exc).__name__}: {exc}): skipping the warp.sim peer")
        return None
    if "deprecated" in captured.getvalue():
        print("note: warp.sim is deprecated in Warp 1.9 (its import warning is hidden here)")
    return warp_sim


class WarpSimCloth:
    """``model`` stepped by Warp's own warp.sim SemiImplicitIntegrator (float32, CPU).

    The ModelBuilder copy has the same particle positions (m), velocities (m/s) and
    masses (kg); pinned particles with mass 0 and PARTICLE_FLAG_ACTIVE cleared (so
    ``integrate_particles`` keeps their position and sets their velocity to 0), as
    ``ModelBuilder.add_cloth_grid`` pins; particle radius 0 (no particle-particle
    contacts); one spring per massspring spring with the same ks (N/m), kd (N s/m)
    and rest length (m); gravity (m/s^2) through the builder's up vector; the
    velocity clamp ``particle_max_velocity`` at 1e30 m/s (never reached); and
    ``model.ground = False``. Models with pin velocities, colliders or drag have no
    counterpart here.
    """

    def __init__(self, model, warp_sim):
        import warp as wp

        if np.any(model.pin_velocity != 0) or model.has_colliders or model.has_drag:
            raise ValueError("warp.sim peer: only models with static pins, no colliders and no drag")
        wp.init()
        self.wp = wp
        g = np.asarray(model.gravity, dtype=np.float64)
        g_norm = float(np.linalg.norm(g))
        up = tuple(float(c) for c in -g / g_norm) if g_norm > 0 else (0.0, 1.0, 0.0)
        builder = warp_sim.ModelBuilder(up_vector=up, gravity=-g_norm)  # gravity = up * (-|g|) = g
        builder.particle_max_velocity = 1e30
        free = model.free_mask()
        for i in range(model.n_particles):
            position = tuple(float(c) for c in model.positions[i])
            if free[i]:
                builder.add_particle(position, tuple(float(c) for c in model.velocities[i]),
                                     float(model.masses[i]), radius=0.0)
            else:
                builder.add_particle(position, (0.0, 0.0, 0.0), 0.0, radius=0.0,
                                     flags=wp.uint32(0))  # PARTICLE_FLAG_ACTIVE cleared
        for s, (i, j) in enumerate(model.springs):
            builder.add_spring(int(i), int(j), float(model.stiffness[s]), float(model.damping[s]), 0.0)
        # add_spring takes the initial distance as rest length: use massspring's instead
        builder.spring_rest_length = [float(length) for length in model.rest_lengths]
        self.model = builder.finalize(device="cpu")
        self.model.ground = False
        _check_springs_only(self.model, model)
        self.integrator = warp_sim.SemiImplicitIntegrator()
        self.state = self.model.state()
        self.next_state = self.model.state()

    def step(self, dt, steps):
        """``steps`` steps of ``dt`` seconds, as warp.sim's examples run them."""
        for _ in range(steps):
            self.state.clear_forces()
            self.integrator.simulate(self.model, self.state, self.next_state, dt)
            self.state, self.next_state = self.next_state, self.state
        self.wp.synchronize()

    def positions(self):
        """(n, 3) float64 positions (m)."""
        return self.state.particle_q.numpy().astype(np.float64)


def _check_springs_only(wmodel, model):
    """Raise unless ``warp.sim``'s ``compute_forces`` would evaluate springs alone on
    ``wmodel`` (the conditions it tests before each launch) and gravity matches."""
    skipped = {
        "triangles": wmodel.tri_count == 0 and not wmodel.enable_tri_collisions,
        "bending": wmodel.edge_count == 0,
        "tetrahedra": wmodel.tet_count == 0,
        "bodies and joints": wmodel.body_count == 0 and wmodel.joint_count == 0,
        "muscles": wmodel.muscle_count == 0,
        "particle contacts": wmodel.particle_max_radius == 0.0,
        "ground contacts": not wmodel.ground,
        "shape contacts": wmodel.shape_count <= 1 and wmodel.rigid_contact_max == 0,  # 1: the unused ground plane
    }
    wrong = [name for name, ok in skipped.items() if not ok]
    if wmodel.particle_count != model.n_particles or wmodel.spring_count != model.n_springs:
        wrong.append("particle or spring count")
    if not np.allclose(np.asarray(wmodel.gravity, dtype=np.float64), model.gravity, rtol=1e-6, atol=1e-6):
        wrong.append(f"gravity {wmodel.gravity} != {model.gravity}")
    if wrong:
        raise RuntimeError("warp.sim model is not springs + gravity only: " + ", ".join(wrong))


def run_case(args, resolution, precision, integrator, have_warp, warp_sim):
    scene = ms.load_scene("cloth").with_params(resolution=resolution)
    model = scene.model()
    symplectic = integrator == "symplectic"
    steps = args.steps
    dt = time_step(resolution)
    sim = ms.Simulation(model, integrator=integrator, dt=dt, precision=precision)
    t0 = time.perf_counter()
    sim.step(1)
    first = time.perf_counter() - t0
    contestants = {"massspring": lambda: sim.step(steps)}
    positions = {}
    if precision == "f64":
        x, v = model.positions.copy(), model.velocities.copy()

        def numpy_run(count):
            nonlocal x, v
            for _ in range(count):
                x, v = peers.numpy_euler_step(model, x, v, dt, symplectic)

        numpy_run(1)
        contestants["numpy"] = lambda: numpy_run(steps)
        positions["numpy"] = lambda: x
    if have_warp:
        w = WarpEuler(model, symplectic, precision)
        w.step(dt, 1)
        contestants["warp"] = lambda: w.step(dt, steps)
        positions["warp"] = w.positions
    if warp_sim is not None and precision == "f32" and symplectic:
        ws = WarpSimCloth(model, warp_sim)
        ws.step(dt, 1)
        contestants["warp.sim"] = lambda: ws.step(dt, steps)
        positions["warp.sim"] = ws.positions
    seconds = interleaved(contestants, args.repeats)
    ours = statistics.median(seconds["massspring"])
    total_steps = 1 + steps * (args.repeats + 1)
    row = {"resolution": resolution, "precision": precision, "integrator": integrator, "springs": model.n_springs,
           "steps": steps, "dt": dt, "loops": sim.loops, "steps_per_s": steps / ours, "compile_s": first,
           "tolerance": TOLERANCE[precision], "peers": {}}
    for name, get in positions.items():
        ratios = [theirs / mine for theirs, mine in zip(seconds[name], seconds["massspring"])]
        row["peers"][name] = {"steps_per_s": steps / statistics.median(seconds[name]),
                              "ratio": statistics.median(ratios), "ratio_range": [min(ratios), max(ratios)],
                              "max_rel_diff": _rel_diff(get(), sim.positions, model.positions)}
    assert sim.steps == total_steps
    return row


def _rel_diff(a, b, start):
    """Largest difference of two runs' displacements from ``start``, relative to the largest displacement."""
    return float(np.max(np.abs(a - b)) / np.max(np.abs(b - start)))


def main(argv=None):
    args = parse_args(argv)
    have_warp, warp_sim = False, None
    if not args.no_warp:
        try:
            import warp

            warp.config.quiet = True
            warp.init()  # once, before the table (it may print a note about CUDA)
            have_warp = True
        except ImportError:
            print("warp-lang not installed: skipping the Warp peers (pip install 'warp-lang==1.9.*')")
    if have_warp and "f32" in args.precision and "symplectic" in args.integrators:
        warp_sim = import_warp_sim()
    print(f"{'res':>5s} {'prec':>4s} {'integrator':>10s} {'springs':>8s} {'steps/s':>10s} "
          f"{'warp.sim/s':>10s} {'ratio':>6s} {'diff':>8s}  other peers (steps/s, ratio, max rel. diff)")
    rows, failures = [], []
    for resolution in args.resolutions:
        for precision in args.precision:
            for integrator in args.integrators:
                row = run_case(args, resolution, precision, integrator, have_warp, warp_sim)
                rows.append(row)
                ws = row["peers"].get("warp.sim")
                ws_text = (f"{ws['steps_per_s']:10.0f} {ws['ratio']:6.2f} {ws['max_rel_diff']:8.1e}" if ws
                           else f"{'-':>10s} {'-':>6s} {'-':>8s}")
                text = "  ".join(f"{name} {p['steps_per_s']:.0f} ({p['ratio']:.1f}x, {p['max_rel_diff']:.1e})"
                                 for name, p in row["peers"].items() if name != "warp.sim")
                print(f"{resolution:5d} {precision:>4s} {integrator:>10s} {row['springs']:8d} "
                      f"{row['steps_per_s']:10.0f} {ws_text}  {text}", flush=True)
                for name, p in row["peers"].items():
                    if not p["max_rel_diff"] <= row["tolerance"]:
                        failures.append(f"res {resolution} {precision} {integrator}: {name} differs by "
                                        f"{p['max_rel_diff']:.2e} (tolerance {row['tolerance']:.0e})")
    write_json(args.json, {"rows": rows})
    print(f"wrote {args.json}")
    for row in rows:
        if "warp.sim" in row["peers"]:
            ratio = row["peers"]["warp.sim"]["ratio"]
            verdict = "met" if ratio >= TARGET_RATIO else "not met"
            low, high = row["peers"]["warp.sim"]["ratio_range"]
            print(f"issue 10 target (warp.sim ratio >= {TARGET_RATIO:g}), res {row['resolution']}: "
                  f"{ratio:.2f} (rounds: {low:.2f}-{high:.2f}; {verdict})")
    for f in failures:
        print("CHECK FAILED:", f)
    return 1 if failures else 0


if __name__ == "__main__":
    sys.exit(main())
