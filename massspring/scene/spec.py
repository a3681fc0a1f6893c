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
            "view": dict}
VIEW_KEYS = {"azimuth": float, "elevation": float, "projection": str, "framing": str}


def builtin_scenes() -> dict:
    """Built-in scene name -> path of its TOML file."""
    root = resources.files("massspring.scenes")
    return {Path(p.name).stem: Path(str(p)) for p in root.iterdir() if p.name.endswith(".toml")}


@dataclass(frozen=True)
class Scene:
    """A parsed scene: ``params`` are the generator's full parameter set (defaults
    filled in); ``dt`` the default time steps the file names; ``view`` its [view]
    table (checked when a picture is made: see ``io.camera.View``)."""

    name: str
    source: str
    description: str
    integrator: str
    duration: float
    dt: dict
    generator: str
    params: dict = field(default_factory=dict)
    view: dict = field(default_factory=dict)
    _suggested: dict = field(default_factory=dict, repr=False, compare=False)

    def with_params(self, **overrides) -> "Scene":
        """A copy with some generator parameters replaced (checked like the file's)."""
        params = dict(self.params)
        for key, value in overrides.items():
            params[key] = _check_param(self.generator, key, value, self.source)
        return dataclasses.replace(self, params=params, _suggested={})

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
            return Model(**generators.GENERATORS[self.generator](**self.params))
        except ValueError as exc:
            raise SceneError(f"{self.source}: model.{exc}") from None

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
    params = dict(generators.PARAMETERS[generator])
    for key, value in model.items():
        params[key] = _check_param(generator, key, value, source)
    view = dict(data.get("view", {}))
    for key, value in view.items():
        if key not in VIEW_KEYS:
            raise SceneError(f"{source}: view.{key}: unknown key (expected {', '.join(VIEW_KEYS)})")
        _check_type(f"view.{key}", value, VIEW_KEYS[key], source)
    return Scene(name=name, source=source, description=data.get("description", ""),
                 integrator=integrator, duration=duration, dt=dt,
                 generator=generator, params=params, view=view)


def _check_param(generator, key, value, source):
    defaults = generators.PARAMETERS[generator]
    prefix = source if source.startswith("--set") else f"{source}: model.{key}"
    if key not in defaults:
        raise SceneError(f"{prefix}: unknown parameter of generator {generator!r} "
                         f"(expected {', '.join(defaults)})")
    default = defaults[key]
    if isinstance(default, list):
        _check_type(prefix, value, list, None)
        if len(value) != len(default):
            raise SceneError(f"{prefix}: expected {len(default)} numbers, got {value!r}")
        for item in value:
            _check_type(prefix, item, float, None)
        return [float(item) for item in value]
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
