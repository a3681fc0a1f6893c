"""What to install for an optional feature: the packages of one of the project's extras.

Another project holds the name "massspring" on PyPI, so a hint never says ``pip install
"massspring[plot]"`` (that installs the other project); this one is distributed as
"massspring-taichi", which is not on PyPI either. It names the extra's own
requirements instead, as this installation's metadata lists them (``pyproject.toml``'s
``[project.optional-dependencies]``), or, without metadata, the install from a checkout.
"""

from __future__ import annotations

import re
from importlib import metadata

DISTRIBUTION = "massspring-taichi"  # pyproject.toml's [project] name (the import name is massspring)


def requirements(extra: str) -> list:
    """The requirement strings of ``extra`` (["matplotlib>=3.5"] for "plot"); [] if this
    installation has no metadata or no such extra."""
    try:
        requires = metadata.requires(DISTRIBUTION) or []
    except metadata.PackageNotFoundError:
        return []
    wanted = re.compile(r"""extra\s*==\s*["']%s["']""" % re.escape(extra))
    return [spec.strip() for spec, _, marker in (req.partition(";") for req in requires) if wanted.search(marker)]


def install_hint(extra: str) -> str:
    """The command that installs ``extra``: 'pip install "matplotlib>=3.5"' for "plot"."""
    found = requirements(extra)
    if not found:
        return f'pip install -e ".[{extra}]" in the massspring checkout'
    return "pip install " + " ".join(f'"{spec}"' for spec in found)
