"""The benchmarks' set-up and outputs: the ``bench`` extra installs every package they
import, and a run writes into benchmarks/out/ unless told to replace a committed result."""

import ast
import sys
import tomllib
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
BENCHMARKS = sorted((ROOT / "benchmarks").glob("*.py"))
DISTRIBUTIONS = {"warp": "warp-lang", "PIL": "pillow", "sksundae": "scikit-sundae"}  # import name -> package name, where they differ


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


OWN_EXTRA = {"vbd.py": "vbd"}  # a benchmark whose peer conflicts with [bench]'s pins: an extra (and a venv) of its own


def test_the_bench_extra_installs_what_the_benchmarks_import():
    """Every module a benchmark imports is this project, the standard library, or a package of
    the ``bench`` extra (of its own extra, ``OWN_EXTRA``); newton is imported past
    benchmarks/newton.py, so the test takes the name of the package, not of the file."""
    project = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]
    extras = project["optional-dependencies"]
    local = ({path.stem for path in BENCHMARKS} | {path.stem for path in (ROOT / "tests").glob("*.py")}
             | {path.stem for path in (ROOT / "examples").glob("*.py")} | {"massspring"})  # the project's own
    for path in BENCHMARKS:
        extra = OWN_EXTRA.get(path.name, "bench")
        installed = requirement_names(project["dependencies"] + extras[extra])
        allowed = local - {"newton"} if extra == "vbd" else local
        if extra == "vbd":
            installed |= {"warp-lang"}  # newton's own requirement
        for module in imported_modules(path) - allowed - set(sys.stdlib_module_names):
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


def test_every_massspring_name_a_benchmark_or_example_imports_exists():
    """The benchmarks and examples run no test of their own here: each name they import
    from massspring (a module path, or a name from one) must exist, so a module moved
    or renamed inside the package cannot leave one of them broken."""
    import importlib

    missing = []
    for path in BENCHMARKS + sorted((ROOT / "examples").glob("*.py")):
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.ImportFrom) and node.level == 0 and node.module.split(".")[0] == "massspring":
                module = importlib.import_module(node.module)
                missing += [f"{path.name}: {node.module}.{alias.name}" for alias in node.names
                            if not hasattr(module, alias.name)
                            and importlib.util.find_spec(f"{node.module}.{alias.name}") is None]
            elif isinstance(node, ast.Import):
                for alias in node.names:
                    if alias.name.startswith("massspring.") and importlib.util.find_spec(alias.name) is None:
                        missing.append(f"{path.name}: {alias.name}")
    assert not missing, missing
