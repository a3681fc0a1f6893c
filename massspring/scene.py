"""Scenes: TOML files naming a generator, its parameters, and run defaults.

A scene file looks like::

    description = "Square cloth pinned at two corners"
    integrator = "implicit"          # default integrator
    duration = 2.0                   # simulated seconds of a default run

    [dt]                             # default dt (s) per integrator
    explicit = 2e-5
    symplectic = 5e-5
    implicit = 0.0166667

    [model]
    generator = "grid"               # one of massspring.generators.GENERATORS
    resolution = 32                  # generator parameters; see generators.PARAMETERS

    [view]                           # optional: camera of GIF/PNG export (see render.View)
    azimuth = -60.0                  # degrees about +z, 0 = looking from +x
    elevation = 20.0                 # degrees above the xy plane
    projection = "orthographic"      # or "perspective"

Unknown keys, wrong types and missing values raise ``SceneError`` (a
``ValueError``) naming the key and the file.
"""

from __future__ import annotations

import dataclasses
import tomllib
from dataclasses import dataclass, field
from importlib import resources
from pathlib import Path

from massspring import generators
from massspring.model import Model
from massspring.render import View
from massspring.simulation import INTEGRATORS, Simulation


class SceneError(ValueError):
    """A scene file or override is invalid; the message names the key and the file."""


TOP_KEYS = {"description": str, "integrator": str, "duration": float, "dt": dict, "model": dict,
            "view": dict}
VIEW_KEYS = {"azimuth": float, "elevation": float, "projection": str}  # optional [view]: see render.View


def builtin_scenes() -> dict:
    """Built-in scene name -> path of its TOML file."""
    root = resources.files("massspring.scenes")
    return {Path(p.name).stem: Path(str(p)) for p in root.iterdir() if p.name.endswith(".toml")}


@dataclass(frozen=True)
class Scene:
    """A parsed scene: ``params`` are the generator's full parameter set (defaults filled in)."""

    name: str
    source: str
    description: str
    integrator: str
    duration: float
    dt: dict
    generator: str
    params: dict = field(default_factory=dict)
    view: View = field(default_factory=View)

    def triangles(self):
        """(t, 3) int surface triangles of the scene's model, for drawing (see generators.surface)."""
        return generators.surface(self.generator, self.params)

    def with_params(self, **overrides) -> "Scene":
        """A copy with some generator parameters replaced (checked like the file's)."""
        params = dict(self.params)
        for key, value in overrides.items():
            params[key] = _check_param(self.generator, key, value, self.source)
        return dataclasses.replace(self, params=params)

    def with_settings(self, settings) -> "Scene":
        """Apply ``key=value`` strings (values parsed as TOML, else taken as strings)."""
        overrides = {}
        for item in settings:
            key, sep, text = item.partition("=")
            key = key.strip()
            if not sep or not key:
                raise SceneError(f"--set: expected key=value, got {item!r}")
            try:
                value = tomllib.loads(f"v = {text.strip()}")["v"]
            except tomllib.TOMLDecodeError:
                value = text.strip()
            overrides[key] = _check_param(self.generator, key, value, "--set")
        return self.with_params(**overrides)

    def model(self) -> Model:
        """Build the Model (raises ValueError naming the parameter if a value is out of range)."""
        try:
            return Model(**generators.GENERATORS[self.generator](**self.params))
        except ValueError as exc:
            raise SceneError(f"{self.source}: model: {exc}") from None

    def default_dt(self, integrator=None) -> float:
        return self.dt[integrator or self.integrator]

    def simulation(self, integrator=None, dt=None, **kwargs) -> Simulation:
        """A Simulation with the scene's defaults; any Simulation argument may be overridden."""
        integrator = integrator or self.integrator
        if integrator not in INTEGRATORS:
            raise ValueError(f"integrator: unknown value {integrator!r}, expected one of {', '.join(INTEGRATORS)}")
        return Simulation(self.model(), integrator=integrator,
                          dt=self.default_dt(integrator) if dt is None else dt, **kwargs)


def load_scene(name_or_path) -> Scene:
    """Load a built-in scene by name (see ``builtin_scenes``) or a TOML file by path."""
    scenes = builtin_scenes()
    path = scenes.get(str(name_or_path))
    if path is None:
        path = Path(name_or_path)
        if not path.is_file():
            raise SceneError(f"scene: {name_or_path!r} is neither a built-in scene "
                             f"({', '.join(sorted(scenes))}) nor a file")
    source = str(path)
    try:
        data = tomllib.loads(path.read_text(encoding="utf-8"))
    except (tomllib.TOMLDecodeError, UnicodeDecodeError) as exc:
        raise SceneError(f"{source}: not valid TOML: {exc}") from None
    return parse_scene(data, name=path.stem, source=source)


def parse_scene(data: dict, name: str, source: str) -> Scene:
    """Check a scene's TOML data and fill in defaults."""
    for key, value in data.items():
        if key not in TOP_KEYS:
            raise SceneError(f"{source}: unknown key {key!r} (expected {', '.join(TOP_KEYS)})")
        _check_type(key, value, TOP_KEYS[key], source)
    for key in ("integrator", "duration", "dt", "model"):
        if key not in data:
            raise SceneError(f"{source}: missing key {key!r}")
    integrator = data["integrator"]
    if integrator not in INTEGRATORS:
        raise SceneError(f"{source}: integrator: unknown value {integrator!r} (expected {', '.join(INTEGRATORS)})")
    if not data["duration"] > 0:
        raise SceneError(f"{source}: duration: must be > 0, got {data['duration']}")
    dt = {}
    for key, value in data["dt"].items():
        if key not in INTEGRATORS:
            raise SceneError(f"{source}: dt.{key}: unknown integrator (expected {', '.join(INTEGRATORS)})")
        _check_type(f"dt.{key}", value, float, source)
        if not value > 0:
            raise SceneError(f"{source}: dt.{key}: must be > 0, got {value}")
        dt[key] = float(value)
    for key in INTEGRATORS:
        if key not in dt:
            raise SceneError(f"{source}: missing key 'dt.{key}'")
    model = dict(data["model"])
    generator = model.pop("generator", None)
    if generator is None:
        raise SceneError(f"{source}: missing key 'model.generator'")
    if generator not in generators.GENERATORS:
        raise SceneError(f"{source}: model.generator: unknown value {generator!r} "
                         f"(expected {', '.join(generators.GENERATORS)})")
    params = dict(generators.PARAMETERS[generator])
    for key, value in model.items():
        params[key] = _check_param(generator, key, value, source)
    return Scene(name=name, source=source, description=data.get("description", ""),
                 integrator=integrator, duration=float(data["duration"]), dt=dt,
                 generator=generator, params=params, view=_parse_view(data.get("view", {}), source))


def _parse_view(table, source):
    for key, value in table.items():
        if key not in VIEW_KEYS:
            raise SceneError(f"{source}: view.{key}: unknown key (expected {', '.join(VIEW_KEYS)})")
        _check_type(f"view.{key}", value, VIEW_KEYS[key], source)
    try:
        return View(**table)
    except ValueError as exc:
        raise SceneError(f"{source}: {exc}") from None


def _check_param(generator, key, value, source):
    defaults = generators.PARAMETERS[generator]
    if key not in defaults:
        raise SceneError(f"{source}: model.{key}: unknown parameter of generator {generator!r} "
                         f"(expected {', '.join(defaults)})")
    default = defaults[key]
    if isinstance(default, list):
        _check_type(f"model.{key}", value, list, source)
        if len(value) != len(default):
            raise SceneError(f"{source}: model.{key}: expected {len(default)} numbers, got {value!r}")
        for item in value:
            _check_type(f"model.{key}", item, float, source)
        return [float(item) for item in value]
    _check_type(f"model.{key}", value, type(default), source)
    return float(value) if isinstance(default, float) else value


def _check_type(key, value, expected, source):
    if expected is float:
        ok = isinstance(value, (int, float)) and not isinstance(value, bool)
    elif expected is int:
        ok = isinstance(value, int) and not isinstance(value, bool)
    else:
        ok = isinstance(value, expected)
    if not ok:
        raise SceneError(f"{source}: {key}: expected {expected.__name__ if expected is not dict else 'a table'}, "
                         f"got {type(value).__name__} {value!r}")
