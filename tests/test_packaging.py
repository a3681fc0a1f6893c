"""What ``pip install .`` (not editable) ships: every package of the source tree."""

import tomllib
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent


def test_every_package_is_listed_in_pyproject():
    """A package missing from [tool.setuptools] packages is left out of a wheel: the
    editable install used in development still imports it, an installed one does not."""
    config = tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["setuptools"]
    listed = set(config["packages"])
    dirs = {name: ROOT / path for name, path in config["package-dir"].items()}
    found = set()
    for name, base in dirs.items():
        for init in base.rglob("__init__.py"):
            parts = init.parent.relative_to(base).parts
            found.add(".".join((name, *parts)))
    assert found - listed == set(), f"packages not in pyproject.toml: {sorted(found - listed)}"


SHADOWED = """
import runpy, sys
# as after a non-editable install: no finder maps the checkout's kernels/ and scenes/ into the package
sys.meta_path[:] = [finder for finder in sys.meta_path if "editable" not in type(finder).__name__.lower()
                    and "editable" not in getattr(finder, "__name__", "").lower()]
sys.argv = ["massspring", *sys.argv[1:]]
runpy.run_module("massspring", run_name="__main__", alter_sys=True)
"""


def test_the_package_runs_from_the_repository_root_without_the_install_mapping():
    """From the repository's root the folder massspring/ is imported before an installed copy;
    ``python -m massspring`` must still find its kernels and scenes (they are top-level folders
    of the checkout, mapped into the package only by an install)."""
    import subprocess
    import sys

    proc = subprocess.run([sys.executable, "-c", SHADOWED, "scenes"], cwd=ROOT, capture_output=True, text=True,
                          timeout=300)
    assert proc.returncode == 0, proc.stderr[-2000:]
    assert "cloth" in proc.stdout
