"""Check the shape of `arena/`: layers, import circles, private names and file sizes.

    python tools/architecture.py        # prints what breaks a rule; exit 1 if anything does

The rules (specs/architecture.md says why):

- Dependencies point one way: a folder imports only folders of a lower rank (RANKS) and itself.
- No import circle among arena's modules, counting every import: at the top, under
  `TYPE_CHECKING` and inside functions.
- No module imports another module's private (`_`-prefixed) name.
- No file under `arena/` is longer than MAX_LINES.

tests/test_architecture.py runs the same checks.
"""

from __future__ import annotations

import ast
import sys
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
MAX_LINES = 600

#: The layers, lowest first (shared/DESIGN.md): a module may import its own folder and folders of
#: a lower rank. Top-level modules count as folders of their own (`arena.client` is `client`).
RANKS: dict[str, int] = {
    "protocol": 0,
    "arena": 1,  # arena/__init__.py: the version
    "child": 1,  # the helper processes' pipes (a policy's worker, a camera's capture)
    "extras": 1,
    "robot": 1,
    "client": 1,
    "servo": 2,  # the servo bus interface, the bus worker, calibration: no family's own
    "sensors": 2,
    "recording": 2,
    "estop_test": 2,
    "feetech": 3,  # the servo families, behind `servo`'s interface
    "dynamixel": 3,
    "drivers": 4,
    "schemas": 4,
    "fleet": 5,
    "policy": 5,
    "script": 5,  # a script's worker and master, as a policy's
    "gym": 6,  # on policy: `arena learn` runs its policy as the master
    "mcp": 6,  # on script: `arena mcp`'s moves end as a script's (a client of the API)
    "ros2": 6,  # on the fleet's Zenoh pieces
    "server": 7,
    "bench": 8,
    "cli": 9,
    "__main__": 10,
}


@dataclass
class Shape:
    """The modules of `arena/` and the imports between them."""

    files: dict[str, Path] = field(default_factory=dict)
    imports: dict[str, set[str]] = field(default_factory=dict)
    private: list[tuple[str, str]] = field(default_factory=list)  # (importer, module.name)


def read(root: Path = ROOT) -> Shape:
    """Parse every module under `root/arena` and collect its imports of arena's modules."""
    shape = Shape()
    for path in sorted((root / "arena").rglob("*.py")):
        if "node_modules" in path.parts:
            continue
        parts = list(path.relative_to(root).with_suffix("").parts)
        if parts[-1] == "__init__":
            parts.pop()
        shape.files[".".join(parts)] = path
    for name, path in shape.files.items():
        package = name if path.name == "__init__.py" else name.rpartition(".")[0]
        found: set[str] = set()
        for target, imported in _imports(ast.parse(path.read_text(encoding="utf-8")), package):
            module = _module_of(shape, target, imported)
            if not module:
                continue
            if module != name:
                found.add(module)
                named = f"{target}.{imported}"
                if imported and imported.startswith("_") and named not in shape.files:
                    shape.private.append((name, named))
        shape.imports[name] = found
    return shape


def _imports(tree: ast.AST, package: str) -> Iterator[tuple[str, str | None]]:
    """(module, imported name or None) of every import of arena's code, wherever it is."""
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            for alias in node.names:
                if alias.name.split(".")[0] == "arena":
                    yield alias.name, None
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = package.split(".")[: len(package.split(".")) - node.level + 1]
                target = ".".join(base + ([node.module] if node.module else []))
            else:
                target = node.module or ""
            if target.split(".")[0] == "arena":
                for alias in node.names:
                    yield target, alias.name


def _module_of(shape: Shape, target: str, imported: str | None) -> str:
    """The arena module an import reaches ('' if none): `from a import b` may name module a.b."""
    if imported and f"{target}.{imported}" in shape.files:
        return f"{target}.{imported}"
    while target and target not in shape.files:
        target = target.rpartition(".")[0]
    return target


def folder(module: str) -> str:
    """`arena.robot.core` -> `robot`; `arena.cli` -> `cli`; `arena` -> `arena`."""
    parts = module.split(".")
    return parts[1] if len(parts) > 1 else parts[0]


def layer_breaks(shape: Shape) -> list[str]:
    """Imports that go up or sideways between folders."""
    out = []
    for name, targets in sorted(shape.imports.items()):
        for target in sorted(targets):
            here, there = folder(name), folder(target)
            if here == there:
                continue
            if here not in RANKS or there not in RANKS:
                out.append(f"{name} -> {target}: a folder without a rank in tools/architecture.py")
            elif RANKS[there] >= RANKS[here]:
                out.append(f"{name} -> {target}: {here} may not import {there}")
    return out


def circles(shape: Shape) -> list[list[str]]:
    """The import circles: strongly connected groups of more than one module (Tarjan)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    found: list[list[str]] = []

    def visit(node: str) -> None:
        index[node] = low[node] = len(index)
        stack.append(node)
        on_stack.add(node)
        for nxt in shape.imports.get(node, ()):
            if nxt not in index:
                visit(nxt)
                low[node] = min(low[node], low[nxt])
            elif nxt in on_stack:
                low[node] = min(low[node], index[nxt])
        if low[node] == index[node]:
            group = []
            while True:
                top = stack.pop()
                on_stack.discard(top)
                group.append(top)
                if top == node:
                    break
            if len(group) > 1:
                found.append(sorted(group))

    for module in sorted(shape.imports):
        if module not in index:
            visit(module)
    return sorted(found)


def long_files(shape: Shape) -> list[tuple[str, int]]:
    """Modules over MAX_LINES lines, with their length."""
    lengths = {n: len(p.read_text(encoding="utf-8").splitlines()) for n, p in shape.files.items()}
    return sorted((n, k) for n, k in lengths.items() if k > MAX_LINES)


def main() -> int:
    """Print every broken rule; exit 1 if there is any."""
    shape = read()
    problems = layer_breaks(shape)
    problems += [f"import circle: {' <-> '.join(c)}" for c in circles(shape)]
    problems += [f"{who} imports the private {what}" for who, what in shape.private]
    problems += [f"{name}: {n} lines (at most {MAX_LINES})" for name, n in long_files(shape)]
    for line in problems:
        print(line)
    print(f"{len(shape.files)} modules, {len(problems)} problem(s)")
    return 1 if problems else 0


if __name__ == "__main__":
    sys.exit(main())
