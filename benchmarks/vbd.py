"""massspring against Newton's VBD cloth solver on the CPU: error at t = 1 s per CPU second.

Newton is PyPI ``newton`` 1.8.0 on NVIDIA Warp; both engines run on the CPU, each error is
measured against two converged references.

What it measures, per run of each case (the same physical system in both engines):

- CPU seconds per simulated second (``time.process_time()`` around the stepping only; each
  run is first warmed up by one step of the same kind, which compiles: Taichi kernels for
  massspring, Warp modules for Newton) and wall seconds;
- the largest spring strain over the run, max over the 1/60 s frames of
  max(|x_j - x_i| / l0 - 1) on massspring's spring list (VBD is given the same list);
- the deepest penetration of a particle into the sphere and into the ground over the frames;
- for ``sheets``, the crossings (an edge through a triangle it shares no particle with,
  ``tests/crossings.py``) at every sixth frame (0.1 s apart);
- the error at t = 1 s against two references, RMS and largest distance over all particles:
  (a) massspring backward Euler at dt = 1/6000 s with cg_tol 1e-8 and newton_tol 1e-6,
  (b) Newton VBD at 60 substeps x 20 iterations per 1/60 s frame;
  and the RMS error at t = 0.25 s (just after the cloth meets the sphere) against both.

Runs: massspring ``implicit`` and ``backward-euler`` at dt 1/60, 1/120, 1/240 and 1/600 s with
the scene's settings (the drape's strain limit 0.1 included), ``implicit`` at 1/60 without
the strain limit (drapes), ``symplectic`` at dt 1/12000, 1/24000 and 1/48000 s on the 32 x 32
drape; VBD at (substeps per frame) x (iterations per substep) settings listed in CASES.
Then, per case and reference, the CPU time each engine needs for a given error, read off
its measured points (log-log interpolation between neighbouring points of one setting
family, the cheaper family at each error), and their ratio.

    python benchmarks/vbd.py                                   # all cases, about 20 minutes
    python benchmarks/vbd.py --quick                           # smoke run: 32 x 32 drape, two settings each
    python benchmarks/vbd.py --cases drape32 --plot benchmarks/out/vbd.png
    python benchmarks/vbd.py --cases drape32 --vbd 120x20 240x10   # other VBD settings (references unchanged)
    python benchmarks/vbd.py --json benchmarks/results/vbd.json --plot docs/vbd.png
    python benchmarks/vbd.py --analyse benchmarks/results/vbd.json --plot docs/vbd.png   # tables and plot again

Needs ``pip install "newton==1.8.0"`` (it brings warp-lang >= 1.17; not the ``[bench]`` extra,
which pins an older warp) and matplotlib for ``--plot``.

How the Newton model is built from massspring's ``Model`` and where the two differ:

- Particles, masses, gravity: the same. Newton/Warp computes in float32, massspring in float64.
- Springs: the same list, stiffness, damping and rest lengths (``ModelBuilder.add_spring``, rest
  lengths overwritten with massspring's). VBD's spring damping is kd times the change of the
  spring's length over the substep divided by the substep, along the spring: the same
  dashpot as massspring's kd (v_j - v_i) . n. No triangle (StVK) or dihedral bending
  elasticity is used: bending is the bend springs in both engines. VBD's per-particle
  3 x 3 solves use the springs' exact Hessians (not made definite as massspring's
  Newton-solved steps do).
- Graph colouring: ``ModelBuilder.color()`` colours triangles and bending edges only, so
  the particles are coloured on the spring graph with ``newton.utils.color_graph`` (7 colours
  for these grids) and given with ``set_coloring``.
- Drag: Newton has no per-particle linear drag; the drape's 0.002 N s/m per particle is
  applied as an external force -c v at the start of each substep (explicit within the
  substep, implicit in massspring).
- Colliders (a sphere and the ground plane, static): massspring's contact is a hard
  constraint (prescribed normal velocity in the implicit solve, projection onto the
  surface, restitution 0) with exact Coulomb friction (sticking and sliding). VBD's is a
  penalty: normal stiffness ke = 1e4 N/m per particle contact (``--ke``), normal damping
  kd = 2 sqrt(ke m) (critical for one particle of mean mass m, acting only while
  approaching: close to restitution 0), and Coulomb friction mu times the penalty's elastic
  normal force, smoothed below a slip speed of ``friction_epsilon`` = 1e-2 m/s (VBD's
  default; a resting particle creeps at up to that speed times its tangential load over
  mu times its normal load). The particle radius is 0, so contact starts at the collider's
  surface as in massspring, and a resting particle sinks m g / ke (1 um) into it. The
  friction coefficients are the scene's exactly: VBD mixes the particles' and a shape's
  coefficients as their geometric mean, so the shape is given mu^2 / mu_particles.
  Contacts are detected once per substep (the solver owns the collision pipeline;
  ``soft_contact_gap`` 0.01 m).
- Strain limit (the drape's 0.1): massspring only; VBD has none.
- Self-collision (``sheets``): massspring's pass of impulses and displacement bounds keeps
  pairs at least thickness/2 apart (thickness 0.01 m, friction 0.2). VBD's self-contact is a
  penalty between vertex-triangle and edge-edge pairs closer than
  ``particle_self_contact_margin`` = 0.01 m (gap 0.01 m, detection before and after each
  substep's initialisation, its default), stiffness ke and damping kd as above, friction
  0.2, with its divide-and-truncate displacement bounds. It needs the mesh's triangles and
  edges: they are added with zero elastic, damping and bending stiffness.
- Time stepping: massspring takes one step per dt; VBD takes ``substeps`` steps per 1/60 s
  frame, each with ``iterations`` Gauss-Seidel sweeps over the colours, and its frames are
  replayed from a captured Warp graph (APIC on the CPU; 2.7x less CPU than launching from
  Python at 10 x 10 on the 32 x 32 drape, its largest strain and penetration the same to all 16 printed digits).
- Threads: both engines run these sizes single-threaded (Warp's CPU kernels are serial,
  massspring uses serial Taichi loops below 1,000,000 springs).
"""

from __future__ import annotations

import argparse
import math
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))
sys.path.insert(0, str(HERE.parent / "tests"))
import output  # noqa: E402
from crossings import crossings  # noqa: E402

import massspring as ms  # noqa: E402
from massspring.io.files import write_json  # noqa: E402
from massspring.model.self_collision import mesh_edges  # noqa: E402

FRAME = 1.0 / 60.0
FRAMES = 60  # 1 s
EARLY = 15  # frame of t = 0.25 s
MS_DTS = (60, 120, 240, 600)  # steps per second
SYMPLECTIC = (12000, 24000, 48000)  # 1/6000 s diverges (at t = 0.005 s)
MS_REF = 6000
VBD_REF = (60, 20)
TIGHT = dict(cg_tol=1e-8, newton_tol=1e-6)
NO_LIMIT = "implicit, no strain limit"  # a different model: shown, left out of the equal-error comparison

# case: scene, resolution (None: the scene's), VBD settings (substeps, iterations), symplectic
CASES = {
    "drape32": dict(scene="drape", resolution=32, symplectic=True,
                    vbd=[(5, 5), (10, 5), (20, 5), (5, 10), (10, 10), (20, 10), (40, 10), (20, 20)]),
    "drape64": dict(scene="drape", resolution=64, symplectic=False, vbd=[(5, 5), (10, 10), (20, 10), (40, 10)]),
    "sheets": dict(scene="sheets", resolution=None, symplectic=False, vbd=[(5, 5), (10, 10), (20, 10)]),
}
QUICK = dict(ms=[("implicit", 60), ("backward-euler", 120)], vbd=[(5, 5), (10, 10)], ms_ref=1200, vbd_ref=(20, 10))


def parse_args(argv=None):
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--cases", nargs="+", default=list(CASES), choices=list(CASES))
    p.add_argument("--quick", action="store_true",
                   help="smoke run: drape32 only, two settings per engine, coarse references "
                        f"(massspring BE 1/{QUICK['ms_ref']} s, VBD {QUICK['vbd_ref'][0]}x{QUICK['vbd_ref'][1]})")
    p.add_argument("--vbd", nargs="+", default=None, metavar="SxI",
                   help="VBD settings to run instead of the case's, as substeps x iterations per substep: 10x10 ...")
    p.add_argument("--vbd-only", action="store_true", help="run the references and the VBD settings only")
    p.add_argument("--ke", type=float, default=1e4, help="VBD contact stiffness, N/m per contact (default 1e4)")
    p.add_argument("--analyse", default=None, metavar="JSON",
                   help="run nothing: print the equal-error tables of the rows in JSON (written by a run), "
                        "store them in it and draw --plot")
    p.add_argument("--plot", default=None, help="PNG of error at t = 1 s against CPU time (log-log)")
    output.add_json(p, "vbd")
    return p.parse_args(argv)


# ----------------------------------------------------------------------------------------
# measurements shared by both engines


@dataclass
class Tracker:
    """What a run is measured by, sampled at every 1/60 s frame (t = 0 included)."""

    model: object
    count_crossings: bool
    frames: list = field(default_factory=list)
    strain: float = 0.0
    depth: dict = field(default_factory=dict)
    crossings: list = field(default_factory=list)

    def sample(self, x):
        m = self.model
        x = np.asarray(x, dtype=np.float64)
        self.frames.append(x.copy())
        if not np.all(np.isfinite(x)):
            return False
        ends = m.springs
        length = np.linalg.norm(x[ends[:, 1]] - x[ends[:, 0]], axis=1)
        self.strain = max(self.strain, float((length / m.rest_lengths - 1).max()))
        for c in m.colliders:
            if isinstance(c, ms.Sphere):
                key, d = "sphere", c.radius - np.linalg.norm(x - np.asarray(c.center), axis=1)
            else:
                n = np.asarray(c.normal, float) / np.linalg.norm(c.normal)
                key, d = "ground", (np.asarray(c.point, float) - x) @ n
            self.depth[key] = max(self.depth.get(key, 0.0), float(d.max()))
        if self.count_crossings and (len(self.frames) - 1) % 6 == 0 and len(self.frames) > 1:
            self.crossings.append(crossings(x, m.triangles, self._edges()))
        return True

    def _edges(self):
        if not hasattr(self, "_edge_list"):
            self._edge_list = mesh_edges(self.model.triangles)
        return self._edge_list


def errors(frames, ref):
    """Per frame: (RMS, max) distance over all particles against the reference's frames."""
    if ref is None or len(frames) != len(ref):
        return None
    d = [np.linalg.norm(a - b, axis=1) for a, b in zip(frames, ref)]
    return [float(np.sqrt(np.mean(e * e))) for e in d], [float(e.max()) for e in d]


# ----------------------------------------------------------------------------------------
# massspring


def run_massspring(model, integrator, steps_per_second, tracker, **options):
    """One massspring run of FRAMES frames: (CPU s, wall s, diverged at t or None)."""
    dt = 1.0 / steps_per_second
    per_frame = round(FRAME / dt)
    warm = ms.Simulation(model, integrator=integrator, dt=dt, **options)  # compiles (cached per size class)
    warm.step()
    warm.close()
    sim = ms.Simulation(model, integrator=integrator, dt=dt, **options)
    tracker.sample(sim.positions)
    cpu = wall = 0.0
    diverged = None
    for frame in range(FRAMES):
        c0, w0 = time.process_time(), time.perf_counter()
        try:
            sim.step(per_frame)
        except ms.DivergenceError:
            diverged = (frame + 1) * FRAME
            break
        finally:
            cpu += time.process_time() - c0
            wall += time.perf_counter() - w0
        if not tracker.sample(sim.positions):
            diverged = (frame + 1) * FRAME
            break
    sim.close()
    return cpu, wall, diverged


# ----------------------------------------------------------------------------------------
# Newton VBD

_wp = _newton = _drag_kernel = None


def warp():
    """Warp, imported on first use, on the CPU (and Newton, past this folder's newton.py)."""
    global _wp, _drag_kernel, _newton
    if _wp is None:
        import warp as wp

        saved = sys.path[:]
        sys.path[:] = [p for p in sys.path if Path(p or ".").resolve() != HERE]
        try:
            import newton
            import newton.solvers
            import newton.utils
        finally:
            sys.path[:] = saved
        _newton = newton

        wp.config.quiet = True
        wp.set_device("cpu")

        @wp.kernel
        def drag_kernel(c: float, qd: wp.array(dtype=wp.vec3), f: wp.array(dtype=wp.vec3)):
            i = wp.tid()
            f[i] = -c * qd[i]

        _drag_kernel = drag_kernel
        _wp = wp
    return _wp


def newton_model(model, ke):
    """Newton's model of massspring's ``model`` (see the module docstring), and its
    self-contact settings (None without self-collision)."""
    wp = warp()
    newton = _newton
    n = model.n_particles
    masses = np.broadcast_to(np.asarray(model.masses, dtype=float), (n,))
    b = newton.ModelBuilder(up_axis=newton.Axis.Z, gravity=tuple(float(g) for g in model.gravity))
    b.add_particles(pos=[tuple(map(float, p)) for p in model.positions],
                    vel=[tuple(map(float, v)) for v in model.velocities], mass=[float(x) for x in masses],
                    radius=[0.0] * n)
    stiffness = np.broadcast_to(model.stiffness, (model.n_springs,))
    damping = np.broadcast_to(model.damping, (model.n_springs,))
    for (i, j), k, c in zip(model.springs, stiffness, damping):
        b.add_spring(int(i), int(j), float(k), float(c), 0.0)
    b.spring_rest_length = [float(x) for x in model.rest_lengths]
    selfc = model.self_collision
    if selfc is not None:
        tri = np.asarray(model.triangles, dtype=np.int32)
        zeros = [0.0] * len(tri)
        b.add_triangles(tri[:, 0], tri[:, 1], tri[:, 2], tri_ke=zeros, tri_ka=zeros, tri_kd=zeros, tri_drag=zeros,
                        tri_lift=zeros)
        edges = newton.utils.MeshAdjacency(tri).edge_indices
        zeros = [0.0] * len(edges)
        b.add_edges(edges[:, 0], edges[:, 1], edges[:, 2], edges[:, 3], edge_ke=zeros, edge_kd=zeros)
    graph = wp.array(np.asarray(model.springs, dtype=np.int32), dtype=int, device="cpu")
    b.set_coloring(newton.utils.color_graph(n, graph))
    kd = 2.0 * math.sqrt(ke * float(masses.mean()))
    particle_mu = selfc.friction if selfc is not None and selfc.friction > 0 else 1.0
    for c in model.colliders:
        cfg = newton.ModelBuilder.ShapeConfig(ke=ke, kd=kd, mu=c.friction ** 2 / particle_mu)
        if any(v != 0 for v in c.velocity):
            raise ValueError("moving colliders are not modelled here")
        if isinstance(c, ms.Plane):
            normal = np.asarray(c.normal, float) / np.linalg.norm(c.normal)
            b.add_shape_plane(plane=(*normal, -float(normal @ np.asarray(c.point, float))), width=0.0, length=0.0,
                              cfg=cfg)
        elif isinstance(c, ms.Sphere):
            b.add_shape_sphere(-1, xform=wp.transform(wp.vec3(*map(float, c.center)), wp.quat_identity()),
                               radius=float(c.radius), cfg=cfg)
        else:
            raise ValueError(f"{type(c).__name__} colliders are not modelled here")
    nm = b.finalize(device="cpu")
    nm.soft_contact_ke, nm.soft_contact_kd, nm.soft_contact_mu = ke, kd, particle_mu
    contact = None
    if selfc is not None:
        contact = dict(particle_enable_self_contact=True, particle_self_contact_margin=selfc.thickness,
                       particle_self_contact_gap=selfc.thickness)
    return nm, contact


def run_vbd(model, substeps, iterations, tracker, ke):
    """One VBD run of FRAMES frames: (CPU s, wall s, diverged at t or None)."""
    wp = warp()
    newton = _newton
    nm, contact = newton_model(model, ke)
    pipeline = newton.CollisionPipeline(nm, soft_contact_gap=0.01)
    solver = newton.solvers.SolverVBD(nm, iterations=iterations, collision_pipeline=pipeline, **(contact or {}))
    states = [nm.state(), nm.state()]
    q0, qd0 = wp.clone(states[0].particle_q), wp.clone(states[0].particle_qd)
    drag = float(model.term_parameters.get("drag", 0.0))
    dt = FRAME / substeps

    def frame(start):
        a, b = states[start], states[1 - start]
        for _ in range(substeps):
            if drag:
                wp.launch(_drag_kernel, dim=nm.particle_count, inputs=[drag, a.particle_qd], outputs=[a.particle_f])
            solver.step(a, b, None, None, dt)
            a, b = b, a
        return states.index(a)

    frame(0)  # warm-up: compiles on first use, sizes the solver's buffers
    states[0].particle_q.assign(q0)
    states[0].particle_qd.assign(qd0)
    graphs = []
    for start in (0, 1) if substeps % 2 else (0,):
        with wp.ScopedCapture() as capture:  # records, runs nothing
            frame(start)
        graphs.append(capture.graph)
    tracker.sample(states[0].particle_q.numpy())
    cpu = wall = 0.0
    diverged = None
    current = 0
    for f in range(FRAMES):
        c0, w0 = time.process_time(), time.perf_counter()
        wp.capture_launch(graphs[current if substeps % 2 else 0])
        cpu += time.process_time() - c0
        wall += time.perf_counter() - w0
        current = (current + substeps) % 2
        if not tracker.sample(states[current].particle_q.numpy()):
            diverged = (f + 1) * FRAME
            break
    return cpu, wall, diverged


# ----------------------------------------------------------------------------------------
# a case: references first, then every setting


def header(sheets):
    cross = f"{'crossings':>10}" if sheets else ""
    return (f"{'engine':<11}{'setting':<22}{'CPU s':>8}{'wall s':>8}{'strain%':>8}{'sph mm':>8}{'gnd mm':>8}{cross}"
            f" |{'MS-ref rms':>11}{'max':>7} |{'VBD-ref rms':>12}{'max':>7} |{'@0.25s MS':>10}{'VBD':>6}   (mm)")


def line(row, sheets):
    def mm(v, w, digits=1):
        return f"{'-' if v is None else f'{1e3 * v:.{digits}f}':>{w}}"

    cross = ""
    if sheets:
        cross = f"{'-' if row['crossings'] is None else max(row['crossings']):>10}"
    e = row["errors"]
    note = f"  diverged at t = {row['diverged']:.3f} s" if row["diverged"] else ""
    return (f"{row['engine']:<11}{row['setting']:<22}{row['cpu_s']:>8.2f}{row['wall_s']:>8.2f}"
            f"{100 * row['max_strain']:>8.2f}{mm(row['depth_sphere_m'], 8, 3)}{mm(row['depth_ground_m'], 8, 3)}{cross}"
            f" |{mm(e['ms_ref']['rms'], 11)}{mm(e['ms_ref']['max'], 7)} |{mm(e['vbd_ref']['rms'], 12)}"
            f"{mm(e['vbd_ref']['max'], 7)} |{mm(e['ms_ref']['rms_early'], 10)}{mm(e['vbd_ref']['rms_early'], 6)}{note}")


def make_row(case, engine, family, setting, cost, tracker, refs):
    cpu, wall, diverged = cost
    row = {"case": case, "engine": engine, "family": family, "setting": setting, "cpu_s": cpu,
           "cpu_per_simulated_s": cpu / (FRAMES * FRAME), "wall_s": wall, "diverged": diverged,
           "max_strain": tracker.strain, "depth_sphere_m": tracker.depth.get("sphere"),
           "depth_ground_m": tracker.depth.get("ground"),
           "crossings": tracker.crossings if tracker.count_crossings else None, "errors": {}}
    for name, ref in refs.items():
        err = None if diverged else errors(tracker.frames, ref)
        row["errors"][name] = {
            "rms": None if err is None else err[0][-1], "max": None if err is None else err[1][-1],
            "rms_early": None if err is None else err[0][EARLY],
            "rms_by_frame": None if err is None else err[0]}
    return row


def run_case(name, spec, args):
    scene = ms.load_scene(spec["scene"])
    if spec["resolution"]:
        scene = scene.with_params(resolution=spec["resolution"])
    model = scene.model()
    sheets = model.self_collision is not None
    quick = args.quick
    ms_ref = QUICK["ms_ref"] if quick else MS_REF
    vbd_ref = QUICK["vbd_ref"] if quick else VBD_REF
    print(f"\n{name}: {spec['scene']}, {model.n_particles} particles, {model.n_springs} springs, "
          f"{FRAMES * FRAME:g} s; references: (a) massspring backward-euler dt 1/{ms_ref} s "
          f"(cg_tol 1e-8, newton_tol 1e-6), (b) VBD {vbd_ref[0]} substeps x {vbd_ref[1]} iterations", flush=True)
    print(header(sheets), flush=True)

    def track():
        return Tracker(model, sheets)

    rows, refs = [], {"ms_ref": None, "vbd_ref": None}
    runs = []  # (engine, family, setting, thunk)
    t = track()
    cost = run_massspring(model, "backward-euler", ms_ref, t, **TIGHT)
    refs["ms_ref"] = None if cost[2] else t.frames
    ms_ref_tracker = (cost, t)
    t2 = track()
    cost2 = run_vbd(model, *vbd_ref, t2, args.ke)
    refs["vbd_ref"] = None if cost2[2] else t2.frames
    rows.append(make_row(name, "massspring", "reference", f"BE 1/{ms_ref} tight", *ms_ref_tracker, refs))
    print(line(rows[-1], sheets), flush=True)
    rows.append(make_row(name, "vbd", "reference", f"{vbd_ref[0]}x{vbd_ref[1]}", cost2, t2, refs))
    print(line(rows[-1], sheets), flush=True)

    if quick:
        ms_runs = QUICK["ms"]
        vbd_runs = QUICK["vbd"]
    else:
        ms_runs = [(i, s) for i in ("implicit", "backward-euler") for s in MS_DTS]
        if spec["symplectic"]:
            ms_runs += [("symplectic", s) for s in SYMPLECTIC]
        vbd_runs = spec["vbd"]
    if args.vbd:
        vbd_runs = [tuple(int(v) for v in setting.lower().split("x")) for setting in args.vbd]
    if args.vbd_only:
        ms_runs = []
    for integrator, per_s in ms_runs:
        runs.append(("massspring", integrator, f"{integrator} 1/{per_s}",
                     lambda t, i=integrator, s=per_s: run_massspring(model, i, s, t)))
    if model.strain_limit is not None and not quick and not args.vbd_only:
        free = model.replaced(strain_limit=None)
        runs.append(("massspring", NO_LIMIT, "implicit 1/60 no limit",
                     lambda t: run_massspring(free, "implicit", 60, t)))
    for substeps, iterations in vbd_runs:
        runs.append(("vbd", f"VBD {iterations} it.", f"{substeps}x{iterations}",
                     lambda t, s=substeps, i=iterations: run_vbd(model, s, i, t, args.ke)))
    for engine, family, setting, thunk in runs:
        t = track()
        rows.append(make_row(name, engine, family, setting, thunk(t), t, refs))
        print(line(rows[-1], sheets), flush=True)
    return rows


# ----------------------------------------------------------------------------------------
# equal-error comparison


def cost_at(points, target):
    """CPU s at which a family (points of (cpu, err), any order) first reaches error <= target,
    interpolated log-log between the neighbouring points; (cost, how) or None."""
    pts = sorted(p for p in points if p[1] is not None and p[1] > 0)
    for k, (cpu, err) in enumerate(pts):
        if err <= target:
            if k == 0:
                return cpu, "<="  # reached by its cheapest point: at most this
            c0, e0 = pts[k - 1]
            s = (math.log(target) - math.log(e0)) / (math.log(err) - math.log(e0))
            return math.exp(math.log(c0) + s * (math.log(cpu) - math.log(c0))), "interp."
    return None


def equal_error(rows, ref, key="rms"):
    """For each engine, its cheapest family's CPU s at six errors spaced log-evenly over all
    the errors measured (``key``: "rms" at t = 1 s or "rms_early" at 0.25 s), None where
    no family of the engine reaches the error."""
    fams = {}
    for r in rows:
        err = r["errors"][ref][key]
        if r["family"] in ("reference", NO_LIMIT) or r["diverged"] or err is None or err <= 0:
            continue
        fams.setdefault(r["engine"], {}).setdefault(r["family"], []).append((r["cpu_s"], err))
    every = [p[1] for fs in fams.values() for f in fs.values() for p in f]
    if not every:
        return []
    out = []
    for target in np.geomspace(min(every), max(every), 6):
        entry = {"target_rms": float(target)}
        for engine in ("massspring", "vbd"):
            best = None
            for fam, pts in fams.get(engine, {}).items():
                c = cost_at(pts, target * (1 + 1e-9))
                if c is not None and (best is None or c[0] < best[0]):
                    best = (c[0], c[1], fam)
            entry[engine] = None if best is None else {"cpu_s": best[0], "how": best[1], "family": best[2]}
        if entry["massspring"] and entry["vbd"]:
            entry["vbd_over_massspring"] = entry["vbd"]["cpu_s"] / entry["massspring"]["cpu_s"]
        out.append(entry)
    return out


def print_equal_error(case, ref, table, when="t = 1 s"):
    label = {"ms_ref": "(a) massspring reference", "vbd_ref": "(b) VBD reference"}[ref]
    print(f"\n{case}, RMS error at {when} against {label}: the CPU s each engine needs for it "
          f"(cheapest family; log-log interpolated between its neighbouring points, <= where its cheapest point already does better)")
    if not table:
        print("  (no runs)")
        return
    print(f"  {'RMS mm':>8}  {'massspring CPU s (family)':<44}{'VBD CPU s (family)':<30}{'VBD/massspring':>14}")
    for entry in table:
        cells = []
        for engine in ("massspring", "vbd"):
            c = entry.get(engine)
            cells.append("not reached" if c is None else
                         f"{'<=' if c['how'] == '<=' else ''}{c['cpu_s']:.2f} ({c['family']})")
        ratio = entry.get("vbd_over_massspring")
        print(f"  {1e3 * entry['target_rms']:>8.1f}  {cells[0]:<44}{cells[1]:<30}"
              f"{'-' if ratio is None else f'{ratio:.2f}':>14}")


# ----------------------------------------------------------------------------------------


COLOURS = {("massspring", "implicit"): "tab:orange", ("massspring", "backward-euler"): "tab:blue",
           ("massspring", "symplectic"): "tab:red", ("massspring", NO_LIMIT): "tab:olive",
           ("massspring", "reference"): "tab:blue", ("vbd", "VBD 5 it."): "tab:pink",
           ("vbd", "VBD 10 it."): "tab:purple", ("vbd", "VBD 20 it."): "tab:brown", ("vbd", "reference"): "tab:purple"}


def plot(rows, cases, path):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    refs = (("ms_ref", "against (a) massspring BE reference"), ("vbd_ref", "against (b) VBD reference"))
    fig, axes = plt.subplots(len(cases), 2, figsize=(12, 4.2 * len(cases)), squeeze=False)
    for r_i, case in enumerate(cases):
        for c_i, (ref, title) in enumerate(refs):
            ax = axes[r_i][c_i]
            fams = {}
            for r in rows:
                if r["case"] != case or r["diverged"] or not r["errors"][ref]["rms"]:
                    continue
                key = (r["engine"], r["family"])
                fams.setdefault(key, []).append((r["cpu_s"], r["errors"][ref]["rms"], r["setting"]))
            for (engine, fam), pts in sorted(fams.items()):
                pts.sort()
                style = "o-" if engine == "massspring" else "s--"
                label = f"{engine}: {fam}" if fam != "reference" else f"{engine} reference"
                ax.plot([p[0] for p in pts], [p[1] for p in pts], style if fam != "reference" else "*",
                        label=label, markersize=6 if fam != "reference" else 12, color=COLOURS.get((engine, fam)))
                for p in pts:
                    ax.annotate(p[2].split(" ")[-1] if engine == "massspring" else p[2], (p[0], p[1]), fontsize=6,
                                xytext=(3, 3), textcoords="offset points")
            ax.set_xscale("log")
            ax.set_yscale("log")
            ax.set_xlabel("CPU s per simulated s")
            ax.set_ylabel("RMS position error at t = 1 s (m)")
            ax.set_title(f"{case}: {title}", fontsize=10)
            ax.grid(True, which="both", alpha=0.3)
            ax.legend(fontsize=7)
    fig.tight_layout()
    Path(path).parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    print(f"wrote {path}")


def versions():
    from importlib.metadata import version

    out = {}
    for name in ("newton", "warp-lang", "taichi", "numpy", "massspring"):
        try:
            out[name] = version(name)
        except Exception:  # noqa: BLE001
            out[name] = None
    return out


def main(argv=None):
    args = parse_args(argv)
    if args.analyse:
        import json

        data = json.loads(Path(args.analyse).read_text())
        data["equal_error"] = analyse(data["rows"], data["cases"])
        write_json(args.analyse, data)
        print(f"\nwrote {args.analyse}")
        if args.plot:
            plot(data["rows"], data["cases"], args.plot)
        return
    cases = ["drape32"] if args.quick else args.cases
    start = time.perf_counter()
    rows = []
    for name in cases:
        rows += run_case(name, CASES[name], args)
    comparison = analyse(rows, cases)
    total = time.perf_counter() - start
    print(f"\nwhole run: {total:.0f} s wall, {time.process_time():.0f} s CPU")
    write_json(args.json, {"versions": versions(), "quick": args.quick, "ke": args.ke, "cases": cases,
                           "wall_s": total, "rows": rows, "equal_error": comparison})
    print(f"wrote {args.json}")
    if args.plot:
        plot(rows, cases, args.plot)


def analyse(rows, cases):
    """Print and return the equal-error tables of every case."""
    comparison = {}
    for name in cases:
        for key, when in (("rms", "t = 1 s"), ("rms_early", "t = 0.25 s")):
            for ref in ("ms_ref", "vbd_ref"):
                table = equal_error([r for r in rows if r["case"] == name], ref, key)
                comparison[f"{name}/{ref}/{key}"] = table
                print_equal_error(name, ref, table, when)
    return comparison


if __name__ == "__main__":
    main()
