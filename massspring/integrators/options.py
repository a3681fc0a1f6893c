"""The record of a solver option that an integrator declares (``Integrator.options``).

``Simulation``'s keywords, settings and properties, a scene's ``[solver]`` keys, the
command line's flags, ``massspring info`` and the study's tolerance sweeps are made
from these records (``integrators.OPTIONS``); docs/scenes.md's ``[solver]`` rows are
checked against them (tests/test_docs.py).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from massspring.support import validate

KINDS = {"fraction": float, "count": int, "choice": str, "switch": bool}


@dataclass(frozen=True)
class Option:
    """A Simulation argument of an integrator's solver.

    ``kind``: "fraction" (a number in (0, 1)), "count" (an integer >= 1), "choice" (one
    of ``choices``) or "switch" (true or false); ``default`` (None: ``default_text`` says
    what it is, computed from the model by ``Simulation``); ``doc``: what it does, one
    sentence (``Simulation``'s docstring, the flag's help); ``lacking``: what an
    integrator without it does not do (the command line's refusal); ``sweep``: the
    values the study tries by default where it sweeps this option (a tolerance), else ().
    """

    name: str
    kind: str
    default: object
    doc: str
    lacking: str
    choices: tuple = ()
    default_text: str = ""
    sweep: tuple = ()

    def __post_init__(self):
        assert self.kind in KINDS, self.kind

    @property
    def type(self) -> type:
        """The Python type of its values (a scene file's TOML type)."""
        return KINDS[self.kind]

    @property
    def flag(self) -> str:
        """The command-line flag: --cg-tol; a switch on by default is turned off by --no-<name>."""
        stem = self.name.replace("_", "-")
        return f"--no-{stem}" if self.kind == "switch" and self.default else f"--{stem}"

    @property
    def bounds(self) -> str:
        """The values it takes, in words (docs/scenes.md's type column)."""
        return {"fraction": "number in (0, 1)", "count": "integer ≥ 1", "choice": "string",
                "switch": "true or false"}[self.kind]

    def check(self, value, label=None):
        """``value`` checked; ValueError naming ``label`` (default: the option's name)."""
        label = label or self.name
        if self.kind == "fraction":
            return validate.fraction(label, value)
        if self.kind == "count":
            return validate.count(label, value)
        if self.kind == "choice":
            validate.choice(label, value, self.choices)
            return value
        if not isinstance(value, (bool, np.bool_)):
            raise ValueError(f"{label}: expected true or false, got {value!r}")
        return bool(value)

    def described_default(self) -> str:
        """The default in words: 1e-6, 50, auto, true."""
        if self.default_text:
            return self.default_text
        if isinstance(self.default, bool):
            return str(self.default).lower()
        return f"{self.default:g}".replace("e-0", "e-") if isinstance(self.default, float) else str(self.default)
