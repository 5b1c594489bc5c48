"""The package's layering, checked statically (every import, at module level or inside a function).

- no module below ``endogsim.cli`` imports the CLI (``endogsim.__main__``, ``python -m endogsim``, runs it);
- no import circle between modules;
- no module imports another module's private (underscore) name.
"""

from __future__ import annotations

import ast
import functools
from pathlib import Path

import endogsim

ROOT = Path(endogsim.__file__).parent


def _module_name(path: Path) -> str:
    rel = path.relative_to(ROOT.parent).with_suffix("")
    parts = list(rel.parts)
    if parts[-1] == "__init__":
        parts = parts[:-1]
    return ".".join(parts)


@functools.lru_cache(maxsize=1)
def _imports() -> dict[str, list[tuple[str, list[str]]]]:
    """module -> [(imported module, imported names)] for every ``endogsim`` import in its source."""
    modules = {_module_name(p): p for p in ROOT.rglob("*.py")}
    out: dict[str, list[tuple[str, list[str]]]] = {}
    for name, path in modules.items():
        found = []
        tree = ast.parse(path.read_text())
        # imports under `if TYPE_CHECKING:` never run: they are annotations, not dependencies
        typing_only = {id(n) for node in ast.walk(tree) if isinstance(node, ast.If)
                       and getattr(node.test, "id", None) == "TYPE_CHECKING" for b in node.body for n in ast.walk(b)}
        for node in ast.walk(tree):
            if id(node) in typing_only:
                continue
            if isinstance(node, ast.ImportFrom) and node.module and node.module.startswith("endogsim"):
                names = [a.name for a in node.names]
                # "from endogsim.x import y" where y is a submodule imports that submodule
                subs = [f"{node.module}.{n}" for n in names if f"{node.module}.{n}" in modules]
                found += [(node.module, [n for n in names if f"{node.module}.{n}" not in modules])]
                found += [(s, []) for s in subs]
            elif isinstance(node, ast.Import):
                found += [(a.name, []) for a in node.names if a.name.startswith("endogsim")]
        out[name] = found
    return out


def test_no_module_below_the_cli_imports_it():
    above = ("endogsim.cli", "endogsim.__main__")  # ``python -m endogsim`` runs the CLI: it sits above it
    offenders = [(m, t) for m, imps in _imports().items() if not m.startswith(above)
                 for t, _ in imps if t == "endogsim.cli" or t.startswith("endogsim.cli.")]
    assert offenders == []


def test_no_private_names_imported_across_modules():
    offenders = [(m, t, n) for m, imps in _imports().items() for t, names in imps for n in names
                 if n.startswith("_") and not n.startswith("__") and t != m]
    assert offenders == []


def test_no_import_circles():
    imports = _imports()
    graph = {m: {t for t, _ in imps if t != m and t in imports} for m, imps in imports.items()}
    # a package's __init__ re-exporting its modules is not a circle through them: drop package -> child edges
    for m in graph:
        graph[m] = {t for t in graph[m] if not t.startswith(m + ".")}
    cycles, state = [], {}

    def visit(node: str, stack: list[str]) -> None:
        state[node] = 1
        for nxt in sorted(graph[node]):
            if state.get(nxt) == 1:
                cycles.append(stack[stack.index(nxt):] + [nxt])
            elif nxt not in state:
                visit(nxt, stack + [nxt])
        state[node] = 2

    for m in sorted(graph):
        if m not in state:
            visit(m, [m])
    assert cycles == []
