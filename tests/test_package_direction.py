"""Packages import in one direction: cli -> (sitl, view, bench) -> service -> recorded -> (sim, calib)
-> backends -> (gpu, cpu) -> core -> (config, jitcache) -> base types (errors, exitcodes, interfaces, report, framepool, pacing, devices, interrupts). Module-level and
function-level imports alike: a circle hidden inside a function is still a circle. Imports under
``if TYPE_CHECKING`` name types for annotations and load nothing; they may name any part.

The service imports the simulator only inside a function (the ``sim`` camera source builds the renderer
when it is asked for), so the flight service never loads it.
"""

from __future__ import annotations

import ast
import subprocess
import sys
from pathlib import Path

import pytest

PACKAGE = Path(__file__).resolve().parent.parent / "companion"

#: Each top-level part of ``companion`` and its rank: a part may import only parts of a lower rank
#: (and itself). ``companion`` is the package's own ``__init__``.
RANK: dict[str, int] = {
    "companion": 0,
    "errors": 0,
    "exitcodes": 0,
    "interfaces": 0,
    "report": 0,
    "framepool": 0,
    "pacing": 0,
    "devices": 0,
    "interrupts": 0,
    "config": 1,
    "jitcache": 1,
    "core": 2,
    "gpu": 3,
    "cpu": 3,
    "backends": 4,
    "sim": 5,
    "calib": 5,
    "recorded": 6,
    "service": 7,
    "view": 8,
    "sitl": 8,
    "bench": 8,
    "cli": 9,
    "__main__": 10,
}

def _module_name(path: Path) -> str:
    parts = path.relative_to(PACKAGE.parent).with_suffix("").parts
    return ".".join(parts).removesuffix(".__init__")


def _part(module: str) -> str:
    parts = module.split(".")
    return parts[1] if len(parts) > 1 else parts[0]


def _imports(path: Path) -> list[tuple[str, int, bool]]:
    """(imported ``companion`` module, line, inside a function) of one file, less typing-only imports."""
    tree = ast.parse(path.read_text(encoding="utf-8"))
    deferred: set[int] = set()
    typing_only: set[int] = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.If) and "TYPE_CHECKING" in ast.unparse(node.test):
            typing_only.update(id(n) for n in ast.walk(node))
        elif isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
            deferred.update(id(n) for n in ast.walk(node))
    found = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            names = [a.name for a in node.names]
        elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
            names = [node.module]
        else:
            continue
        if id(node) in typing_only:
            continue
        found += [(n, node.lineno, id(node) in deferred) for n in names if n.split(".")[0] == "companion"]
    return found


def _all_imports() -> list[tuple[str, str, int, bool]]:
    return [
        (_module_name(p), target, line, deferred)
        for p in sorted(PACKAGE.rglob("*.py"))
        for target, line, deferred in _imports(p)
    ]


def test_every_part_of_the_package_has_a_rank() -> None:
    parts = {_part(_module_name(p)) for p in PACKAGE.rglob("*.py")}
    assert parts <= set(RANK), sorted(parts - set(RANK))


def test_imports_go_down_the_layers() -> None:
    upward = sorted(
        f"{module}:{line} imports {target}"
        for module, target, line, _ in _all_imports()
        if _part(module) != _part(target)
        and RANK[_part(target)] >= RANK[_part(module)]
    )
    assert not upward, "\n".join(upward)


def test_the_service_never_imports_the_simulator_at_module_level() -> None:
    offenders = sorted(
        f"{module}:{line} imports {target}"
        for module, target, line, deferred in _all_imports()
        if _part(module) == "service" and _part(target) == "sim" and not deferred
    )
    assert not offenders, "\n".join(offenders)


@pytest.mark.parametrize(
    ("module", "never"),
    [
        ("companion.service.daemon", ("companion.sim", "companion.view", "companion.bench", "companion.cli")),
        ("companion.core.pipeline", ("companion.gpu", "companion.service", "companion.sim", "companion.backends")),
        ("companion.config", ("companion.core",)),
        ("companion.interfaces", ("companion.core", "companion.config")),
    ],
)
def test_importing_a_module_loads_nothing_above_it(module: str, never: tuple[str, ...]) -> None:
    code = f"import sys, {module}\nprint(sorted(m for m in sys.modules if m.startswith({never!r})))\n"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "[]", out.stdout


def test_loading_and_changing_a_config_loads_nothing_above_it(tmp_path) -> None:
    """Not only importing: reading a file, validating a mapping and applying a patch (the calls a
    function-level import would hide in) load no module of the core or above. The rig check runs
    where the config meets the rig (``companion.core.rig_check.check_rig_config``)."""
    path = tmp_path / "companion.toml"
    path.write_text('[stereo]\nnum_disparities = 16\n', encoding="utf-8")  # the rig check would refuse it
    code = (
        "import sys\n"
        "from companion.config import apply_patch, load_config, parse_config\n"
        f"cfg = load_config({str(path)!r})\n"
        "cfg = apply_patch(parse_config({'stereo': {'num_disparities': 16}}), {'lut': {'median_frames': 5}})\n"
        "print(sorted(m for m in sys.modules if m.split('.')[:2] != ['companion', 'config']"
        " and m.startswith('companion.') and m not in ('companion.errors', 'companion.exitcodes',"
        " 'companion.interfaces', 'companion.report', 'companion.framepool', 'companion.devices')))\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "[]", out.stdout


#: A module longer than this is two modules: split it where its parts meet (a reader holds one module
#: in mind at a time).
MAX_MODULE_LINES = 600


def test_no_module_is_longer_than_a_reader_holds_at_once() -> None:
    long = {
        str(p.relative_to(PACKAGE)): n
        for p in PACKAGE.rglob("*.py")
        if (n := len(p.read_text(encoding="utf-8").splitlines())) > MAX_MODULE_LINES
    }
    assert not long, f"modules over {MAX_MODULE_LINES} lines: {long}"
