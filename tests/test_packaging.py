"""What ``pip install .`` (not editable) ships: every package of the source tree."""

import re
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


# an install of the name "massspring" from an index (with or without extras), not of a path
FROM_AN_INDEX = re.compile(r"""pip install\s+(?:-e\s+)?["']?massspring(?:\[|\s|["']|$)""")


def test_no_command_or_message_installs_the_other_projects_distribution():
    """The name "massspring" on PyPI belongs to another project (issue 42): no install
    line of the README, the docs, the examples, the benchmarks or the package's own
    messages may install it. Paths (`pip install "./massspring[cluster]"`) are fine."""
    files = [ROOT / "README.md", *(ROOT / "docs").glob("*.md"), *(ROOT / "examples").glob("*.py"),
             *(ROOT / "benchmarks").glob("*.py"), *(ROOT / "massspring").rglob("*.py"), *(ROOT / "tests").glob("*.py")]
    found = [f"{path.relative_to(ROOT)}:{number}: {line.strip()}" for path in files
             for number, line in enumerate(path.read_text().splitlines(), 1)
             if FROM_AN_INDEX.search(line) and "FROM_AN_INDEX" not in line and "re.compile" not in line]
    assert found == []
    assert FROM_AN_INDEX.search("""pip install 'massspring[plot]'""") and FROM_AN_INDEX.search("pip install massspring")
    assert not FROM_AN_INDEX.search('pip install "./massspring[cluster]"')


def test_install_hints_name_each_extras_own_packages():
    """``extras.install_hint`` names what pyproject.toml's extra lists (read back from the
    installation's metadata, which may reorder a requirement's version bounds); an extra
    it does not know falls back to the checkout."""
    from massspring.support.extras import install_hint

    def parsed(requirement):  # (name with extras, set of version bounds)
        name = re.match(r"[A-Za-z0-9_.\-\[\]]+", requirement).group(0)
        return name, frozenset(filter(None, requirement[len(name):].replace(" ", "").split(",")))

    extras = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]["optional-dependencies"]
    for extra, requirements in extras.items():
        hint = install_hint(extra)
        assert hint.startswith("pip install ") and "massspring" not in hint, hint
        named = {parsed(quoted) for quoted in re.findall(r'"([^"]+)"', hint)}
        assert named == {parsed(requirement) for requirement in requirements}, (extra, hint)
    assert install_hint("no-such-extra") == 'pip install -e ".[no-such-extra]" in the massspring checkout'


def test_the_distribution_is_not_named_as_the_other_project():
    """Issue 60: installed as "massspring", `pip index versions massspring` reported
    "INSTALLED: 0.2.0, LATEST: 1.2.0" and `pip install -U massspring` replaced it with the
    other project; the distribution has a name of its own, which ``extras`` reads."""
    from massspring.support import extras

    name = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]["name"]
    assert name != "massspring" and extras.DISTRIBUTION == name
    assert extras.requirements("plot") == ["matplotlib>=3.5"]  # the metadata found under that name
