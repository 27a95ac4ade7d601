"""The layout is the architecture: imports run one way.

edge.core <- edge.hw, edge.vlm <- edge.runtime <- edge.interfaces, edge.recordings <- edge.app
<- edge.ops, edge.lab, edge.bench <- edge.cli (see ALLOWED); edge.sim and train may use the
core (the simulator also the hardware contracts and tables, train the simulator, the dataset
recorder, which presses with the runtime's own press controller, and the bench's results
file); nothing in edge imports train, the daemon never loads the simulator, and importing
train loads no press machinery until a dataset is recorded. No exception per file.
"""

from __future__ import annotations

import ast
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]

def _below(*layers: str) -> set[str]:
    """``layers`` and everything they may import."""
    return {"edge", *layers}.union(*(ALLOWED[layer] for layer in layers if layer in ALLOWED))


# Which rooms each room may import (besides the stdlib and third parties), built bottom up:
# core < hw, vlm < runtime < interfaces, recordings < app < ops, lab, bench < cli. The
# simulator sits beside: it may use the core and the hardware contracts and tables, and the
# tools that drive or measure the emulated robot may use it.
ALLOWED: dict[str, set[str]] = {}
ALLOWED["edge.core"] = _below("edge.core")
ALLOWED["edge.vlm"] = _below("edge.vlm", "edge.core")
ALLOWED["edge.hw"] = _below("edge.hw", "edge.core")
ALLOWED["edge.sim"] = _below("edge.sim", "edge.hw")
ALLOWED["edge.runtime"] = _below("edge.runtime", "edge.hw", "edge.vlm")
ALLOWED["edge.interfaces"] = _below("edge.interfaces", "edge.runtime")
ALLOWED["edge.recordings"] = _below("edge.recordings", "edge.runtime")
ALLOWED["edge.deploy"] = _below("edge.deploy", "edge.core")
ALLOWED["edge.app"] = _below("edge.app", "edge.interfaces", "edge.recordings")
ALLOWED["edge.ops"] = _below("edge.ops", "edge.app", "edge.sim")
ALLOWED["edge.lab"] = _below("edge.lab", "edge.app", "edge.sim")
ALLOWED["edge.bench"] = _below("edge.bench", "edge.lab")
ALLOWED["edge.cli"] = _below("edge.cli", "edge.ops", "edge.bench", "edge.deploy")
# The entry point holds the daemon's signals (edge.runtime.signals) before it loads the CLI.
ALLOWED["edge.__main__"] = {"edge", "edge.runtime", "edge.cli"}
ALLOWED["edge"] = {"edge"}
# Training uses the core, the VLM client, the simulator, the dataset recorder (which presses
# with the runtime's own press controller) and the bench's results file.
ALLOWED["train"] = {"train", "edge", "edge.core", "edge.vlm", "edge.sim", "edge.lab",
                    "edge.bench"}


def _module(path: Path) -> str:
    parts = list(path.relative_to(ROOT).with_suffix("").parts)
    if parts[-1] == "__init__":
        parts.pop()
    return ".".join(parts)


def _layer(module: str) -> str:
    for layer in sorted(ALLOWED, key=len, reverse=True):
        if module == layer or module.startswith(layer + "."):
            return layer
    raise AssertionError(f"{module} is in no layer")


def _imports(path: Path) -> list[tuple[int, str]]:
    """Every project module ``path`` imports, at any depth (lazy imports included)."""
    out = []
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.Import):
            out += [(node.lineno, a.name) for a in node.names]
        elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            out.append((node.lineno, node.module))
            out += [(node.lineno, f"{node.module}.{a.name}") for a in node.names
                    if node.module in ("edge", "train")]
    return [(line, m) for line, m in out if m.split(".")[0] in ("edge", "train")]


def test_imports_run_one_way():
    wrong = []
    for path in sorted([*ROOT.glob("edge/**/*.py"), *ROOT.glob("train/**/*.py")]):
        layer = _layer(_module(path))
        for line, target in _imports(path):
            if _layer(target) not in ALLOWED[layer]:
                wrong.append(f"{path.relative_to(ROOT)}:{line} ({layer}) imports {target}")
    assert not wrong, "imports against the layering:\n" + "\n".join(wrong)


@pytest.mark.parametrize("module", ["edge.app", "edge.runtime.lifecycle", "edge.cli"])
def test_the_daemon_loads_neither_training_nor_the_simulator(module):
    code = (f"import sys, {module}; "
            "print(sorted(m for m in sys.modules if m == 'torch' or m.startswith('train') "
            "or m.startswith('edge.sim') or m.startswith(('edge.ops', 'edge.lab', 'edge.bench'))))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         cwd=ROOT, check=True).stdout.strip()
    assert out == "[]", f"importing {module} loaded {out}"


def test_importing_train_loads_no_press_machinery():
    """Only recording a dataset (edge.lab.record, imported where it records) loads the
    daemon's press controller, the drivers and the virtual robot."""
    code = ("import importlib, pkgutil, sys, train; "
            "[importlib.import_module(m.name) for m in pkgutil.walk_packages(train.__path__, "
            "'train.') if not m.name.endswith('__main__')]; "
            "print(sorted(m for m in sys.modules if m.startswith(('edge.runtime', 'edge.hw', "
            "'edge.lab.record', 'edge.sim.virtual'))))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         cwd=ROOT, check=True).stdout.strip()
    assert out == "[]", f"importing train loaded {out}"


def _runtime_imports(path: Path, modules: set[str]) -> set[str]:
    """The project modules ``path`` loads when it runs: any depth, lazy imports included,
    ``if TYPE_CHECKING:`` blocks left out (they never run). ``from package import module``
    needs the module, not the package's own names."""
    tree = ast.parse(path.read_text(), str(path))
    skipped = {id(n) for node in ast.walk(tree) if isinstance(node, ast.If)
               and getattr(node.test, "id", None) == "TYPE_CHECKING"
               for child in node.body for n in ast.walk(child)}
    found = set()
    for node in ast.walk(tree):
        if id(node) in skipped:
            continue
        if isinstance(node, ast.Import):
            found |= {a.name for a in node.names}
        elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            for a in node.names:
                name = f"{node.module}.{a.name}"
                found.add(name if name in modules else node.module)
    return found


def test_no_import_cycle():
    paths = {_module(p): p for p in [*ROOT.glob("edge/**/*.py"), *ROOT.glob("train/**/*.py")]}
    graph = {m: {t for t in _runtime_imports(p, set(paths)) if t in paths and t != m}
             for m, p in paths.items()}
    cycles: set[tuple[str, ...]] = set()

    def visit(m: str, trail: list[str]) -> None:
        for t in sorted(graph[m]):
            if t in trail:
                cycle = trail[trail.index(t):]
                start = cycle.index(min(cycle))
                cycles.add(tuple(cycle[start:] + cycle[:start]))
            elif t not in done:
                visit(t, [*trail, t])
        done.add(m)

    done: set[str] = set()
    for m in sorted(graph):
        if m not in done:
            visit(m, [m])
    assert not cycles, "import cycles:\n" + "\n".join(" -> ".join(c) for c in sorted(cycles))


def _private_uses(path: Path, modules: set[str]) -> list[tuple[int, str]]:
    """Another project module's private names that ``path`` takes: ``from m import _x``, or
    ``m._x`` on a name bound to a project module (``import m``, ``import a.m as m``, ``from a
    import m``). Dunders are not private; a module's own names are its business."""
    tree = ast.parse(path.read_text(), str(path))
    bound: dict[str, str] = {}  # local name -> the project module it stands for
    found = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            for a in node.names:
                if a.asname:
                    bound[a.asname] = a.name
                else:
                    bound[a.name.split(".")[0]] = a.name.split(".")[0]
        elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            for a in node.names:
                if f"{node.module}.{a.name}" in modules:
                    bound[a.asname or a.name] = f"{node.module}.{a.name}"
                elif node.module in modules and _private(a.name):
                    found.append((node.lineno, f"{node.module}.{a.name}"))
    for node in ast.walk(tree):
        if isinstance(node, ast.Attribute) and _private(node.attr):
            owner = _dotted(node.value, bound)
            if owner in modules:
                found.append((node.lineno, f"{owner}.{node.attr}"))
    return found


def _private(name: str) -> bool:
    return name.startswith("_") and not name.endswith("__")


def _dotted(node: ast.expr, bound: dict[str, str]) -> str | None:
    """``a.b.c`` with ``a`` resolved through the imports, or None for any other expression."""
    if isinstance(node, ast.Name):
        return bound.get(node.id)
    if isinstance(node, ast.Attribute):
        base = _dotted(node.value, bound)
        return f"{base}.{node.attr}" if base else None
    return None


def test_no_module_takes_another_modules_private_names():
    paths = {_module(p): p for p in [*ROOT.glob("edge/**/*.py"), *ROOT.glob("train/**/*.py")]}
    taken = [f"{path.relative_to(ROOT)}:{line} takes {name}"
             for module, path in sorted(paths.items())
             for line, name in _private_uses(path, set(paths))]
    assert not taken, ("private names used across modules (make them public where they are "
                       "defined):\n" + "\n".join(taken))


def _starts_a_process() -> None:
    subprocess.run(["true"], check=True)


def _calls_a_helper_that_does() -> None:
    _starts_a_process()


def _records_a_press() -> None:
    from edge.lab.record import record_press

    record_press("cube", 0)


def _reads_the_layout() -> list[tuple[int, str]]:
    return _imports(ROOT / "edge" / "__main__.py")


def test_the_unit_tier_leaves_out_what_starts_a_process_or_an_emulator():
    """tests/conftest.py marks a test integration from what it names, through the tests'
    own helpers and imports inside it too; `make test-unit` runs the rest."""
    from tests.conftest import _names_integration

    assert _names_integration(_starts_a_process, set())
    assert _names_integration(_calls_a_helper_that_does, set())
    assert _names_integration(_records_a_press, set())
    assert not _names_integration(_reads_the_layout, set())
