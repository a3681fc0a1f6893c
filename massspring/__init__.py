"""massspring: mass-spring systems with explicit, symplectic and implicit Euler on Taichi kernels."""

import os
import sys

if sys.version_info < (3, 11):  # tomllib, and the syntax used throughout
    raise ImportError(f"massspring needs Python 3.11 or later; this is {sys.version.split()[0]}")

# Imported from a source checkout (this folder beside kernels/ and scenes/: run from the
# repository's root after a non-editable install, whose copy the checkout then shadows),
# the package's kernels and scenes are the checkout's, as an install maps them.
_root = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
if not os.path.isdir(os.path.join(os.path.dirname(__file__), "kernels")) and os.path.isfile(
        os.path.join(_root, "kernels", "__init__.py")):
    __path__.append(_root)

# Taichi prints a banner on import; keep the CLI's stdout clean (set it to 1 to see it).
os.environ.setdefault("ENABLE_TAICHI_HEADER_PRINT", "0")

from massspring.support.defaults import VERSION  # noqa: E402
from massspring.support.errors import DivergenceError, KinkWarning, SimulationClosedError  # noqa: E402
from massspring.model.controls import Controls  # noqa: E402
from massspring.model.feedback import Controller, ControlState  # noqa: E402
from massspring.model.network import SineNetwork  # noqa: E402
from massspring.model import Model  # noqa: E402
from massspring.model.colliders import Box, Plane, Sphere  # noqa: E402
from massspring.model.self_collision import SelfCollision  # noqa: E402
from massspring.scene import Scene, SceneError, load_scene  # noqa: E402
from massspring.engine.simulation import Simulation, run  # noqa: E402
from massspring.gradients import Frames, gradient  # noqa: E402
from massspring.analysis.sweep import sweep  # noqa: E402

__all__ = ["Model", "Controls", "Controller", "ControlState", "SineNetwork", "Plane", "Sphere", "Box", "SelfCollision", "Simulation", "run", "Scene", "SceneError", "load_scene",
           "sweep", "gradient", "Frames", "DivergenceError", "KinkWarning", "SimulationClosedError"]
__version__ = VERSION
