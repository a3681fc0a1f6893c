"""Scene files: TOML naming a generator, its parameters, and run defaults.

A scene file looks like::

    description = "Square cloth pinned at two corners"
    integrator = "implicit"          # default integrator
    duration = 2.0                   # simulated seconds of a default run

    [dt]                             # optional: default dt (s) per integrator
    explicit = 2e-5                  # integrators not named here get one from the
    implicit = 0.0166667             # stability estimate (Integrator.suggest_dt)

    [model]
    generator = "grid"               # one of generators.GENERATORS
    resolution = 32                  # generator parameters; see generators.PARAMETERS

    [view]                           # optional: camera of GIF/PNG pictures (io.camera.View)
    azimuth = -60.0                  # degrees about +z, 0 = looking from +x
    elevation = 20.0                 # degrees above the xy plane
    projection = "orthographic"      # or "perspective"
    framing = "run"                  # or "follow" (each frame centred), "last" (fit the last frame)

Contact, pins and air (optional; ``COMMON_KEYS`` work with every generator and ``--set``)::

    [model]
    drag = 0.05                      # N s/m per particle: f = -drag (v - wind)
    wind = [2.0, 0.0, 0.0]           # m/s; only with drag > 0
    pin_velocity = [0.0, 0.0, 0.5]   # m/s: every pin of the generator moves so

    [[pin]]                          # a pinned particle with its own velocity (repeatable)
    index = -1                       # particle index; negative counts from the end
    velocity = [0.5, 0.0, 0.0]       # m/s (default 0)

    [[collider]]                     # repeatable; the fields of massspring.Plane/Sphere/Box
    type = "sphere"                  # "plane" | "sphere" | "box"
    center = [0.5, 0.5, -0.4]
    radius = 0.3
    friction = 0.5                   # optional: friction, restitution, velocity

Unknown keys, wrong types and missing values raise ``SceneError`` (a
``ValueError``) naming the key and the file.
"""

from __future__ import annotations

import dataclasses
import math
import tomllib
from dataclasses import dataclass, field
from importlib import resources
from pathlib import Path

import numpy as np

from massspring.colliders import COLLIDERS
from massspring.device import available_memory
from massspring.integrators import INTEGRATORS
from massspring.model import Model
from massspring.scene import generators


class SceneError(ValueError):
    """A scene file or override is invalid; the message names the key and the file."""


# Peak numpy bytes while a generator builds a Model, per particle and per spring,
# about 1.2x the measured peak (775 MB for the 1000 x 1000 cloth: 1e6 particles, 6e6
# springs). The Simulation then checks its own fields (device.Layout.allocate).
BUILD_BYTES_PER_PARTICLE = 150
BUILD_BYTES_PER_SPRING = 130
SIZE_KEYS = {"chain": ("count",), "grid": ("resolution",), "lattice": ("resolution",)}
TOP_KEYS = {"description": str, "integrator": str, "duration": float, "dt": dict, "model": dict,
            "view": dict, "collider": list, "pin": list}
VIEW_KEYS = {"azimuth": float, "elevation": float, "projection": str, "framing": str}
# Model keys of every generator, applied to the Model arguments it returns: name -> default.
COMMON_KEYS = {"drag": 0.0, "wind": [0.0, 0.0, 0.0], "pin_velocity": [0.0, 0.0, 0.0]}
PIN_KEYS = {"index": int, "velocity": list}


def builtin_scenes() -> dict:
    """Built-in scene name -> path of its TOML file."""
    root = resources.files("massspring.scenes")
    return {Path(p.name).stem: Path(str(p)) for p in root.iterdir() if p.name.endswith(".toml")}


@dataclass(frozen=True)
class Scene:
    """A parsed scene: ``params`` are the generator's full parameter set (defaults
    filled in); ``dt`` the default time steps the file names; ``view`` its [view]
    table (checked when a picture is made: see ``io.camera.View``); ``common`` the
    ``COMMON_KEYS`` (defaults filled in), ``colliders`` its [[collider]] tables as
    ``massspring.Plane``/``Sphere``/``Box``, ``pins`` its [[pin]] tables as
    (index, velocity) pairs."""

    name: str
    source: str
    description: str
    integrator: str
    duration: float
    dt: dict
    generator: str
    params: dict = field(default_factory=dict)
    view: dict = field(default_factory=dict)
    common: dict = field(default_factory=lambda: dict(COMMON_KEYS))
    colliders: tuple = ()
    pins: tuple = ()
    _suggested: dict = field(default_factory=dict, repr=False, compare=False)

    def with_params(self, **overrides) -> "Scene":
        """A copy with some generator parameters or ``COMMON_KEYS`` replaced (checked like the file's)."""
        params, common = dict(self.params), dict(self.common)
        for key, value in overrides.items():
            if key in COMMON_KEYS:
                common[key] = _check_common(key, value, self.source)
            else:
                params[key] = _check_param(self.generator, key, value, self.source)
        return dataclasses.replace(self, params=params, common=common, _suggested={})

    def with_settings(self, settings) -> "Scene":
        """Apply ``key=value`` strings (values parsed as TOML, else taken as strings);
        a key given twice is an error."""
        overrides = {}
        for item in settings:
            key, sep, text = item.partition("=")
            key = key.strip()
            if not sep or not key:
                raise SceneError(f"--set: expected key=value, got {item!r}")
            if key in overrides:
                raise SceneError(f"--set {key}: given twice")
            try:
                value = tomllib.loads(f"v = {text.strip()}")["v"]
            except tomllib.TOMLDecodeError:
                value = text.strip()
            if key in COMMON_KEYS:
                overrides[key] = _check_common(key, value, f"--set {key}")
            else:
                overrides[key] = _check_param(self.generator, key, value, f"--set {key}")
        return self.with_params(**overrides)

    def model(self) -> Model:
        """Build the Model (raises SceneError naming the parameter if a value is out of range,
        or if the model would not fit in the memory available)."""
        particles, springs = generators.counts(self.generator, self.params)
        need = particles * BUILD_BYTES_PER_PARTICLE + springs * BUILD_BYTES_PER_SPRING
        available = available_memory()
        if available is not None and need > available:
            size = ", ".join(f"{k} = {self.params[k]}" for k in SIZE_KEYS.get(self.generator, ()))
            raise SceneError(f"{self.source}: model: {size} gives {particles:,} particles and {springs:,} springs, "
                             f"about {need / 1e9:.3g} GB to build; {available / 1e9:.3g} GB of memory is available")
        try:
            args = generators.GENERATORS[self.generator](**self.params)
            args.update(self._contact_and_air(args))
            return Model(**args)
        except ValueError as exc:
            raise SceneError(f"{self.source}: {exc if str(exc).startswith('pin[') else f'model.{exc}'}") from None

    def _contact_and_air(self, args) -> dict:
        """The Model arguments of ``common``, ``pins`` and ``colliders`` for a generator's
        ``args``: the generator's pins move with ``pin_velocity``; each [[pin]] pins its
        particle (a generator's pin too) with its own velocity."""
        n = len(args["positions"])
        pins = dict.fromkeys(np.asarray(args.get("fixed", []), dtype=np.int64).tolist(), self.common["pin_velocity"])
        for k, (index, velocity) in enumerate(self.pins):
            if not -n <= index < n:
                raise ValueError(f"pin[{k}].index: {index} is outside -{n}..{n - 1} ({n} particles)")
            pins[index % n] = velocity
        return {"fixed": np.array(list(pins), dtype=np.int64),
                "pin_velocity": np.array(list(pins.values())).reshape(-1, 3),
                "drag": self.common["drag"], "wind": self.common["wind"], "colliders": self.colliders}

    def default_dt(self, integrator=None) -> float:
        """The scene's dt (s) for ``integrator`` (default: the scene's): the [dt] entry, else
        ``Integrator.suggest_dt`` of the stability prediction at the initial state."""
        name = integrator or self.integrator
        if name not in INTEGRATORS:
            raise ValueError(f"integrator: unknown value {name!r}, expected one of {', '.join(INTEGRATORS)}")
        if name in self.dt:
            return self.dt[name]
        if name not in self._suggested:
            from massspring.analysis.stability import predict

            self._suggested[name] = INTEGRATORS[name].suggest_dt(predict(self.model()))
        return self._suggested[name]

    def simulation(self, integrator=None, dt=None, **kwargs):
        """A Simulation with the scene's defaults; any Simulation argument may be overridden."""
        from massspring.simulation import Simulation

        integrator = integrator or self.integrator
        dt = self.default_dt(integrator) if dt is None else dt
        return Simulation(self.model(), integrator=integrator, dt=dt, **kwargs)


def load_scene(name_or_path) -> Scene:
    """Load a built-in scene by name (see ``builtin_scenes``) or a TOML file by path."""
    scenes = builtin_scenes()
    path = scenes.get(str(name_or_path))
    if path is None:
        path = Path(name_or_path)
        if not path.is_file():
            raise SceneError(f"scene: {str(name_or_path)!r} is neither a built-in scene "
                             f"({', '.join(sorted(scenes))}) nor a file")
    source = str(path)
    try:
        data = tomllib.loads(path.read_text(encoding="utf-8"))
    except (tomllib.TOMLDecodeError, UnicodeDecodeError) as exc:
        raise SceneError(f"{source}: not valid TOML: {exc}") from None
    except OSError as exc:
        raise SceneError(f"{source}: cannot be read: {exc.strerror}") from None
    return parse_scene(data, name=path.stem, source=source)


def parse_scene(data: dict, name: str, source: str) -> Scene:
    """Check a scene's TOML data and fill in defaults."""
    for key, value in data.items():
        if key not in TOP_KEYS:
            raise SceneError(f"{source}: unknown key {key!r} (expected {', '.join(TOP_KEYS)})")
        _check_type(key, value, TOP_KEYS[key], source)
    for key in ("integrator", "duration", "model"):
        if key not in data:
            raise SceneError(f"{source}: missing key {key!r}")
    integrator = data["integrator"]
    if integrator not in INTEGRATORS:
        raise SceneError(f"{source}: integrator: unknown value {integrator!r} (expected {', '.join(INTEGRATORS)})")
    duration = float(data["duration"])
    if not (math.isfinite(duration) and duration > 0):
        raise SceneError(f"{source}: duration: must be a finite number > 0, got {data['duration']}")
    dt = {}
    for key, value in data.get("dt", {}).items():
        if key not in INTEGRATORS:
            raise SceneError(f"{source}: dt.{key}: unknown integrator (expected {', '.join(INTEGRATORS)})")
        _check_type(f"dt.{key}", value, float, source)
        if not (math.isfinite(value) and value > 0):
            raise SceneError(f"{source}: dt.{key}: must be a finite number > 0, got {value}")
        dt[key] = float(value)
    model = dict(data["model"])
    generator = model.pop("generator", None)
    if generator is None:
        raise SceneError(f"{source}: missing key 'model.generator'")
    _check_type("model.generator", generator, str, source)
    if generator not in generators.GENERATORS:
        raise SceneError(f"{source}: model.generator: unknown value {generator!r} "
                         f"(expected {', '.join(generators.GENERATORS)})")
    params, common = dict(generators.PARAMETERS[generator]), dict(COMMON_KEYS)
    for key, value in model.items():
        if key in COMMON_KEYS:
            common[key] = _check_common(key, value, f"{source}: model.{key}")
        else:
            params[key] = _check_param(generator, key, value, source)
    view = dict(data.get("view", {}))
    for key, value in view.items():
        if key not in VIEW_KEYS:
            raise SceneError(f"{source}: view.{key}: unknown key (expected {', '.join(VIEW_KEYS)})")
        _check_type(f"view.{key}", value, VIEW_KEYS[key], source)
    colliders = tuple(_collider(k, table, source) for k, table in enumerate(data.get("collider", [])))
    pins = tuple(_pin(k, table, source) for k, table in enumerate(data.get("pin", [])))
    return Scene(name=name, source=source, description=data.get("description", ""),
                 integrator=integrator, duration=duration, dt=dt,
                 generator=generator, params=params, view=view, common=common, colliders=colliders, pins=pins)


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
    if kind not in COLLIDERS:
        raise SceneError(f"{where}.type: expected one of {', '.join(map(repr, COLLIDERS))}, got {kind!r}")
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
    """A ``COMMON_KEYS`` value: a finite number >= 0 (drag) or 3 finite numbers."""
    default = COMMON_KEYS[key]
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


def _check_param(generator, key, value, source):
    defaults = generators.PARAMETERS[generator]
    prefix = source if source.startswith("--set") else f"{source}: model.{key}"
    if key not in defaults:
        raise SceneError(f"{prefix}: unknown parameter of generator {generator!r} "
                         f"(expected {', '.join(defaults)})")
    default = defaults[key]
    if isinstance(default, list):
        return _numbers(prefix, value, len(default))
    _check_type(prefix, value, type(default), None)
    if isinstance(default, float) and not math.isfinite(value):
        raise SceneError(f"{prefix}: must be finite, got {value!r}")
    return float(value) if isinstance(default, float) else value


def _check_type(key, value, expected, source):
    if expected is float:
        ok = isinstance(value, (int, float)) and not isinstance(value, bool)
        what = "a number"
    elif expected is int:
        ok = isinstance(value, int) and not isinstance(value, bool)
        what = "an integer"
    elif expected is dict:
        ok, what = isinstance(value, dict), "a table"
    elif expected is list:
        ok, what = isinstance(value, list), "a list"
    else:
        ok, what = isinstance(value, expected), "a string"
    if not ok:
        where = f"{source}: {key}" if source else key
        raise SceneError(f"{where}: expected {what}, got {type(value).__name__} {value!r}")
