"""Scene files: TOML describing a model (one of three forms) and run defaults.

The model comes from exactly one of: ``[model] generator = "..."`` with the
generator's parameters (``generators.PARAMETERS``); ``[model] mesh = "file.obj"`` (a
path relative to the scene file) with the parameters of ``mesh.PARAMETERS``; or
hand-made ``[particles]`` and ``[springs]`` tables (``PARTICLE_KEYS``,
``SPRING_KEYS``; ``[model]`` then holds only ``HANDMADE_PARAMETERS``). docs/scenes.md
lists every key. A generator scene file looks like::

    description = "Square cloth pinned at two corners"
    integrator = "implicit"          # default integrator
    duration = 2.0                   # simulated seconds of a default run

    [dt]                             # optional: default dt (s) per integrator
    explicit = 2e-5                  # integrators not named here get one from the
    implicit = 0.0166667             # stability estimate (Integrator.suggest_dt)

    [model]
    generator = "grid"               # one of generators.GENERATORS
    resolution = 32                  # generator parameters; see generators.PARAMETERS

    [solver]                         # optional: solver options (integrators.OPTIONS; Simulation arguments)
    preconditioner = "auto"          # or "block-jacobi", "multigrid", "multigrid-f32", "none"
    cg_tol = 1e-6                    # CG tolerance, relative to the first residual of each solve
    newton_tol = 1e-3                # Newton-solved integrators: Newton tolerance (see Simulation)
    newton_max_iter = 50             # Newton-solved integrators: Newton iterations per step at most

    [view]                           # optional: camera of GIF/PNG pictures (io.camera.View)
    azimuth = -60.0                  # degrees about +z, 0 = looking from +x
    elevation = 20.0                 # degrees above the xy plane
    projection = "orthographic"      # or "perspective"
    framing = "run"                  # or "follow" (each frame centred), "last" (fit the last frame)

Contact, pins and air (optional; ``common_keys()`` work with every generator and ``--set``)::

    [model]
    drag = 0.05                      # N s/m per particle: f = -drag (v - wind)
    wind = [2.0, 0.0, 0.0]           # m/s; only with drag > 0
    pin_velocity = [0.0, 0.0, 0.5]   # m/s: every pin of the generator moves so

    [[pin]]                          # a pinned particle with its own velocity (repeatable)
    index = -1                       # particle index; negative counts from the end
    velocity = [0.5, 0.0, 0.0]       # m/s (default 0)

    [self_collision]                 # the mesh never passes through itself (massspring.SelfCollision)
    thickness = 0.005                # m; optional: friction, stiffness (N/m)

    [controls]                       # inputs per interval (massspring.Controls)
    interval = 0.5                   # s: a whole number of the run's steps
    wind = [[2.0, 0.0, 0.0], [0.0, 0.0, 0.0]]   # m/s per interval (with drag > 0)
    pin_targets = [[[0, 0, 1], [1, 0, 1]], [[0, 0, 1.2], [1, 0, 1.2]]]   # m: each pin's keyframes

    [[collider]]                     # repeatable; the fields of massspring.Plane/Sphere/Box
    type = "sphere"                  # "plane" | "sphere" | "box"
    center = [0.5, 0.5, -0.4]
    radius = 0.3
    friction = 0.5                   # optional: friction, restitution, velocity

Unknown keys, wrong types and missing values raise ``SceneError`` (a
``ValueError``) naming the key and the file; an OBJ file that cannot be used is
refused when the scene is loaded, naming the OBJ file and line.
"""

from __future__ import annotations

import dataclasses
import math
import sys
import tomllib
from dataclasses import dataclass, field
from importlib import resources
from pathlib import Path

import numpy as np

from massspring.support import memory
from massspring.model import mesh
from massspring.support import validate
from massspring.model.colliders import COLLIDERS
from massspring.support.defaults import GRAVITY
from massspring.model.controls import Controls
from massspring.model.self_collision import SelfCollision
from massspring.engine.adaptive import Tolerance
from massspring.integrators import INTEGRATORS, OPTIONS, taken
from massspring.io.camera import DEFAULT_FRAMING, FRAMINGS, View
from massspring.model import terms
from massspring.model import Model
from massspring.scene import generators
from massspring.support.text import brief


class SceneError(ValueError):
    """A scene file or override is invalid; the message names the key and the file."""


MAX_FLOAT = sys.float_info.max
MAX_SCENE_BYTES = 64 * 2**20  # a scene file's size limit (a hand-made [particles] table of about a million rows)
SIZE_KEYS = {"chain": ("count",), "grid": ("resolution",), "lattice": ("resolution",)}
TOP_KEYS = {"description": str, "integrator": str, "duration": float, "tol": (float, dict), "dt": dict, "model": dict,
            "solver": dict, "view": dict, "particles": dict, "springs": dict, "collider": list, "pin": list,
            "self_collision": dict, "controls": dict}
# [solver]: the integrators' solver options a scene may set (``integrators.OPTIONS``; the
# CLI's options and the API's arguments override them).
SOLVER_KEYS = {name: option.type for name, option in OPTIONS.items()}
VIEW_KEYS = {"azimuth": float, "elevation": float, "projection": str, "framing": str}
FORMS = ("generator", "mesh", "particles")
# Hand-made scenes: key -> what it holds ("rows": a list of lists of numbers, "numbers": one
# number or a list of them, "indices": a list of integers); the Model checks shapes and values.
PARTICLE_KEYS = {"positions": "rows", "masses": "numbers", "velocities": "rows", "fixed": "indices"}
SPRING_KEYS = {"pairs": "rows", "stiffness": "numbers", "damping": "numbers", "rest_lengths": "numbers"}
REQUIRED_KEYS = ("particles.positions", "springs.pairs")
# The [model] table of a hand-made scene (also what --set changes there).
HANDMADE_PARAMETERS = {"gravity": list(GRAVITY), "triangles": []}
HANDMADE_TYPES = {"triangles": "rows"}
# Model argument -> the key of a hand-made scene that gives it (for error messages); any
# other argument is "model.<name>".
HANDMADE_ARGUMENTS = {"positions": "particles.positions", "masses": "particles.masses",
                      "velocities": "particles.velocities", "fixed": "particles.fixed", "springs": "springs.pairs",
                      "stiffness": "springs.stiffness", "damping": "springs.damping",
                      "rest_lengths": "springs.rest_lengths"}


def common_keys() -> dict:
    """[model] keys of every form, applied to the Model arguments it makes: name -> default
    (the force terms' parameters, ``terms.parameters()``, then the pins' velocity and the strain
    limit, 0 for none)."""
    return {**{name: list(p.default) if p.vector else p.default for name, p in terms.parameters().items()},
            "pin_velocity": [0.0, 0.0, 0.0], "strain_limit": 0.0}


PIN_KEYS = {"index": int, "velocity": list}


def builtin_scenes() -> dict:
    """Built-in scene name -> path of its TOML file."""
    root = resources.files("massspring.scenes")
    return {Path(p.name).stem: Path(str(p)) for p in root.iterdir() if p.name.endswith(".toml")}


@dataclass(frozen=True)
class Scene:
    """A parsed scene. ``form``: "generator", "mesh" or "particles" (hand-made);
    ``generator``: the generator's name (None for the other forms); ``params``: the
    [model] parameters with defaults filled in (a mesh scene's ``mesh`` is the OBJ
    path, resolved against the scene file's folder); ``dt``: the default time steps
    the file names; ``view``: the camera of its [view] table (``io.camera.View``, checked
    when the file is loaded); ``framing``: that table's ``framing`` (``io.camera.FRAMINGS``); ``obj_mesh``: the ``io.obj.ObjMesh`` read (mesh form);
    ``tables``: the [particles] and [springs] tables (hand-made form); ``solver``: its
    [solver] table (checked Simulation arguments); ``common``: the ``common_keys()``
    (defaults filled in); ``colliders``: its [[collider]] tables as
    ``massspring.Plane``/``Sphere``/``Box``; ``self_collision``: its [self_collision]
    table as a ``massspring.SelfCollision`` (None without one); ``controls``: its [controls]
    table as a ``massspring.Controls`` (None without one); ``pins``: its [[pin]] tables as
    (index, velocity) pairs; ``builtin``: whether it is a built-in scene (its errors name
    it, not its file: ``label``); ``set_keys``: the [model] keys changed by ``with_settings``
    (``--set``), which errors found when the model is built then name instead of the file."""

    name: str
    source: str
    description: str
    integrator: str
    duration: float
    dt: dict
    generator: str | None
    params: dict = field(default_factory=dict)
    view: View = field(default_factory=View)
    framing: str = DEFAULT_FRAMING
    solver: dict = field(default_factory=dict)
    form: str = "generator"
    obj_mesh: object = field(default=None, repr=False, compare=False)
    tables: dict = field(default_factory=dict, repr=False)
    common: dict = field(default_factory=common_keys)
    colliders: tuple = ()
    pins: tuple = ()
    self_collision: object = None
    controls: object = None
    tol: dict = field(default_factory=dict)  # integrator -> its error-controlled default (``Simulation(tol=...)``)
    set_keys: tuple = ()
    builtin: bool = False
    _suggested: dict = field(default_factory=dict, repr=False, compare=False)  # default dts, and the prediction

    @property
    def label(self) -> str:
        """What errors about the scene start with: a built-in scene's name, else its file."""
        return f"scene {self.name!r}" if self.builtin else self.source

    def with_params(self, **overrides) -> "Scene":
        """A copy with some [model] parameters or ``common_keys()`` replaced (checked like the
        file's). In a mesh scene, ``density`` replaces ``mass`` and the other way round,
        and a new ``mesh`` path (relative to the working directory) is read at once."""
        params, common = dict(self.params), dict(self.common)
        surface = self.obj_mesh
        shared = common_keys()
        for key, value in overrides.items():
            if key in shared:
                common[key] = _check_common(key, value, f"{self.label}: model.{key}")
                continue
            params[key] = _check_param(self._parameters(), key, value, self.label)
            if self.form == "mesh" and key in ("density", "mass"):
                params["mass" if key == "density" else "density"] = None
            if self.form == "mesh" and key == "mesh":
                surface = _read_mesh(params["mesh"], f"{self.label}: model.mesh")
        return dataclasses.replace(self, params=params, common=common, obj_mesh=surface, _suggested={})

    def _parameters(self):
        """(defaults, types, what) of this scene's [model] parameters (see ``_check_param``)."""
        if self.form == "mesh":
            return mesh.PARAMETERS, mesh.TYPES, "a mesh scene"
        if self.form == "particles":
            return HANDMADE_PARAMETERS, HANDMADE_TYPES, "a hand-made scene ([particles] and [springs])"
        return generators.PARAMETERS[self.generator], {}, f"generator {self.generator!r}"

    def with_settings(self, settings) -> "Scene":
        """Apply ``key=value`` strings (values parsed as TOML, else taken as strings);
        a key given twice is an error."""
        overrides, shared = {}, common_keys()
        for key, text in setting_items(settings, "--set", "key=value"):
            value = setting_value(text)
            if key in shared:
                overrides[key] = _check_common(key, value, f"--set {key}")
            else:
                overrides[key] = _check_param(self._parameters(), key, value, f"--set {key}")
        return dataclasses.replace(self.with_params(**overrides), set_keys=self.set_keys + tuple(overrides))

    def counts(self) -> tuple[int, int]:
        """(particles, springs) of the scene's model, known without building it (for a
        mesh, an upper bound on the springs: one per face edge)."""
        if self.form == "mesh":
            return len(self.obj_mesh.vertices), 3 * sum(len(f) - 2 for f in self.obj_mesh.faces)
        if self.form == "particles":
            return len(self.tables["particles"]["positions"]), len(self.tables["springs"]["pairs"])
        return generators.counts(self.generator, self.params)

    def check_memory(self, need, particles, springs, what):
        """Refuse (SceneError naming the size keys) a model of ``particles`` and ``springs``
        for which ``what`` (e.g. "building it") would need ``need`` bytes more than this
        process may take (``memory.check``)."""
        if self.form == "mesh":
            size = f"{self.params['mesh']} has {particles:,} vertices"
        elif self.form == "particles":
            size = f"{particles:,} particles and {springs:,} springs"
        else:
            keys = ", ".join(f"{k} = {brief(self.params[k])}" for k in SIZE_KEYS.get(self.generator, ()))
            size = f"{keys or 'the ' + self.generator} gives {_count(particles)} particles and {_count(springs)} springs"
        try:
            memory.check(need, f"model: {size}; {what}")
        except memory.MemoryNeedError as exc:
            raise SceneError(f"{self.label}: {exc}") from None

    def model(self) -> Model:
        """Build the Model (raises SceneError naming the parameter if a value is out of range,
        or if building the model would not fit in the memory available)."""
        if self.form != "particles":  # a hand-made scene's arrays are in memory already
            particles, springs = self.counts()
            self.check_memory(memory.build_bytes(particles, springs), particles, springs, "building it")
        try:
            args = self._arguments()
            args.update(self._contact_and_air(args))
            return Model(**args)
        except ValueError as exc:
            message = str(exc)
            name, _, reason = message.partition(": ")
            if name in self.set_keys:
                raise SceneError(f"--set {name}: {reason}") from None
            if message.startswith(("pin[", "controls")):
                raise SceneError(f"{self.label}: {message}") from None
            if self.form == "particles":
                key = HANDMADE_ARGUMENTS.get(name, f"model.{name}")
                raise SceneError(f"{self.label}: {key}: {reason}") from None
            raise SceneError(f"{self.label}: model.{message}") from None

    def _arguments(self) -> dict:
        """The Model arguments of the scene's form (before ``_contact_and_air``)."""
        if self.form == "particles":
            args = {name: value for table in self.tables.values() for name, value in table.items()}
            args["springs"] = args.pop("pairs")
            return {**args, **self.params}
        if self.form == "mesh":
            params = {key: value for key, value in self.params.items() if key != "mesh"}
            return mesh.mesh_arguments(self.obj_mesh.vertices, self.obj_mesh.faces, **params)
        return generators.GENERATORS[self.generator](**self.params)

    def _contact_and_air(self, args) -> dict:
        """The Model arguments of ``common``, ``pins`` and ``colliders`` for a form's ``args``:
        its pins move with ``pin_velocity``; each [[pin]] pins its particle (one already
        pinned too) with its own velocity."""
        air = {**{name: self.common[name] for name in terms.parameters()}, "colliders": self.colliders,
               "self_collision": self.self_collision, "controls": self.controls,
               "strain_limit": self.common["strain_limit"] or None}
        if not self.pins and not any(self.common["pin_velocity"]):
            return air  # the form's own pins, left to the Model to check
        n = len(np.asarray(args["positions"]))
        fixed = np.asarray([] if args.get("fixed") is None else args["fixed"])
        if fixed.size and fixed.dtype.kind not in "iu":
            raise ValueError(f"fixed: expected integer particle indices, got {fixed.tolist()!r}")
        pins = dict.fromkeys(fixed.astype(np.int64).ravel().tolist(), self.common["pin_velocity"])
        for k, (index, velocity) in enumerate(self.pins):
            if not -n <= index < n:
                raise ValueError(f"pin[{k}].index: {index} is outside -{n}..{n - 1} ({n} particles)")
            pins[index % n] = velocity
        return {"fixed": np.array(list(pins), dtype=np.int64),
                "pin_velocity": np.array(list(pins.values())).reshape(-1, 3), **air}

    def default_dt(self, integrator=None) -> float:
        """The scene's dt (s) for ``integrator`` (default: the scene's): the [dt] entry, else
        ``Integrator.suggest_dt`` of the stability prediction at the initial state."""
        name = integrator or self.integrator
        if name not in INTEGRATORS:
            raise ValueError(f"integrator: unknown value {name!r}, expected one of {', '.join(INTEGRATORS)}")
        if name in self.dt:
            return self.dt[name]
        if name not in self._suggested:
            self._suggested[name] = INTEGRATORS[name].suggest_dt(self.prediction())
        return self._suggested[name]

    def prediction(self):
        """The stability prediction (``engine.spectrum.predict``) at the initial state,
        computed once."""
        if "prediction" not in self._suggested:
            from massspring.engine.spectrum import predict

            self._suggested["prediction"] = predict(self.model())
        return self._suggested["prediction"]

    def simulation(self, integrator=None, dt=None, **kwargs):
        """A Simulation with the scene's defaults (integrator, dt, [solver], tol); any
        Simulation argument may be overridden. With a tolerance (``tol`` given, else the
        scene's for ``integrator`` unless ``dt``, ``newton_tol`` or ``cg_tol`` is given:
        they ask for fixed steps), the run is error-controlled over ``horizon`` (default:
        the scene's duration; without a tolerance it is not used) and the scene's
        [solver] newton_tol and cg_tol give way to those tol derives."""
        from massspring.engine import footprint
        from massspring.engine.footprint import Sketch
        from massspring.engine.simulation import Simulation

        integrator = integrator or self.integrator
        validate.choice("integrator", integrator, tuple(INTEGRATORS))
        options = {**taken(integrator, self.solver), **kwargs}  # of the scene's [solver] keys, those it takes
        fixed = dt is not None or any(kwargs.get(name) is not None for name in ("newton_tol", "cg_tol"))
        tol = options.setdefault("tol", None if fixed else self.tol.get(integrator))
        if tol is not None:
            options.setdefault("horizon", self.duration)
            for name in ("newton_tol", "cg_tol"):
                if name not in kwargs:
                    options.pop(name, None)
        else:
            options.pop("tol")
            options.pop("horizon", None)
        particles, springs = self.counts()
        sketch = Sketch(particles, springs, particles, self.self_collision is not None, bool(self.common["strain_limit"]))
        name, precision = options.get("preconditioner") or "auto", options.get("precision", "f64")
        solver = footprint.preconditioner(sketch, integrator, precision, name)
        self.check_memory(footprint.run_bytes(sketch, integrator, precision, name), particles, springs,
                          f"a run of it ({integrator}{f', {solver}' if solver else ''})")
        dt = self.default_dt(integrator) if dt is None else dt
        return Simulation(self.model(), integrator=integrator, dt=dt, **options)


def _count(n) -> str:
    """``n`` with thousands separators, or its number of digits when that is long."""
    text = f"{n:,}"
    return text if len(text) <= 40 else f"a {len(str(n))}-digit number of"


def setting_items(items, option, form):
    """(key, text) of each ``KEY=TEXT`` string of ``option`` (``form``: how to write one),
    checked: a key, an equals sign, each key once, one line."""
    seen = set()
    for item in items:
        key, sep, text = item.partition("=")
        key = key.strip()
        if not sep or not key:
            raise SceneError(f"{option}: expected {form}, got {item!r}")
        if key in seen:
            raise SceneError(f"{option} {key}: given twice")
        if any(c in text for c in "\n\r\x00"):
            raise SceneError(f"{option} {key}: one value on one line, got {brief(text)}")
        seen.add(key)
        yield key, text


def setting_value(text):
    """The value of a ``--set`` (or ``--vary``) text: parsed as a TOML value, else the
    stripped text as a string."""
    try:
        return tomllib.loads(f"v = {text.strip()}")["v"]
    except tomllib.TOMLDecodeError:
        return text.strip()


MESH_SCENE = {"integrator": "implicit", "duration": 2.0}  # an OBJ file given as the scene: these, the model's defaults


def load_scene(name_or_path) -> Scene:
    """Load a built-in scene by name (see ``builtin_scenes``), a TOML file by path, or an
    OBJ mesh by path (a ``.obj`` file: the scene of ``mesh = "file.obj"`` with the
    defaults of ``MESH_SCENE`` and of docs/scenes.md; no dt: the integrator suggests it,
    or pass ``tol``)."""
    scenes = builtin_scenes()
    path = scenes.get(str(name_or_path))
    if path is None:
        path = Path(name_or_path)
        try:
            is_file = path.is_file()
        except (OSError, ValueError) as exc:  # a name longer than the file system takes, a NUL byte
            raise SceneError(f"scene: {brief(str(name_or_path))} is neither a built-in scene nor a readable "
                             f"path ({getattr(exc, 'strerror', None) or exc})") from None
        if not is_file:
            raise SceneError(f"scene: {brief(str(name_or_path))} is neither a built-in scene "
                             f"({', '.join(sorted(scenes))}) nor a file")
    source = str(path)
    if path.suffix.lower() == ".obj":
        data = {"description": f"the mesh {path.name} with the mesh form's defaults", **MESH_SCENE,
                "model": {"mesh": path.name}}
        return parse_scene(data, name=path.stem, source=source)
    try:
        with open(path, "rb") as fh:
            raw = fh.read(MAX_SCENE_BYTES + 1)
        if len(raw) > MAX_SCENE_BYTES:
            raise SceneError(f"{source}: more than {MAX_SCENE_BYTES // 2**20} MB, more than a scene file holds "
                             "(put large meshes in an OBJ file: mesh = \"file.obj\")")
        data = tomllib.loads(raw.decode("utf-8"))
    except (tomllib.TOMLDecodeError, UnicodeDecodeError) as exc:
        raise SceneError(f"{source}: not valid TOML: {brief(str(exc), 200)}") from None
    except OSError as exc:
        raise SceneError(f"{source}: cannot be read: {exc.strerror}") from None
    scene = parse_scene(data, name=path.stem, source=source)
    return dataclasses.replace(scene, builtin=True) if str(name_or_path) in scenes else scene


def parse_scene(data: dict, name: str, source: str) -> Scene:
    """Check a scene's TOML data and fill in defaults (a mesh scene's OBJ file is read here)."""
    for key, value in data.items():
        if key not in TOP_KEYS:
            raise SceneError(f"{source}: unknown key {key!r} (expected {', '.join(TOP_KEYS)})")
        _check_type(key, value, TOP_KEYS[key], source)
    for key in ("integrator", "duration"):
        if key not in data:
            raise SceneError(f"{source}: missing key {key!r}")
    integrator = data["integrator"]
    if integrator not in INTEGRATORS:
        raise SceneError(f"{source}: integrator: unknown value {integrator!r} (expected {', '.join(INTEGRATORS)})")
    duration = float(data["duration"])
    if not (math.isfinite(duration) and duration > 0):
        raise SceneError(f"{source}: duration: must be a finite number > 0, got {data['duration']}")
    tol = _tolerances(data.get("tol", {}), source)
    dt = {}
    for key, value in data.get("dt", {}).items():
        if key not in INTEGRATORS:
            raise SceneError(f"{source}: dt.{key}: unknown integrator (expected {', '.join(INTEGRATORS)})")
        _check_type(f"dt.{key}", value, float, source)
        if not (math.isfinite(value) and value > 0):
            raise SceneError(f"{source}: dt.{key}: must be a finite number > 0, got {value}")
        dt[key] = float(value)
    view, framing = _view(data.get("view", {}), source)
    colliders = tuple(_collider(k, table, source) for k, table in enumerate(data.get("collider", [])))
    pins = tuple(_pin(k, table, source) for k, table in enumerate(data.get("pin", [])))
    scene = Scene(name=name, source=source, description=data.get("description", ""), integrator=integrator,
                  duration=duration, tol=tol, dt=dt, generator=None, view=view, framing=framing, solver=_solver(data, source),
                  form=_form(data, source), colliders=colliders, pins=pins,
                  self_collision=_self_collision(data.get("self_collision"), source),
                  controls=_controls(data.get("controls"), source))
    model = dict(data.get("model", {}))
    if scene.form == "generator":
        generator = model.pop("generator")
        _check_type("model.generator", generator, str, source)
        if generator not in generators.GENERATORS:
            raise SceneError(f"{source}: model.generator: unknown value {generator!r} "
                             f"(expected {', '.join(generators.GENERATORS)})")
        scene = dataclasses.replace(scene, generator=generator)
    elif scene.form == "mesh":
        _check_type("model.mesh", model["mesh"], str, source)
        if "density" in model and "mass" in model:
            raise SceneError(f"{source}: model.density, model.mass: give one of them, not both")
        model["mesh"] = str(Path(source).parent / model["mesh"])
        scene = dataclasses.replace(scene, obj_mesh=_read_mesh(model["mesh"], f"{source}: model.mesh"))
    else:
        scene = dataclasses.replace(scene, tables=_handmade_tables(data, source))
    defaults = scene._parameters()
    params, common = dict(defaults[0]), common_keys()
    for key, value in model.items():
        if key in common:
            common[key] = _check_common(key, value, f"{source}: model.{key}")
        else:
            params[key] = _check_param(defaults, key, value, source)
    return dataclasses.replace(scene, params=params, common=common)


def _tables(name, table, k, source):
    where = f"{source}: {name}[{k}]"
    if not isinstance(table, dict):
        raise SceneError(f"{where}: expected a table ([[{name}]]), got {type(table).__name__} {table!r}")
    return where


def _collider(k, table, source):
    """A [[collider]] table as a massspring collider; errors name collider[k].<field> and the file."""
    where = _tables("collider", table, k, source)
    fields = dict(table)
    kind = fields.pop("type", None)
    if not isinstance(kind, str) or kind not in COLLIDERS:
        raise SceneError(f"{where}.type: expected one of {', '.join(map(repr, COLLIDERS))}, got {brief(kind)}")
    cls = COLLIDERS[kind]
    names = [f.name for f in dataclasses.fields(cls)]
    for key in fields:
        if key not in names:
            raise SceneError(f"{where}.{key}: unknown key of a {kind} (expected type, {', '.join(names)})")
    required = [f.name for f in dataclasses.fields(cls) if f.default is dataclasses.MISSING]
    missing = [key for key in required if key not in fields]
    if missing:
        raise SceneError(f"{where}.{missing[0]}: missing (a {kind} needs {', '.join(required)})")
    try:
        return cls(**fields)
    except ValueError as exc:
        raise SceneError(f"{where}.{exc}") from None


def _settings_table(name, cls, table, source, required, hint):
    """A [name] table as ``cls(**table)`` (None without one): an unknown key, the missing
    ``required`` key (``hint`` says what it is) and the class's own ValueErrors name
    ``name.<key>`` and the file."""
    if table is None:
        return None
    names = [f.name for f in dataclasses.fields(cls)]
    for key in table:
        if key not in names:
            raise SceneError(f"{source}: {name}.{key}: unknown key (expected {', '.join(names)})")
    if required not in table:
        raise SceneError(f"{source}: {name}.{required}: missing ({hint})")
    try:
        return cls(**table)
    except ValueError as exc:
        message = str(exc)
        raise SceneError(f"{source}: {message if message.startswith(name) else f'{name}.{message}'}") from None


def _self_collision(table, source):
    """The [self_collision] table as a ``massspring.SelfCollision`` (None without one)."""
    return _settings_table("self_collision", SelfCollision, table, source, "thickness",
                           "m: how close the mesh may come to itself")


CONTROL_KEYS = tuple(f.name for f in dataclasses.fields(Controls))


def _controls(table, source):
    """The [controls] table as a ``massspring.Controls`` (None without one); its shapes
    against the model's pins and springs are checked when the model is built."""
    return _settings_table("controls", Controls, table, source, "interval", "s: how long each value holds")


def _pin(k, table, source):
    """A [[pin]] table as (index, velocity)."""
    where = _tables("pin", table, k, source)
    for key in table:
        if key not in PIN_KEYS:
            raise SceneError(f"{where}.{key}: unknown key (expected {', '.join(PIN_KEYS)})")
    if "index" not in table:
        raise SceneError(f"{where}.index: missing (the pinned particle's index)")
    _check_type(f"{where}.index", table["index"], int, None)
    return table["index"], _check_common("pin_velocity", table.get("velocity", [0.0, 0.0, 0.0]),
                                         f"{where}.velocity")


def _check_common(key, value, prefix):
    """A ``common_keys()`` value: a finite number >= 0 or 3 finite numbers, as its default is."""
    default = common_keys()[key]
    if isinstance(default, list):
        out = _numbers(prefix, value, len(default))
    else:
        _check_type(prefix, value, float, None)
        out = float(value)
        if not out >= 0:
            raise SceneError(f"{prefix}: must be >= 0, got {value!r}")
    if not np.all(np.isfinite(out)):
        raise SceneError(f"{prefix}: must be finite, got {value!r}")
    return out


def _numbers(prefix, value, count):
    """A list of ``count`` numbers, as floats."""
    _check_type(prefix, value, list, None)
    if len(value) != count:
        raise SceneError(f"{prefix}: expected {count} numbers, got {value!r}")
    for item in value:
        _check_type(prefix, item, float, None)
    return [float(item) for item in value]


def _solver(data, source):
    """The [solver] table, its keys known and values valid (``integrators.OPTIONS``)."""
    solver = dict(data.get("solver", {}))
    for key, value in solver.items():
        if key not in SOLVER_KEYS:
            raise SceneError(f"{source}: solver.{key}: unknown key (expected {', '.join(SOLVER_KEYS)})")
        _check_type(f"solver.{key}", value, SOLVER_KEYS[key], source)
        try:
            OPTIONS[key].check(value, f"solver.{key}")
        except ValueError as exc:
            raise SceneError(f"{source}: {exc}") from None
    return solver


def _form(data, source):
    """Which of the three forms a scene's data gives (exactly one)."""
    model = data.get("model", {})
    given = [form for form, present in (("generator", "generator" in model), ("mesh", "mesh" in model),
                                        ("particles", "particles" in data or "springs" in data)) if present]
    names = {"generator": "model.generator", "mesh": "model.mesh", "particles": "[particles] and [springs]"}
    if len(given) > 1:
        raise SceneError(f"{source}: {' and '.join(names[g] for g in given)}: give only one way to make the model")
    if not given:
        if "model" not in data:
            raise SceneError(f"{source}: missing key 'model' (or [particles] and [springs] tables)")
        raise SceneError(f"{source}: missing key 'model.generator' (or model.mesh, or [particles] and [springs])")
    return given[0]


def _read_mesh(path, where):
    from massspring.io.obj import ObjError, read_obj

    try:
        return read_obj(path)
    except ObjError as exc:
        raise SceneError(f"{where}: {exc}" if exc.line is None else str(exc)) from None


def _handmade_tables(data, source):
    """The [particles] and [springs] tables, their keys known and of the right TOML types."""
    tables = {}
    for table, keys in (("particles", PARTICLE_KEYS), ("springs", SPRING_KEYS)):
        tables[table] = dict(data.get(table, {}))
        for key, value in tables[table].items():
            if key not in keys:
                raise SceneError(f"{source}: {table}.{key}: unknown key (expected {', '.join(keys)})")
            _check_kind(f"{source}: {table}.{key}", value, keys[key])
    for key in REQUIRED_KEYS:
        table, _, name = key.partition(".")
        if name not in tables[table]:
            raise SceneError(f"{source}: missing key {key!r}")
    return tables


def _view(table, source):
    """(``View``, framing) of a [view] table, checked: SceneError naming the key and the file."""
    for key, value in table.items():
        if key not in VIEW_KEYS:
            raise SceneError(f"{source}: view.{key}: unknown key (expected {', '.join(VIEW_KEYS)})")
        _check_type(f"view.{key}", value, VIEW_KEYS[key], source)
    settings = dict(table)
    framing = settings.pop("framing", DEFAULT_FRAMING)
    try:
        return View(**settings), validate.choice("view.framing", framing, FRAMINGS)
    except ValueError as exc:
        raise SceneError(f"{source}: {exc}") from None


def _check_param(parameters, key, value, source):
    """``value`` of [model] parameter ``key`` checked against ``parameters`` = (defaults,
    types, what: the kind of scene, for messages): a known key, of its default's type (or
    of ``types[key]``: float, "indices", "box" or "rows"), a float finite."""
    defaults, types, what = parameters
    prefix = source if source.startswith("--set") else f"{source}: model.{key}"
    if key not in defaults:
        raise SceneError(f"{prefix}: unknown parameter of {what} (expected {', '.join(defaults)})")
    default = defaults[key]
    kind = types.get(key)
    if kind is not None and not isinstance(kind, type):
        return _check_kind(prefix, value, kind)
    if isinstance(default, list):
        return _numbers(prefix, value, len(default))
    kind = kind or type(default)
    _check_type(prefix, value, kind, None)
    if kind is float and not math.isfinite(value):
        raise SceneError(f"{prefix}: must be finite, got {value!r}")
    return float(value) if kind is float else value


def _check_kind(prefix, value, kind):
    """A TOML value of one of the array kinds: "rows" (a list of lists of numbers),
    "numbers" (a number or a list of numbers), "indices" (a list of integers), "box" (two
    lists of 3 numbers: the low and high corners). Shapes and ranges are the Model's to check."""
    if kind == "numbers" and not isinstance(value, list):
        _check_type(prefix, value, float, None)
        return value
    _check_type(prefix, value, list, None)
    if kind == "box" and not (len(value) == 2 and all(isinstance(c, list) and len(c) == 3 for c in value)):
        raise SceneError(f"{prefix}: expected two corners [[x, y, z], [x, y, z]], got {value!r}")
    rows = value if kind in ("rows", "box") else [value]
    for row in rows:
        _check_type(prefix, row, list, None)
        for item in row:
            _check_type(prefix, item, int if kind == "indices" else float, None)
    return value


def _tolerances(value, source) -> dict:
    """``tol``: a number (every integrator's) or a table of integrator -> number, checked
    as ``Simulation(tol=...)`` checks it; the integrators it names run error-controlled
    by default."""
    table = isinstance(value, dict)
    tols = {}
    for key, tol in (value if table else dict.fromkeys(INTEGRATORS, value)).items():
        name = f"tol.{key}" if table else "tol"
        if key not in INTEGRATORS:
            raise SceneError(f"{source}: {name}: unknown integrator (expected {', '.join(INTEGRATORS)})")
        _check_type(name, tol, float, source)
        try:
            tols[key] = Tolerance.of(tol).tol
        except ValueError as exc:
            raise SceneError(f"{source}: {name}{str(exc).removeprefix('tol')}") from None
    return tols


KINDS = {float: (lambda v: isinstance(v, (int, float)) and not isinstance(v, bool), "a number"),
         int: (lambda v: isinstance(v, int) and not isinstance(v, bool), "an integer"),
         dict: (lambda v: isinstance(v, dict), "a table"),
         list: (lambda v: isinstance(v, list), "a list (a vector is written [0, 0, -9.81])"),
         bool: (lambda v: isinstance(v, bool), "true or false"),
         str: (lambda v: isinstance(v, str), "a string")}


def _check_type(key, value, expected, source):
    """A SceneError unless ``value`` is of the ``KINDS`` ``expected`` (a tuple: any of them)."""
    kinds = expected if isinstance(expected, tuple) else (expected,)
    ok = any(KINDS[kind][0](value) for kind in kinds)
    what = " or ".join(KINDS[kind][1] for kind in kinds)
    where = f"{source}: {key}" if source else key
    if not ok:
        raise SceneError(f"{where}: expected {what}, got {type(value).__name__} {brief(value)}")
    if float in kinds and isinstance(value, int) and not -MAX_FLOAT <= value <= MAX_FLOAT:
        raise SceneError(f"{where}: {brief(value)} is beyond the range of a number (|value| <= {MAX_FLOAT:.4g})")
