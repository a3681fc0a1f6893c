"""docs/scenes.md cannot drift from the parser: every key it accepts is listed there (with its
default where it has one), in the section of its table, generator or form; the complete example
there is the shipped examples/my_scene.toml."""

import dataclasses
import json
import re
from pathlib import Path

import pytest

from massspring import solvers
from massspring.model import mesh
from massspring.model.colliders import COLLIDERS
from massspring.integrators import INTEGRATORS, OPTIONS, takers
from massspring.scene import generators, spec

ROOT = Path(__file__).resolve().parent.parent
DOCS = (ROOT / "docs" / "scenes.md").read_text()


def section(prefix):
    """The text of the section whose heading starts with ``prefix`` (up to the next heading)."""
    parts = re.split(r"^(#{2,3} .*)$", DOCS, flags=re.M)
    for heading, body in zip(parts[1::2], parts[2::2]):
        if heading.lstrip("# ").startswith(prefix):
            return body
    raise AssertionError(f"docs/scenes.md has no section {prefix!r}")


def row(text, key):
    """The table row of ``key`` in ``text``."""
    rows = [line for line in text.splitlines() if line.startswith(f"| `{key}` |")]
    assert len(rows) == 1, f"docs/scenes.md: expected one table row for `{key}`, found {len(rows)}"
    return rows[0]


def shown(default):
    """A default as the TOML of a scene file writes it."""
    if isinstance(default, bool):
        return "true" if default else "false"
    return json.dumps(default) if isinstance(default, str) else repr(default)


def test_top_level_keys_are_listed():
    text = section("Top level")
    for key, kind in spec.TOP_KEYS.items():
        row(text, f"[{key}]" if kind is dict else f"[[{key}]]" if kind is list else key)
    for key in spec.common_keys():
        row(section("Keys of every"), key)
    for key in spec.PIN_KEYS:
        row(section("`[[pin]]`"), key)
    for cls in COLLIDERS.values():
        for key in ("type", *(f.name for f in dataclasses.fields(cls))):
            row(section("`[[collider]]`"), key)
    for key in INTEGRATORS:
        row(section("`[dt]`"), key)
    for key in spec.VIEW_KEYS:
        row(section("`[view]`"), key)
    for key in spec.CONTROL_KEYS:
        row(section("`[controls]`"), key)
    for key in spec.SOLVER_KEYS:
        row(section("`[solver]`"), key)
    assert f"{solvers.MULTIGRID_FROM:,} free particles" in row(section("`[solver]`"), "preconditioner")


def solver_row(option):
    """docs/scenes.md's row of a solver option, made from its record (integrators.OPTIONS)."""
    kind = ("string: " + ", ".join(f'`"{c}"`' for c in option.choices)) if option.choices else option.bounds
    shown_default = shown(option.default) if option.kind == "choice" else option.described_default()
    default = option.default_text or f"`{shown_default}`"
    doc = option.doc.replace("``", "`")
    return f"| `{option.name}` | {kind} | {default} | | {', '.join(takers(option.name))}: {doc} |"


@pytest.mark.parametrize("name", list(OPTIONS))
def test_solver_rows_follow_from_the_option_records(name):
    assert row(section("`[solver]`"), name) == solver_row(OPTIONS[name])
    assert f"`{OPTIONS[name].flag}`" in section("`[solver]`")


@pytest.mark.parametrize("name", sorted(generators.PARAMETERS))
def test_every_generator_parameter_is_listed_with_its_default(name):
    text = section(name)
    for key, default in generators.PARAMETERS[name].items():
        assert f"`{shown(default)}`" in row(text, key), (name, key, default)


def test_mesh_parameters_are_listed_with_their_defaults():
    text = section("A mesh")
    for key, default in mesh.PARAMETERS.items():
        line = row(text, key)
        if default is not None and key != "mesh":
            assert f"`{shown(default)}`" in line, (key, default)


def test_hand_made_keys_are_listed():
    text = section("By hand")
    for key in [*spec.PARTICLE_KEYS, *spec.SPRING_KEYS, *spec.HANDMADE_PARAMETERS]:
        row(text, key)
    for key in spec.REQUIRED_KEYS:
        assert "required" in row(text, key.split(".")[1])


def test_the_complete_example_is_the_shipped_file():
    block = re.search(r"```toml\n(.*?)```", section("A complete example"), flags=re.S).group(1)
    assert block == (ROOT / "examples" / "my_scene.toml").read_text()


def test_the_lists_of_collider_types_and_export_formats_are_the_registries():
    """Where the docs list every collider type or every export format, the list is
    exactly the registry's (``colliders.COLLIDERS``, ``io.frames.FORMATS``): a new kind
    or format cannot be left out of them."""
    from massspring.io.frames import FORMATS

    contact = (ROOT / "docs" / "contact.md").read_text()
    command_line = (ROOT / "docs" / "command-line.md").read_text()
    export = (ROOT / "docs" / "export.md").read_text()
    types = list(COLLIDERS)
    quoted = [f'"{t}"' for t in types]
    assert f"`type = {' | '.join(quoted)}`" in " ".join(contact.split())
    assert f"`type` one of {', '.join(f'`{q}`' for q in quoted)}," in section("`[[collider]]`")
    assert f"| {', '.join(f'`{q}`' for q in quoted[:-1])} or `{quoted[-1]}` |" in row(section("`[[collider]]`"), "type")
    formats = f"--format {'|'.join(FORMATS)}"
    assert formats in command_line and formats in DOCS
    prose = " ".join(export[export.index("`--format`: "):].split())
    for name in FORMATS:
        assert f"`{name}`" in prose[:prose.index("`pip install")], name
