"""massspring: mass-spring systems with explicit, symplectic and implicit Euler on Taichi kernels."""

import os

# Taichi prints a banner on import; keep the CLI's stdout clean (set it to 1 to see it).
os.environ.setdefault("ENABLE_TAICHI_HEADER_PRINT", "0")

from massspring.errors import DivergenceError  # noqa: E402
from massspring.model import Model  # noqa: E402
from massspring.scene import Scene, SceneError, load_scene  # noqa: E402
from massspring.simulation import Simulation  # noqa: E402

__all__ = ["Model", "Simulation", "Scene", "SceneError", "load_scene", "DivergenceError"]
__version__ = "0.1.0"
