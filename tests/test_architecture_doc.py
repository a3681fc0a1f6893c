"""docs/architecture.md cannot name what does not exist: every file or folder it names is
in the repository, and every code name it writes in backquotes (a module, class,
function, attribute, constant or status string) is defined or written somewhere in the
package, the kernels or the benchmarks."""

import ast
import re
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
DOC = (ROOT / "docs" / "architecture.md").read_text()
SOURCES = [p for d in ("massspring", "kernels", "benchmarks") for p in (ROOT / d).rglob("*.py")]
PLACES = [ROOT, ROOT / "massspring", ROOT / "kernels", *(p for p in (ROOT / "massspring").iterdir() if p.is_dir())]


def code_spans():
    return sorted(set(re.findall(r"`([^`\n]+)`", DOC)))


def known_names():
    """Every name the sources define or mention: modules, classes, functions, arguments,
    assigned names and attributes, attribute accesses, and string constants."""
    names = set()
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
    return "/" in span and " " not in span and not span.startswith(("-", "[")) or span.endswith((".py", ".md"))


def test_every_file_and_folder_named_exists():
    missing = []
    for span in filter(is_path, code_spans()):
        path = span.rstrip("/")
        if path.startswith(("massspring.", "kernels.")) or "=" in path or "(" in path:
            continue  # a dotted module or an expression, checked below
        if not any((place / path).exists() for place in PLACES) and not (ROOT / "massspring" / "io" / path).exists():
            missing.append(span)
    assert not missing, f"docs/architecture.md names files that do not exist: {missing}"


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
