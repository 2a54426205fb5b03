"""The core is pure: nothing under companion/core imports asyncio, zmq or mavsdk (or reads clocks for logic),
and it depends on no shell or backend: the GPU backend, the simulator and the service depend on the core,
never the other way round (no import circle)."""

from __future__ import annotations

import ast
import subprocess
import sys
from pathlib import Path

CORE = Path(__file__).resolve().parent.parent / "companion" / "core"
FORBIDDEN = ("asyncio", "zmq", "mavsdk")
#: Packages of the shell and the backends: the core may import none of them.
OUTSIDE_CORE = ("companion.gpu", "companion.cpu", "companion.sim", "companion.service", "companion.sitl", "companion.cli", "companion.backends")


def _modules(path: Path) -> set[str]:
    """Every module ``path`` imports, by its full dotted name (function-level imports included)."""
    names: set[str] = set()
    for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
        if isinstance(node, ast.Import):
            names.update(a.name for a in node.names)
        elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            names.add(node.module)
    return names


def _imports(path: Path) -> set[str]:
    return {name.split(".")[0] for name in _modules(path)}


def test_no_core_module_names_a_forbidden_import() -> None:
    offenders = {
        str(p.relative_to(CORE)): sorted(_imports(p) & set(FORBIDDEN)) for p in CORE.rglob("*.py")
    }
    assert not {k: v for k, v in offenders.items() if v}


def test_the_core_imports_no_backend_and_no_shell() -> None:
    offenders = {
        str(p.relative_to(CORE)): sorted(
            m for m in _modules(p) if any(m == o or m.startswith(o + ".") for o in OUTSIDE_CORE)
        )
        for p in CORE.rglob("*.py")
    }
    assert not {k: v for k, v in offenders.items() if v}


def test_importing_every_core_module_loads_none_of_them() -> None:
    modules = sorted(
        "companion.core." + ".".join(p.relative_to(CORE).with_suffix("").parts).removesuffix(".__init__")
        for p in CORE.rglob("*.py")
    )
    code = (
        "import importlib, sys\n"
        f"for m in {modules!r}: importlib.import_module(m.rstrip('.'))\n"
        f"print(sorted(m for m in sys.modules if m.split('.')[0] in {FORBIDDEN!r}))\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "[]", out.stdout
