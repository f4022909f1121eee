"""The structure of phisim.io: no import cycles, no imports inside functions, no private names across modules."""

from __future__ import annotations

import ast
from pathlib import Path

import phisim.io

IO = Path(phisim.io.__file__).parent


def _modules() -> dict[str, ast.Module]:
    return {p.stem: ast.parse(p.read_text(encoding="utf-8")) for p in sorted(IO.glob("*.py"))}


def _io_imports(tree: ast.Module) -> list[tuple[str, list[str], bool]]:
    """(imported phisim.io module, imported names, at module level) for every import of phisim.io."""
    top = {id(n) for n in tree.body}
    out = []
    for node in ast.walk(tree):
        if isinstance(node, ast.ImportFrom) and node.module and node.module.startswith("phisim.io"):
            mod = node.module.removeprefix("phisim.io").lstrip(".")
            names = [a.name for a in node.names]
            if not mod:  # from phisim.io import journal
                for name in names:
                    out.append((name if (IO / f"{name}.py").exists() else "__init__", [name], id(node) in top))
            else:
                out.append((mod, names, id(node) in top))
    return out


def test_no_import_cycles_between_io_modules():
    graph = {name: {m for m, _, _ in _io_imports(tree) if m != "__init__"} for name, tree in _modules().items()}
    graph.pop("__init__")
    order: list[str] = []
    while graph:
        ready = sorted(m for m, deps in graph.items() if deps <= set(order))
        assert ready, f"import cycle among {sorted(graph)}: {graph}"
        order += ready
        for m in ready:
            graph.pop(m)
    assert order.index("journal") < order.index("traininglog") < order.index("reader") < order.index("writer") \
        < order.index("recovery")


def test_no_function_level_imports_and_no_private_names():
    for name, tree in _modules().items():
        top = {id(n) for n in tree.body}
        for node in ast.walk(tree):
            if isinstance(node, (ast.Import, ast.ImportFrom)):
                assert id(node) in top, f"phisim/io/{name}.py:{node.lineno}: an import inside a function"
        for mod, names, _ in _io_imports(tree):
            private = [n for n in names if n.startswith("_")]
            assert not private, f"phisim/io/{name}.py imports private names {private} of phisim.io.{mod}"


def test_public_names_and_old_paths():
    import importlib
    import warnings

    for name in ("SimulationWriter", "SimulationData", "read_simulation", "recover_file", "TrainingLog",
                 "read_training", "well_bc_type", "FIELD_KINDS", "compute_statistics", "write_statistics",
                 "format_statistics", "STATISTICS_KEYS"):
        assert name in phisim.io.__all__ and hasattr(phisim.io, name), name
    from phisim.io import simulation

    assert simulation.SimulationWriter is phisim.io.SimulationWriter
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", DeprecationWarning)
        assert importlib.import_module("phisim.traininglog").TrainingLog is phisim.io.TrainingLog
        assert importlib.import_module("phisim.wellstats").write_statistics is phisim.io.write_statistics
