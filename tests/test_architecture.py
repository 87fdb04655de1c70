"""The package's import graph: one way, no cycles, no private names across modules, light top-level import.

Parses every module of ``torch_interreflect`` with :mod:`ast` (imports inside functions included: a lazy import
is still a dependency) and checks the rules of the layout (README "What is in the box").
"""

from __future__ import annotations

import ast
import subprocess
import sys
from pathlib import Path

import pytest

PKG = Path(__file__).resolve().parents[1] / "torch_interreflect"
NAME = "torch_interreflect"


def _modules() -> dict[str, Path]:
    out = {}
    for path in PKG.rglob("*.py"):
        rel = path.relative_to(PKG.parent).with_suffix("")
        parts = list(rel.parts)
        if parts[-1] == "__init__":
            parts = parts[:-1]
        out[".".join(parts)] = path
    return out


MODULES = _modules()


def _resolve(module: str, is_pkg: bool, level: int, target: str | None) -> str:
    base = module.split(".") if is_pkg else module.split(".")[:-1]
    if level > 1:
        base = base[: len(base) - (level - 1)]
    return ".".join([*base, *([target] if target else [])])


def _imports(module: str) -> list[tuple[str, str | None, int]]:
    """``(imported module, imported name or None, line)`` for every import of ``module`` inside the package."""
    path = MODULES[module]
    is_pkg = path.name == "__init__.py"
    out = []
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.ImportFrom):
            mod = _resolve(module, is_pkg, node.level, node.module) if node.level else (node.module or "")
            if not mod.startswith(NAME):
                continue
            for alias in node.names:
                sub = f"{mod}.{alias.name}"
                if sub in MODULES:  # "from . import x" imports the module x
                    out.append((sub, None, node.lineno))
                else:
                    out.append((mod, alias.name, node.lineno))
        elif isinstance(node, ast.Import):
            out.extend((a.name, None, node.lineno) for a in node.names if a.name.startswith(NAME))
    return out


def _find_cycle(graph: dict[str, set[str]]) -> list[str] | None:
    state: dict[str, int] = {}
    stack: list[str] = []

    def visit(n: str) -> list[str] | None:
        state[n] = 1
        stack.append(n)
        for nxt in sorted(graph[n]):
            if state.get(nxt) == 1:
                return [*stack[stack.index(nxt) :], nxt]
            if nxt not in state:
                found = visit(nxt)
                if found:
                    return found
        stack.pop()
        state[n] = 2
        return None

    for n in sorted(graph):
        if n not in state:
            found = visit(n)
            if found:
                return found
    return None


def _module_edges() -> dict[str, set[str]]:
    """Module → module edges, where importing a name from a package counts as importing the module defining it."""
    graph: dict[str, set[str]] = {m: set() for m in MODULES}
    for m in MODULES:
        for target, name, _ in _imports(m):
            if target not in MODULES or target == m:
                continue
            if MODULES[target].name == "__init__.py" and name is not None:
                # follow the re-export to the defining submodule
                for sub_target, sub_name, _ in _imports(target):
                    if sub_name == name or (sub_name is None and sub_target.endswith("." + name)):
                        target = sub_target
                        break
            if target != m and not (MODULES[target].name == "__init__.py" and m.startswith(target + ".")):
                graph[m].add(target)
    return graph


def test_cycle_finder_finds_cycles() -> None:
    """The checker itself: a planted cycle is found, an acyclic graph passes."""
    assert _find_cycle({"a": {"b"}, "b": {"c"}, "c": {"a"}}) == ["a", "b", "c", "a"]
    assert _find_cycle({"a": {"b", "c"}, "b": {"c"}, "c": set()}) is None


def test_no_import_cycle() -> None:
    cycle = _find_cycle(_module_edges())
    assert cycle is None, "import cycle: " + " → ".join(cycle or [])


def test_no_private_name_across_modules() -> None:
    bad = []
    for m in MODULES:
        for target, name, line in _imports(m):
            if name and name.startswith("_") and not name.startswith("__") and target != m:
                bad.append(f"{MODULES[m].relative_to(PKG.parent)}:{line} imports {name} from {target}")
    assert not bad, "private names imported across modules:\n" + "\n".join(bad)


#: Stages in data-flow order; a module may import from its own stage or an earlier one, never a later one.
STAGES = [
    ("errors", "_checks", "_unique", "_sparse", "_version", "_deprecation"),
    ("geometry",),
    ("formfactors",),
    ("lights", "light_moments", "sky_openings", "sky_parts", "spectral"),
    ("solver",),
    ("camera",),
    ("accuracy",),
    ("layers",),
    ("inverse",),
    ("training",),
    ("cli",),
]


def _stage(module: str) -> int | None:
    parts = module.split(".")
    if len(parts) < 2:
        return None
    for i, names in enumerate(STAGES):
        if parts[1] in names:
            return i
    return None


def test_imports_run_one_way() -> None:
    bad = []
    for m in MODULES:
        sm = _stage(m)
        for target, _, line in _imports(m):
            st = _stage(target)
            if sm is not None and st is not None and st > sm:
                bad.append(f"{MODULES[m].relative_to(PKG.parent)}:{line} ({STAGES[sm][0]}) imports {target}")
    assert not bad, "imports against the data flow:\n" + "\n".join(bad)


def test_layers_hold_modules_only() -> None:
    """``layers/`` defines ``nn.Module`` classes (and private helpers of them), no public functions."""
    bad = []
    for m, path in MODULES.items():
        if not m.startswith(f"{NAME}.layers.") or path.name == "__init__.py":
            continue
        for node in ast.parse(path.read_text()).body:
            if isinstance(node, ast.FunctionDef) and not node.name.startswith("_"):
                bad.append(f"{path.relative_to(PKG.parent)}: def {node.name}")
    assert not bad, "public functions in layers/ (move them to the stage they belong to):\n" + "\n".join(bad)


@pytest.mark.parametrize("heavy", ["torch_interreflect.training", "torch_interreflect.cli", "matplotlib", "trimesh"])
def test_top_level_import_is_light(heavy: str) -> None:
    code = f"import sys, torch_interreflect; print({heavy!r} in sys.modules)"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout.strip()
    assert out == "False", f"import torch_interreflect imports {heavy} eagerly"


def test_module_size() -> None:
    big = {}
    for path in MODULES.values():
        n = len(path.read_text().splitlines())
        if n > 500:
            big[str(path.relative_to(PKG.parent))] = n
    assert not big, f"modules over 500 lines: {big}"


def test_function_size() -> None:
    long = {}
    for path in MODULES.values():
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
                body_start = node.body[0]
                if isinstance(body_start, ast.Expr) and isinstance(getattr(body_start, "value", None), ast.Constant):
                    body_start = node.body[1] if len(node.body) > 1 else body_start  # skip the docstring
                n = node.end_lineno - body_start.lineno + 1
                if n > 80:
                    long[f"{path.relative_to(PKG.parent)}:{node.lineno} {node.name}"] = n
    assert not long, f"functions over 80 lines (docstring excluded): {long}"
