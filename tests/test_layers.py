"""The layers of docs/architecture.md hold: import-linter checks the contracts in
pyproject.toml ([tool.importlinter]) on the package as it is installed, and a planted
import across a layer breaks them. kernels/ holds only Taichi kernels and ``ti.func``s,
and massspring/ defines none.

The package is laid out as setuptools installs it ([tool.setuptools.package-dir]: the
folder kernels/ is ``massspring.kernels``) in a temporary directory, where
``lint-imports`` runs: an editable install maps kernels/ by an import hook that
import-linter does not follow.
"""

import ast
import os
import shutil
import subprocess
import sys
import tomllib
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
PYPROJECT = ROOT / "pyproject.toml"


def package_tree(into):
    """The package's modules copied to ``into`` as setuptools installs them; returns ``into``."""
    setup = tomllib.loads(PYPROJECT.read_text())["tool"]["setuptools"]
    folders = setup["package-dir"]
    for package in setup["packages"]:
        mapped = max((name for name in folders if package == name or package.startswith(name + ".")), key=len)
        source = ROOT / folders[mapped] / Path(*package[len(mapped):].split(".")[1:])
        target = into.joinpath(*package.split("."))
        target.mkdir(parents=True, exist_ok=True)
        for module in source.glob("*.py"):
            shutil.copy(module, target / module.name)
    return into


def lint_imports(tree):
    """``lint-imports`` on ``tree`` with the project's contracts: (exit code, its report)."""
    env = dict(os.environ, PYTHONPATH=str(tree), COLUMNS="200")
    done = subprocess.run([sys.executable, "-c", "import sys; from importlinter.cli import lint_imports_command; "
                           "sys.exit(lint_imports_command())", str(PYPROJECT), "--no-cache"],
                          cwd=tree, env=env, capture_output=True, text=True, timeout=120)
    return done.returncode, done.stdout + done.stderr


@pytest.fixture(scope="module")
def tree(tmp_path_factory):
    return package_tree(tmp_path_factory.mktemp("installed"))


def test_contracts_hold(tree):
    code, report = lint_imports(tree)
    assert code == 0, report
    contracts = tomllib.loads(PYPROJECT.read_text())["tool"]["importlinter"]["contracts"]
    assert report.count(" KEPT") == len(contracts) >= 4, report
    modules = len(list(tree.rglob("*.py")))
    assert f"Analyzed {modules} files" in report, report  # the kernels included


@pytest.mark.parametrize("module, line, broken", [
    ("kernels/planted.py", "from massspring.engine.simulation import Simulation",
     "massspring.kernels.planted -> massspring.engine.simulation"),  # a kernel module reaching up
    ("model_extra.py", "from massspring import cli",
     "massspring.model_extra"),  # a module outside every layer ("exhaustive")
    ("io/planted.py", "import massspring.device",
     "massspring.io is not allowed to import massspring.device"),  # files holding fields
    ("analysis/planted.py", "from massspring.kernels import cg",
     "massspring.analysis is not allowed to import massspring.kernels"),  # analysis calling a kernel
])
def test_a_planted_violation_breaks_a_contract(tmp_path, module, line, broken):
    tree = package_tree(tmp_path)
    (tree / "massspring" / module).write_text(f'"""Planted by tests/test_layers.py."""\n\n{line}\n')
    code, report = lint_imports(tree)
    assert code == 1 and "BROKEN" in report and broken in report, report


def decorators(function):
    return {ast.unparse(d) for d in function.decorator_list}


def is_taichi(function):
    return any(d.startswith(("ti.kernel", "ti.func")) for d in decorators(function))


def functions(path):
    """(qualified name, node) of every function defined in ``path`` (methods as Class.name)."""
    out = []
    for node in ast.parse(path.read_text()).body:
        if isinstance(node, ast.FunctionDef):
            out.append((node.name, node))
        elif isinstance(node, ast.ClassDef):
            out += [(f"{node.name}.{f.name}", f) for f in node.body if isinstance(f, ast.FunctionDef)]
    return out


def wrapped_as_funcs(path):
    """Names that a module turns into a ``ti.func`` by a call (``next_action = ti.func(exit_rule)``)."""
    return {node.args[0].id for node in ast.walk(ast.parse(path.read_text()))
            if isinstance(node, ast.Call) and ast.unparse(node.func) == "ti.func" and node.args
            and isinstance(node.args[0], ast.Name)}


def test_kernels_hold_only_kernels_and_funcs():
    host = []
    for path in sorted((ROOT / "kernels").rglob("*.py")):
        wrapped = wrapped_as_funcs(path)
        host += [f"{path.relative_to(ROOT)}: {name}" for name, f in functions(path)
                 if not is_taichi(f) and name not in wrapped]
    assert not host, f"host functions in kernels/ (move them to massspring/): {host}"


def test_no_kernel_outside_kernels():
    found = [f"{path.relative_to(ROOT)}: {name}" for path in sorted((ROOT / "massspring").rglob("*.py"))
             for name, f in functions(path) if is_taichi(f)]
    assert not found, f"kernels or ti.funcs outside kernels/ (move them there): {found}"
