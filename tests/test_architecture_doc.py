"""docs/architecture.md says what the code is: its layers table is the import contract
that tests/test_layers.py checks, the contract's exception and its forbidden imports are
the ones it lists, its packages table names every module, each row of "Where a change
goes" names files that exist, every file it names is in the repository, and every code
name it writes in backquotes (a module, class, function, attribute, constant or status
string) is defined or written somewhere in the package, the kernels or the benchmarks."""

import ast
import re
import tomllib
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
DOC = (ROOT / "docs" / "architecture.md").read_text()
CONTRACTS = tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["importlinter"]["contracts"]
SOURCES = [p for d in ("massspring", "kernels", "benchmarks") for p in (ROOT / d).rglob("*.py")]
PLACES = [ROOT, ROOT / "massspring", ROOT / "kernels", *(p for p in (ROOT / "massspring").iterdir() if p.is_dir())]


def section(title):
    """The text of the section headed ``## title``, up to the next one."""
    return re.search(rf"^## {re.escape(title)}\n(.*?)(?=^## |\Z)", DOC, flags=re.S | re.M).group(1)


def table(text):
    """The rows of the first table in ``text`` as lists of cells, without the header."""
    rows = [line for line in text.splitlines() if line.startswith("|")]
    return [[cell.strip() for cell in row.strip("|").split("|")] for row in rows[2:]]


def spans(text):
    return re.findall(r"`([^`\n]+)`", text)


def tail(module):
    """``massspring.kernels`` -> ``kernels``: a module as the doc writes it."""
    return module.removeprefix("massspring.")


def code_spans():
    return sorted(set(spans(DOC)))


def known_names():
    """Every name the sources define or mention: modules and packages, classes, functions,
    arguments, assigned names and attributes, attribute accesses, and string constants."""
    names = {p.name for p in (ROOT / "massspring").iterdir() if p.is_dir()}
    for path in SOURCES:
        names.add(path.stem)
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, (ast.FunctionDef, ast.ClassDef)):
                names.add(node.name)
            elif isinstance(node, ast.Name):
                names.add(node.id)
            elif isinstance(node, ast.Attribute):
                names.add(node.attr)
            elif isinstance(node, ast.arg):
                names.add(node.arg)
            elif isinstance(node, ast.Constant) and isinstance(node.value, str):
                names.add(node.value)
    return names


def is_path(span):
    return " " not in span and ("/" in span and not span.startswith(("-", "[")) or span.endswith((".py", ".md", ".toml")))


def exists(path):
    path = path.rstrip("/")
    return any((place / path).exists() for place in PLACES) or (ROOT / "massspring" / "io" / path).exists()


def named_files(text):
    """The files and folders written in backquotes in ``text`` (not dotted modules or expressions)."""
    return [s for s in spans(text) if is_path(s) and not s.startswith(("massspring.", "kernels."))
            and "=" not in s and "(" not in s]


def test_every_file_and_folder_named_exists():
    missing = [span for span in named_files(DOC) if not exists(span)]
    assert not missing, f"docs/architecture.md names files that do not exist: {missing}"


def test_no_file_outside_the_repository_is_cited():
    """Written in backquotes or not, every file name in the doc is one of the repository's."""
    missing = [name for name in set(re.findall(r"[\w./-]*\w\.(?:py|md|toml|json)\b", DOC)) if not exists(name)]
    assert not missing, f"docs/architecture.md cites files that are not in the repository: {missing}"


def test_every_code_name_is_defined_somewhere():
    names = known_names()
    missing = []
    for span in code_spans():
        if is_path(span) or span.startswith(("-", "[", ".", "massspring ")) or " " in span:
            continue  # options, TOML tables, suffixes, commands and prose
        for part in re.split(r"[.()=,\[\]]+", span):
            if re.fullmatch(r"[A-Za-z_][A-Za-z0-9_]*", part) and part not in names:
                missing.append(f"{span} ({part})")
    assert not missing, f"docs/architecture.md names what the code does not have: {missing}"


def test_the_layers_table_is_the_import_contract():
    (layers,) = [c for c in CONTRACTS if c["type"] == "layers"]
    contract = [sorted(m.strip() for m in layer.split("|")) for layer in layers["layers"]]
    doc = [sorted(spans(row[1])) for row in table(section("Layers"))]
    assert doc == contract, f"the doc's layers, top down: {doc}; the contract's: {contract}"
    assert [row[0] for row in table(section("Layers"))] == [str(k) for k in range(1, len(contract) + 1)]


def test_the_contracts_exceptions_and_forbidden_imports_are_written():
    """Each ignored import is written as in the contract; each forbidden contract has a
    bullet naming all its source modules and all its forbidden ones."""
    text = section("Layers")
    bullets = [" ".join(b.split()) for b in re.split(r"\n- ", text)]
    for contract in CONTRACTS:
        for ignored in contract.get("ignore_imports", []):
            assert f"`{ignored}`" in text, ignored
        if contract["type"] == "forbidden":
            modules = contract["source_modules"] + contract["forbidden_modules"]
            assert any(all(f"`{m}`" in b or f"`{tail(m)}`" in b for m in modules) for b in bullets), \
                (contract["name"], modules)


def test_the_packages_table_names_every_module():
    cells = table(section("Packages"))
    first = {s for row in cells for s in spans(row[0])}
    modules = {f"massspring/{p.name}" + ("/" if p.is_dir() else "") for p in (ROOT / "massspring").iterdir()
               if (p.suffix == ".py" and p.stem not in ("__init__", "__main__")) or (p / "__init__.py").exists()}
    assert not modules - first, f"modules missing from the packages table: {sorted(modules - first)}"
    (kernels,) = [row[1] for row in cells if "`kernels/`" in row[0]]
    files = {p.name for p in (ROOT / "kernels").glob("*.py") if p.stem != "__init__"} | {"terms/"}
    assert not {f for f in files if f"`{f}`" not in kernels}, files


def test_every_change_names_files_that_exist():
    for change, touches in table(section("Where a change goes")):
        files = named_files(touches)
        assert files, f"'{change}' names no file"
        missing = [f for f in files if not exists(f)]
        assert not missing, f"'{change}' names files that do not exist: {missing}"
