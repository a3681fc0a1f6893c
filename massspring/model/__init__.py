"""What is simulated, as plain validated numpy data that never touches Taichi: ``Model``
(``model.py``), its mesh reading (``mesh.py``), force terms (``terms.py``), colliders
(``colliders/``), controls over time (``controls.py``), feedback controllers that choose them
from the state (``feedback.py``, the built-in ``network.py``), the settings of self-collision
and of the strain limit, and its renumbering for locality (``ordering.py``)."""

from massspring.model.model import PHYSICS, Model

__all__ = ["Model", "PHYSICS"]
