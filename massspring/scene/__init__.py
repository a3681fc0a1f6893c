"""Scenes: TOML files (``spec``), the generators that turn parameters into a Model
(``generators``), and the built-in scene files (package ``massspring.scenes``)."""

from massspring.scene import generators
from massspring.scene.spec import Scene, SceneError, builtin_scenes, load_scene, parse_scene

__all__ = ["Scene", "SceneError", "builtin_scenes", "generators", "load_scene", "parse_scene"]
