"""docs/architecture.md says what the code is. Checked against the sources, without
importing the package (no Taichi, no kernels):

* its packages table has a row for every package of massspring/, kernels/ and scenes/
  (a folder with an ``__init__.py``), every row is a folder that exists, and each row
  names every module and subfolder of its folder (and its ``__init__.py`` where that
  defines something), each file it names being there;
* its layers table is the ``layers`` contract of pyproject.toml (folders, order, and
  whether a row's folders may import each other), and the contract's exception and
  forbidden imports are written under it, the exception with the function that makes it;
* each row of "Where a change goes" names files that exist, and the kinds of change
  the project grows by each have a row;
* every code name written in backquotes (a module, class, function, attribute,
  constant or string) is defined or written somewhere in the package, the kernels or
  the benchmarks, and every file the doc cites is in the repository;
* facts that went stale once: the bundles of their own are counted and named, every
  CLI verb is named, the Model row names every field of ``Model``.
"""

import ast
import re
import tomllib
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
DOC = (ROOT / "docs" / "architecture.md").read_text()
CONTRACTS = tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["importlinter"]["contracts"]
SOURCES = [p for d in ("massspring", "kernels", "benchmarks") for p in (ROOT / d).rglob("*.py")]
TREES = ("massspring", "kernels", "scenes")  # the folders that hold the installed packages
# Named in the doc's one sentence about the pass protocol (issue 61), being written: cited
# as plain text, allowed to be missing until it lands (then its folder's row must name it).
COMING = {"massspring/passes/base.py"}
# The kinds of change the "Where a change goes" table must keep a row for.
CHANGES = ("a force term", "an integrator", "a preconditioner", "an output format", "a collider kind", "a pass",
           "a CLI verb", "a scene key", "a module")
NUMBERS = {"one": 1, "two": 2, "three": 3, "four": 4, "five": 5, "six": 6, "seven": 7, "eight": 8}


def section(title):
    """The text of the section headed ``## title``, up to the next one."""
    match = re.search(rf"^## {re.escape(title)}\n(.*?)(?=^## |\Z)", DOC, flags=re.S | re.M)
    assert match, f"docs/architecture.md has no section '## {title}'"
    return match.group(1)


def table(text):
    """The rows of the first table in ``text`` as lists of cells, without the header."""
    rows = [line for line in text.splitlines() if line.startswith("|")]
    return [[cell.strip() for cell in row.strip().strip("|").split("|")] for row in rows[2:]]


def spans(text):
    return re.findall(r"`([^`\n]+)`", text)


def tail(module):
    """``massspring.kernels`` -> ``kernels``: a module as the doc writes it."""
    return module.removeprefix("massspring.")


def is_path(span):
    return " " not in span and ("/" in span and not span.startswith(("-", "[")) or span.endswith((".py", ".md", ".toml")))


def named_files(text):
    """The files and folders written in backquotes in ``text`` (not dotted modules or expressions)."""
    return [s for s in spans(text) if is_path(s) and not s.startswith(("massspring.", "kernels."))
            and "=" not in s and "(" not in s and "<" not in s]


def repository_paths():
    """Every file and folder of the repository, relative to its root (hidden folders,
    caches and build outputs left out)."""
    paths = set()
    for path in ROOT.rglob("*"):
        parts = path.relative_to(ROOT).parts
        if any(p.startswith(".") or p in ("__pycache__", "build", "dist") or p.endswith(".egg-info") for p in parts):
            continue
        paths.add("/".join(parts))
    return paths


PATHS = repository_paths()


def exists_somewhere(name):
    """Whether ``name`` (a path, or a bare file name) is a file or folder of the repository."""
    name = name.rstrip("/")
    return name in PATHS or any(p.endswith("/" + name) for p in PATHS)


def resolves(name, *bases):
    """Whether ``name`` is a file or folder relative to one of ``bases`` (folders of the
    repository as written in the doc), to the repository's root or to massspring/."""
    name = name.rstrip("/")
    return any((ROOT / base / name).exists() for base in (*bases, "", "massspring"))


def package_rows():
    """{folder (as written, with its trailing slash): the row's text} of the packages table."""
    rows = {}
    for first, holds in table(section("Packages")):
        (folder,) = [s for s in spans(first) if s.endswith("/")] or [first]
        rows[folder] = holds
    return rows


def packages():
    """Every package folder of the trees, as the doc writes it: ``massspring/model/``."""
    return sorted(str(init.parent.relative_to(ROOT)) + "/" for tree in TREES for init in (ROOT / tree).rglob("__init__.py")
                  if "__pycache__" not in init.parts)


def defines_something(module):
    """Whether a module defines a function, class or public name (not only imports it)."""
    for node in ast.parse(module.read_text()).body:
        if isinstance(node, (ast.FunctionDef, ast.ClassDef)):
            return True
        targets = node.targets if isinstance(node, ast.Assign) else [node.target] if isinstance(node, ast.AnnAssign) else []
        if any(isinstance(t, ast.Name) and not t.id.startswith("_") for t in targets):
            return True
    return False


def known_names():
    """Every name the sources define or mention: modules and packages, classes, functions,
    arguments, assigned names and attributes, attribute accesses, and string constants."""
    names = {p.name for tree in TREES for p in (ROOT / tree).rglob("*") if p.is_dir()}
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


# ---------------------------------------------------------------- the packages table

def test_every_package_has_a_row_and_every_row_is_a_package_folder():
    rows = package_rows()
    missing = [p for p in packages() if p not in rows]
    assert not missing, f"packages without a row in docs/architecture.md: {missing}"
    absent = [folder for folder in rows if not folder.endswith("/") or not (ROOT / folder).is_dir()]
    assert not absent, f"rows of docs/architecture.md that are not folders of the repository: {absent}"


@pytest.mark.parametrize("folder", packages())
def test_each_row_names_every_module_of_its_folder(folder):
    """A module ``x.py`` (or a subpackage ``x/``) is named in its folder's row as `x.py`
    (`x/`) or by a path ending so; ``__init__.py`` too where it defines something."""
    holds = package_rows().get(folder, "")
    named = set(spans(holds))

    def is_named(name):
        return name in named or any(s.endswith("/" + name) for s in named)

    path = ROOT / folder
    wanted = [m.name for m in sorted(path.glob("*.py")) if m.name != "__init__.py" or defines_something(m)]
    wanted += [d.name + "/" for d in sorted(path.iterdir()) if (d / "__init__.py").exists()]
    missing = [name for name in wanted if not is_named(name)]
    assert not missing, f"the row of {folder} in docs/architecture.md does not name {missing}"


@pytest.mark.parametrize("folder", sorted(package_rows()))
def test_each_row_names_only_files_that_exist(folder):
    missing = [name for name in named_files(package_rows()[folder]) if not resolves(name, folder)]
    assert not missing, f"the row of {folder} in docs/architecture.md names files that do not exist: {missing}"


def test_the_model_row_names_every_field_of_model():
    """Every field of ``Model`` (the dataclass's annotations) and every force term's own
    parameter (``Parameter("name", ...)`` in model/terms.py) is written in the model row."""
    tree = ast.parse((ROOT / "massspring" / "model" / "model.py").read_text())
    (model,) = [n for n in tree.body if isinstance(n, ast.ClassDef) and n.name == "Model"]
    fields = [n.target.id for n in model.body if isinstance(n, ast.AnnAssign)]
    terms = ast.parse((ROOT / "massspring" / "model" / "terms.py").read_text())
    fields += [n.args[0].value for n in ast.walk(terms) if isinstance(n, ast.Call)
               and getattr(n.func, "id", None) == "Parameter"]
    assert len(fields) > 10
    row = set(spans(package_rows()["massspring/model/"]))
    assert not [f for f in fields if f not in row], [f for f in fields if f not in row]


def test_every_cli_verb_is_named_in_the_cli_row():
    tree = ast.parse((ROOT / "massspring" / "cli" / "__init__.py").read_text())
    (commands,) = [n.value for n in tree.body if isinstance(n, ast.Assign)
                   and any(getattr(t, "id", None) == "COMMANDS" for t in n.targets)]
    verbs = [key.value for key in commands.keys]
    assert "fit" in verbs and len(verbs) >= 7
    row = set(spans(package_rows()["massspring/cli/"]))
    assert not [v for v in verbs if v not in row], [v for v in verbs if v not in row]


# ---------------------------------------------------------------- the layers

def test_the_layers_table_is_the_import_contract():
    """Each row: its layer number, its folders, and whether they may import each other
    (``:`` in the contract) or not (``|``; one folder: the cell is empty)."""
    (layers,) = [c for c in CONTRACTS if c["type"] == "layers"]
    contract = []
    for layer in layers["layers"]:
        separator = ":" if ":" in layer else "|"
        contract.append((sorted(m.strip() for m in layer.split(separator)), separator if separator in layer else ""))
    doc = []
    for number, folders, siblings in table(section("Layers")):
        kind = ":" if siblings.startswith("may import") else "|" if siblings.startswith("independent") else ""
        doc.append((sorted(spans(folders)), kind))
    assert doc == contract, f"the doc's layers, top down: {doc}; the contract's: {contract}"
    assert [row[0] for row in table(section("Layers"))] == [str(k) for k in range(1, len(contract) + 1)]


def test_every_layer_is_a_folder_with_a_row():
    (layers,) = [c for c in CONTRACTS if c["type"] == "layers"]
    rows = package_rows()
    for layer in layers["layers"]:
        for module in re.split(r"[|:]", layer):
            folder = "kernels/" if module.strip() == "kernels" else f"massspring/{module.strip()}/"
            assert folder in rows, f"layer {module.strip()!r} has no row {folder} in the packages table"


def test_the_contracts_exceptions_and_forbidden_imports_are_written():
    """Each ignored import is written as in the contract, with the function of its
    module that makes it; each forbidden contract has a bullet naming all its source
    modules and all its forbidden ones."""
    text = section("Layers")
    bullets = [" ".join(b.split()) for b in re.split(r"\n- ", text)]
    for contract in CONTRACTS:
        for ignored in contract.get("ignore_imports", []):
            assert f"`{ignored}`" in text, ignored
            importer, imported = (m.strip() for m in ignored.split("->"))
            path = ROOT / Path(*importer.split(".")).with_suffix(".py")
            makers = []  # the functions (``Class.function`` for a method) whose body imports ``imported``
            for node in ast.parse(path.read_text()).body:
                functions = [(f"{node.name}.", f) for f in node.body if isinstance(f, ast.FunctionDef)] \
                    if isinstance(node, ast.ClassDef) else [("", node)] if isinstance(node, ast.FunctionDef) else []
                for prefix, function in functions:
                    if any(isinstance(n, ast.ImportFrom) and n.module == imported for n in ast.walk(function)):
                        makers.append(prefix + function.name)
            assert makers, f"no function of {importer} imports {imported}: the exception is stale"
            bullet = next(b for b in bullets if f"`{ignored}`" in b)
            assert all(f"`{m}`" in bullet for m in makers), (makers, bullet)
        if contract["type"] == "forbidden":
            modules = contract["source_modules"] + contract["forbidden_modules"]
            assert any(all(f"`{m}`" in b or f"`{tail(m)}`" in b for m in modules) for b in bullets), \
                (contract["name"], modules)


# ---------------------------------------------------------------- where a change goes

def test_every_change_names_files_that_exist():
    for change, touches in table(section("Where a change goes")):
        files = named_files(touches)
        assert files, f"'{change}' names no file"
        missing = [f for f in files if not resolves(f)]
        assert not missing, f"'{change}' names files that do not exist: {missing}"


def test_every_kind_of_change_has_a_row():
    changes = [change for change, _ in table(section("Where a change goes"))]
    missing = [kind for kind in CHANGES if not any(c.startswith(kind) for c in changes)]
    assert not missing, f"'Where a change goes' has no row for {missing}"


# ---------------------------------------------------------------- names and files

def test_every_code_name_is_defined_somewhere():
    names = known_names()
    missing = []
    for span in sorted(set(spans(DOC))):
        if is_path(span) or span.startswith(("-", "[", ".", "massspring ")) or " " in span or "<" in span:
            continue  # options, TOML tables, suffixes, commands, patterns and prose
        for part in re.split(r"[.()=,\[\]]+", span):
            if re.fullmatch(r"[A-Za-z_][A-Za-z0-9_]*", part) and part not in names:
                missing.append(f"{span} ({part})")
    assert not missing, f"docs/architecture.md names what the code does not have: {missing}"


def test_no_file_outside_the_repository_is_cited():
    """Written in backquotes or not, every file name in the doc is one of the repository's
    (or one of ``COMING``, named as being written)."""
    cited = set(re.findall(r"[\w./<>-]*\w\.(?:py|md|toml|json)\b", DOC))
    missing = [name for name in cited if "<" not in name and name not in COMING and not exists_somewhere(name)]
    assert not missing, f"docs/architecture.md cites files that are not in the repository: {missing}"
    for name in COMING:
        assert name in DOC and f"`{name}`" not in DOC or exists_somewhere(name), name


def test_the_bundles_of_their_own_are_counted_and_named():
    """The modules that allocate a bundle besides the simulation's (``.allocate(`` outside
    device/ and engine/simulation.py) are as many as the doc says and each is named."""
    text = " ".join(section("The device bundle and compilation").split())
    match = re.search(r"(\w+) things have bundles of their own", text)
    assert match, "the bundles of their own are not counted"
    owners = sorted(str(p.relative_to(ROOT)) for p in (ROOT / "massspring").rglob("*.py")
                    if ".allocate(" in p.read_text() and p.parent.name != "device" and p.name != "simulation.py")
    assert NUMBERS[match.group(1).lower()] == len(owners), (match.group(1), owners)
    missing = [owner for owner in owners if f"`{owner}`" not in text]
    assert not missing, f"bundles of their own not named: {missing}"
