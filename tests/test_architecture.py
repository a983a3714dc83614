"""The house rules of ARCHITECTURE.md, read from the code (issue 18).

An AST walk over ``mocapskel/`` finds every import of the package's own modules, at module level and inside
functions alike, and checks that data flows one way: stages call solvers and the model, never each other,
the command line or file I/O; solvers need nothing but numpy/scipy, other solvers and the model (its
data types in ``artifacts.py`` included) and the error types; no import circle anywhere; no module over
700 lines; the solvers' folders by concern import one another one way, each says what it holds and
imports nothing itself, and only the model uses the priors' geometry.
"""
from __future__ import annotations

import ast
from pathlib import Path

import networkx as nx
import pytest

PACKAGE = Path(__file__).resolve().parents[1] / "mocapskel"
MAX_LINES = 700

#: What each part may import of the package (a part is a module or a package prefix; the longest prefix
#: that names a module decides its part). Anything not listed here is the orchestration around the stages
#: (pipeline, cache, batch, reports, checks, the command line), which may import any part but the CLI.
ALLOWED: dict[str, tuple[str, ...]] = {
    "mocapskel.errors": (),
    "mocapskel.model": ("mocapskel.model", "mocapskel.artifacts", "mocapskel.errors"),
    "mocapskel.artifacts": ("mocapskel.errors",),
    "mocapskel.solvers": ("mocapskel.solvers", "mocapskel.model", "mocapskel.artifacts", "mocapskel.errors"),
    "mocapskel.stages": ("mocapskel.artifacts", "mocapskel.errors", "mocapskel.model", "mocapskel.solvers"),
    "mocapskel.io": ("mocapskel.io", "mocapskel.artifacts", "mocapskel.errors", "mocapskel.model", "mocapskel.solvers"),
    "mocapskel.synth": ("mocapskel.synth", "mocapskel.artifacts", "mocapskel.errors", "mocapskel.model",
                        "mocapskel.solvers"),
}
#: Only the command line and the entry points import the command line.
CLI = "mocapskel.cli"
ENTRY = ("mocapskel.cli", "mocapskel._entry", "mocapskel.__main__")


def _name(path: Path) -> str:
    parts = path.relative_to(PACKAGE.parent).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def _is_module(name: str) -> bool:
    p = PACKAGE.parent.joinpath(*name.split("."))
    return p.with_suffix(".py").is_file() or (p / "__init__.py").is_file()


def _imports(path: Path) -> set[str]:
    """The package's modules that the file imports, anywhere in it."""
    name = _name(path)
    here = name if path.name == "__init__.py" else name.rpartition(".")[0]
    out: set[str] = set()
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.Import):
            out.update(a.name for a in node.names if a.name.split(".")[0] == "mocapskel")
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = here.split(".")[: len(here.split(".")) - node.level + 1]
                target = ".".join(base + ([node.module] if node.module else []))
            else:
                target = node.module or ""
            if target.split(".")[0] != "mocapskel":
                continue
            subs = [f"{target}.{a.name}" for a in node.names if _is_module(f"{target}.{a.name}")]
            out.update(subs or [target])
            if len(subs) < len(node.names) and subs:
                out.add(target)
    return {m for m in out if m != name}


GRAPH = {_name(p): _imports(p) for p in sorted(PACKAGE.rglob("*.py"))}


def _part(module: str) -> str | None:
    for prefix in sorted(ALLOWED, key=len, reverse=True):
        if module == prefix or module.startswith(prefix + "."):
            return prefix
    return None


def _within(module: str, prefixes: tuple[str, ...]) -> bool:
    return any(module == p or module.startswith(p + ".") for p in prefixes)


def test_the_walk_sees_the_package() -> None:
    assert len(GRAPH) > 50
    assert "mocapskel.pipeline" in GRAPH and GRAPH["mocapskel.pipeline"]
    assert any(m.startswith("mocapskel.stages.") for m in GRAPH["mocapskel.pipeline"])


def test_every_import_of_the_package_names_one_of_its_modules() -> None:
    missing = [f"{m} -> {d}" for m, deps in GRAPH.items() for d in sorted(deps) if not _is_module(d)]
    assert not missing, missing


def test_each_part_imports_only_what_it_may() -> None:
    broken = []
    for mod, deps in GRAPH.items():
        part = _part(mod)
        for dep in sorted(deps):
            if dep == "mocapskel":  # the package itself: its version and its start-up settings
                if part in ("mocapskel.solvers", "mocapskel.stages", "mocapskel.model"):
                    broken.append(f"{mod} -> {dep}")
                continue
            if _within(dep, (CLI,)) and not _within(mod, ENTRY):
                broken.append(f"{mod} -> {dep} (only the command line imports the command line)")
            elif part is not None and not _within(dep, ALLOWED[part]):
                broken.append(f"{mod} -> {dep}")
    assert not broken, "imports against ARCHITECTURE.md:\n" + "\n".join(broken)


def test_a_stage_never_imports_another_stage() -> None:
    stages = {m for m in GRAPH if m.startswith("mocapskel.stages.")}
    assert len(stages) >= 8
    broken = [f"{m} -> {d}" for m in sorted(stages) for d in sorted(GRAPH[m]) if d in stages or d == "mocapskel.stages"]
    assert not broken, broken


def test_no_import_circle() -> None:
    g = nx.DiGraph()
    for mod, deps in GRAPH.items():
        for d in deps:
            # a package's __init__ is imported on the way to any of its modules; it imports nothing of them here
            g.add_edge(mod, d)
    cycles = [sorted(c) for c in nx.strongly_connected_components(g) if len(c) > 1]
    assert not cycles, f"import circles: {cycles}"


@pytest.mark.parametrize("path", sorted(PACKAGE.rglob("*.py")), ids=lambda p: str(p.relative_to(PACKAGE)))
def test_no_module_over_700_lines(path: Path) -> None:
    n = len(path.read_text().splitlines())
    assert n <= MAX_LINES, f"{path.relative_to(PACKAGE.parent)} has {n} lines"


#: The solvers' folders by concern (each a sub-package of ``mocapskel.solvers``); modules at the
#: solvers' top level are the ones several folders and the rest of the package share.
SOLVERS = "mocapskel.solvers"


def _solver_node(module: str) -> str | None:
    """A solvers module's folder (``mocapskel.solvers.ik``), or the module itself when it is at the
    solvers' top level; None outside the solvers."""
    if not module.startswith(SOLVERS + "."):
        return None
    parts = module.split(".")
    folder = ".".join(parts[:3])
    return folder if (PACKAGE.parent.joinpath(*parts[:3]) / "__init__.py").is_file() else module


def test_the_solvers_are_in_folders_that_say_what_they_hold() -> None:
    folders = sorted(p for p in (PACKAGE / "solvers").iterdir() if p.is_dir() and (p / "__init__.py").is_file())
    assert {"model", "joints", "ik", "priors"} <= {p.name for p in folders}
    for p in folders:
        init = p / "__init__.py"
        tree = ast.parse(init.read_text())
        doc = ast.get_docstring(tree)
        assert doc and f"{SOLVERS}.{p.name}." in doc, f"{init}: no docstring naming its modules"
        # importing a folder costs nothing and makes no circle: its __init__ imports nothing
        assert GRAPH[f"{SOLVERS}.{p.name}"] == set(), f"{init} imports {GRAPH[f'{SOLVERS}.{p.name}']}"


def test_the_solver_folders_import_one_another_one_way() -> None:
    g = nx.DiGraph()
    for mod, deps in GRAPH.items():
        a = _solver_node(mod)
        for d in deps:
            b = _solver_node(d)
            if a is not None and b is not None and a != b:
                g.add_edge(a, b)
    assert f"{SOLVERS}.model" in g and f"{SOLVERS}.ik" in g
    cycles = [sorted(c) for c in nx.strongly_connected_components(g) if len(c) > 1]
    assert not cycles, f"solver folders that import each other: {cycles}"


def test_only_the_model_uses_the_priors_geometry() -> None:
    """Where the priors put a joint the data leave free is the model's: nothing else may move joints by it."""
    priors = f"{SOLVERS}.priors"
    users = {m for m, deps in GRAPH.items() if any(_within(d, (priors,)) for d in deps) and not _within(m, (priors,))}
    assert users, "nothing imports the priors' geometry: remove the folder"
    assert all(_within(m, (f"{SOLVERS}.model",)) for m in users), sorted(users)
