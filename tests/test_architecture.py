"""The package's shape (ARCHITECTURE.md), read from the code: its import graph has no cycle,
each package imports only the packages below it, and the root holds few modules.

Every import counts, at the top of a module or inside a function (a lazy import is still a
dependency, and a cycle through one is still a cycle).
"""

from __future__ import annotations

import ast
import re
import tokenize
from pathlib import Path

PACKAGE = Path(__file__).resolve().parents[1] / "omniscape_torch"

#: ARCHITECTURE.md: each package may import only those after it.
LAYERS = ("data", "scenes", "calibration", "augment", "render", "cubemap", "cameras", "io")


def _modules() -> dict[str, Path]:
    out = {}
    for path in PACKAGE.rglob("*.py"):
        parts = list(path.relative_to(PACKAGE.parent).with_suffix("").parts)
        if parts[-1] == "__init__":
            parts = parts[:-1]
        out[".".join(parts)] = path
    return out


def _imports(name: str, path: Path, modules: dict[str, Path]) -> set[str]:
    """The package modules ``name`` imports (a name imported from a package that is one of its
    submodules counts as that submodule)."""
    package = name if path.name == "__init__.py" else name.rsplit(".", 1)[0]
    found = set()
    for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
        if isinstance(node, ast.ImportFrom):
            if node.level:
                base = package.split(".")[: len(package.split(".")) - node.level + 1]
                target = ".".join(base + ([node.module] if node.module else []))
            else:
                target = node.module or ""
            for alias in node.names:
                sub = f"{target}.{alias.name}"
                if sub in modules:
                    found.add(sub)
                elif target in modules:
                    found.add(target)
        elif isinstance(node, ast.Import):
            found |= {alias.name for alias in node.names if alias.name in modules}
    found.discard(name)
    return found


def _graph() -> dict[str, set[str]]:
    modules = _modules()
    return {name: _imports(name, path, modules) for name, path in modules.items()}


def test_the_import_graph_has_no_cycle():
    graph = _graph()
    assert len(graph) > 40   # the parser found the package
    state: dict[str, int] = {}   # 1: on the current path, 2: done
    cycles = []

    def visit(node: str, path: list[str]) -> None:
        state[node] = 1
        for nxt in sorted(graph[node]):
            if state.get(nxt) == 1:
                cycles.append(path[path.index(nxt):] + [nxt] if nxt in path else [node, nxt])
            elif nxt not in state:
                visit(nxt, path + [nxt])
        state[node] = 2

    for node in sorted(graph):
        if node not in state:
            visit(node, [node])
    assert not cycles, "import cycles: " + "; ".join(" -> ".join(c) for c in cycles)


def test_each_package_imports_only_the_packages_below_it():
    graph = _graph()
    checked = 0
    for module, targets in graph.items():
        parts = module.split(".")
        if len(parts) < 3 and not (len(parts) == 2 and parts[1] in LAYERS):
            continue   # the root: __init__ and cli may import anything
        own = parts[1]
        below = set(LAYERS[LAYERS.index(own) + 1:])
        for target in targets:
            other = target.split(".")[1] if target.count(".") else ""
            checked += 1
            assert other == own or other in below, (
                f"{module} imports {target}: {own}/ may import only {sorted(below)}")
    assert checked > 100


def test_the_root_holds_at_most_six_modules_and_io_is_a_leaf():
    root = sorted(p.name for p in PACKAGE.glob("*.py"))
    assert len(root) <= 6, root
    graph = _graph()
    io = {t for m, ts in graph.items() if m.startswith("omniscape_torch.io") for t in ts}
    assert all(t.startswith("omniscape_torch.io") for t in io), io


def test_the_cpp_ops_are_called_from_the_kernel_boundary_only():
    """One kernel boundary (`render/kernels/`): no other module of the package reaches the C++
    library (its build, `torch.ops.omniscape_torch`, the ops handle) or asks whether it runs;
    they pass a `backend` to the boundary's functions, which choose."""
    boundary = PACKAGE / "render" / "kernels"
    reach = re.compile(r"torch\.ops\.omniscape_torch|\bbuild\.(ops|load)\(|\bextension\b"
                       r"|import build\b|\bavailable\(\)|\b_require\(\)|\bchoose\(")
    offenders = []
    for path in PACKAGE.rglob("*.py"):
        if boundary in path.parents:
            continue
        for number, code in _code_lines(path):
            if reach.search(code):
                offenders.append(f"{path.relative_to(PACKAGE)}:{number}: {code.strip()}")
    assert not offenders, "\n".join(offenders)
    assert (boundary / "_backend.py").is_file()


def _code_lines(path: Path) -> list[tuple[int, str]]:
    """The lines of a module with its strings (docstrings too) and comments blanked out."""
    lines = path.read_text(encoding="utf-8").splitlines()
    blank = [list(line) for line in lines]
    with path.open("rb") as source:
        for tok in tokenize.tokenize(source.readline):
            if tok.type in (tokenize.STRING, tokenize.COMMENT):
                (r0, c0), (r1, c1) = tok.start, tok.end
                for r in range(r0, r1 + 1):
                    row = blank[r - 1]
                    lo, hi = (c0 if r == r0 else 0), (c1 if r == r1 else len(row))
                    row[lo:hi] = " " * (hi - lo)
    return [(i, "".join(row)) for i, row in enumerate(blank, 1)]
