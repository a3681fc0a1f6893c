"""Where the benchmarks write by default: ``benchmarks/out/`` (ignored by git), so that
running one never replaces the results committed in ``benchmarks/results/`` or the
figures in ``docs/``. To update those on purpose, name them: ``--json
benchmarks/results/NAME.json`` (``--png docs/performance.png``, ``--docs docs``)."""

from __future__ import annotations

from pathlib import Path

OUT = Path(__file__).resolve().parent / "out"
RESULTS = Path(__file__).resolve().parent / "results"


def add_json(parser, name):
    """The ``--json`` option of a benchmark that writes ``name``.json."""
    parser.add_argument("--json", default=str(OUT / f"{name}.json"),
                        help=f"where the JSON goes (default benchmarks/out/{name}.json; the committed "
                        f"result is benchmarks/results/{name}.json)")
