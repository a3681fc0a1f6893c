"""What is simulated, as plain validated numpy data that never touches Taichi: ``Model``
(``model.py``), its mesh reading (``mesh.py``), force terms (``terms.py``), colliders
(``colliders/``), controls over time (``controls.py``), the settings of self-collision
and of the strain limit, and its renumbering for locality (``ordering.py``)."""

from massspring.model.model import PHYSICS, Model

__all__ = ["Model", "PHYSICS"]
