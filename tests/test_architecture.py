"""The project's import structure: no cycle between its modules, and the lower layers (io, geometry,
errors, factors, and the solver's observations) never reach up into the solver, the evaluation, the
CLI or the report.

Every module of ``calib3r_graph`` and ``factors`` is parsed with ``ast`` (nothing is imported),
and every import statement counts, at module level or inside a function.
"""

import ast
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
PACKAGES = ("calib3r_graph", "factors")

# The lower layers and what they must never import.
LOWER = ("factors", "calib3r_graph.io", "calib3r_graph.geometry", "calib3r_graph.errors",
         "calib3r_graph.solver.observations")
UPPER = ("calib3r_graph.solver", "calib3r_graph.evaluation", "calib3r_graph.cli", "calib3r_graph.report",
         "calib3r_graph.dense")


def _module_name(path: Path) -> str:
    parts = list(path.relative_to(REPO).with_suffix("").parts)
    if parts[-1] == "__init__":
        parts = parts[:-1]
    return ".".join(parts)


def _modules() -> dict:
    out = {}
    for pkg in PACKAGES:
        for path in sorted((REPO / pkg).rglob("*.py")):
            out[_module_name(path)] = path
    return out


def _resolve(name: str, modules: dict) -> str | None:
    """The project module an imported name lives in (the longest known prefix), or None."""
    parts = name.split(".")
    for n in range(len(parts), 0, -1):
        cand = ".".join(parts[:n])
        if cand in modules:
            return cand
    return None


def import_graph() -> dict:
    """{module: {project modules it imports anywhere in its body}}."""
    modules = _modules()
    graph = {}
    for mod, path in modules.items():
        is_pkg = path.name == "__init__.py"
        package = mod if is_pkg else mod.rpartition(".")[0]
        deps = set()
        for node in ast.walk(ast.parse(path.read_text(), filename=str(path))):
            names = []
            if isinstance(node, ast.Import):
                names = [a.name for a in node.names]
            elif isinstance(node, ast.ImportFrom):
                base = node.module or ""
                if node.level:
                    anchor = package.split(".")
                    anchor = anchor[:len(anchor) - (node.level - 1)]
                    base = ".".join(anchor + ([base] if base else []))
                # "from pkg import sub" imports the submodule pkg.sub when it is one
                names = [f"{base}.{a.name}" for a in node.names] + [base]
            for n in names:
                target = _resolve(n, modules)
                if target is not None and target != mod:
                    deps.add(target)
        graph[mod] = deps
    return graph


def _find_cycle(graph: dict) -> list | None:
    WHITE, GREY, BLACK = 0, 1, 2
    colour = {m: WHITE for m in graph}
    stack = []

    def visit(m):
        colour[m] = GREY
        stack.append(m)
        for d in sorted(graph.get(m, ())):
            if colour.get(d, BLACK) == GREY:
                return stack[stack.index(d):] + [d]
            if colour.get(d) == WHITE:
                found = visit(d)
                if found:
                    return found
        stack.pop()
        colour[m] = BLACK
        return None

    for m in sorted(graph):
        if colour[m] == WHITE:
            found = visit(m)
            if found:
                return found
    return None


def _in(mod: str, prefixes) -> bool:
    return any(mod == p or mod.startswith(p + ".") for p in prefixes)


def test_import_graph_is_parsed():
    g = import_graph()
    # a few edges that exist for sure, at module level and inside functions
    assert "calib3r_graph.solver.graph" in g["calib3r_graph.solver.solve"]
    assert "calib3r_graph.solver.solve" in g["calib3r_graph.cli"]  # function-level import
    assert "factors.match3d" in g["factors"]
    assert len(g) >= 25


def test_no_import_cycle():
    cycle = _find_cycle(import_graph())
    assert cycle is None, "import cycle: " + " -> ".join(cycle)


def test_lower_layers_never_import_upper_layers():
    g = import_graph()
    bad = sorted(f"{m} imports {d}" for m, deps in g.items() if _in(m, LOWER) for d in deps if _in(d, UPPER))
    assert not bad, "; ".join(bad)


def test_cycle_finder_finds_cycles():
    assert _find_cycle({"a": {"b"}, "b": {"c"}, "c": {"a"}}) == ["a", "b", "c", "a"]
    assert _find_cycle({"a": {"b"}, "b": {"c"}, "c": set()}) is None


def test_solver_never_imports_evaluation_report_or_cli():
    """The evaluation (compare, pattern methods) runs the solver, never the other way round."""
    g = import_graph()
    above = ("calib3r_graph.evaluation", "calib3r_graph.report", "calib3r_graph.cli")
    bad = sorted(f"{m} imports {d}" for m, deps in g.items() if _in(m, ("calib3r_graph.solver",))
                 for d in deps if _in(d, above))
    assert not bad, "; ".join(bad)


def test_dense_reads_results_and_never_the_solver_evaluation_report_or_cli():
    """The dense step works from a solve's files (and io), so it never needs the solver or what sits above."""
    g = import_graph()
    above = ("calib3r_graph.solver", "calib3r_graph.evaluation", "calib3r_graph.report", "calib3r_graph.cli")
    bad = sorted(f"{m} imports {d}" for m, deps in g.items() if _in(m, ("calib3r_graph.dense",))
                 for d in deps if _in(d, above))
    assert any(_in(m, ("calib3r_graph.dense",)) for m in g) and not bad, "; ".join(bad)
