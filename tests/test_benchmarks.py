"""The benchmarks' set-up and outputs: the ``bench`` extra installs every package they
import, and a run writes into benchmarks/out/ unless told to replace a committed result."""

import ast
import sys
import tomllib
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
BENCHMARKS = sorted((ROOT / "benchmarks").glob("*.py"))
DISTRIBUTIONS = {"warp": "warp-lang", "PIL": "pillow"}  # import name -> package name, where they differ


def requirement_names(requirements):
    return {r.split(";")[0].split("[")[0].split("<")[0].split(">")[0].split("=")[0].strip().lower()
            for r in requirements}


def imported_modules(path):
    modules = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.Import):
            modules |= {alias.name.split(".")[0] for alias in node.names}
        elif isinstance(node, ast.ImportFrom) and node.level == 0:
            modules.add(node.module.split(".")[0])
    return modules


def test_the_bench_extra_installs_what_the_benchmarks_import():
    project = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]
    installed = requirement_names(project["dependencies"] + project["optional-dependencies"]["bench"])
    local = {path.stem for path in BENCHMARKS} | {path.stem for path in (ROOT / "tests").glob("*.py")} | {"massspring"}
    for path in BENCHMARKS:
        for module in imported_modules(path) - local - set(sys.stdlib_module_names):
            assert DISTRIBUTIONS.get(module, module).lower() in installed, (path.name, module)


def test_benchmarks_write_outside_the_committed_results_by_default():
    import importlib.util

    spec = importlib.util.spec_from_file_location("output", ROOT / "benchmarks" / "output.py")
    output = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(output)
    assert output.OUT != output.RESULTS and "benchmarks/out/" in (ROOT / ".gitignore").read_text().split()
    writers = [path for path in BENCHMARKS if "args.json" in path.read_text()]
    assert len(writers) >= 10
    for path in writers:
        text = path.read_text()
        assert "output.add_json(p, " in text and 'default="benchmarks/results' not in text, path.name
    for name, option in (("plot_performance.py", "--png"), ("study_figures.py", "--docs")):
        text = (ROOT / "benchmarks" / name).read_text()
        assert "default=str(output.OUT" in text and 'default="docs' not in text, (name, option)
