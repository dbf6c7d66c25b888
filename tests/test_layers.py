"""The layers the design names hold: the tick core imports no driver, no fieldbus or simulation
code and no hardware or simulation library; neither bus driver imports the other; controllers
import no driver; no module imports itself back."""

from __future__ import annotations

import ast
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
SOURCES = {"aiohal": ROOT / "aiohal", "aiohal.drivers": ROOT / "drivers", "aiohal.controllers": ROOT / "controllers"}
#: the rooms apart from the tick core, then the libraries it never loads
APART = ("aiohal.fieldbus", "aiohal.simulation", "aiohal.mjcf", "aiohal.drivers", "aiohal.controllers")
CORE_ONLY = (*APART, "mujoco", "pysoem", "can", "canopen", "zenoh")
#: bus drivers, each with its simulator: what both need is in aiohal.fieldbus or aiohal.simulation
BUSES = ("aiohal.drivers.ethercat", "aiohal.drivers.canopen")


def module_files() -> dict[str, Path]:
    """Every installed module name of the repo's packages, with its file."""
    out: dict[str, Path] = {}
    for package, folder in SOURCES.items():
        for path in folder.rglob("*.py"):
            parts = list(path.relative_to(folder).with_suffix("").parts)
            if parts[-1] == "__init__":
                parts.pop()
            name = ".".join([package, *parts])
            if name.startswith("aiohal.drivers") or name.startswith("aiohal.controllers") or package == "aiohal":
                out.setdefault(name, path)
    return out


def within(name: str, packages: tuple[str, ...]) -> bool:
    """``name`` is one of ``packages`` or a module inside one."""
    return any(name == p or name.startswith(p + ".") for p in packages)


def imports_of(name: str, path: Path, known: set[str]) -> set[str]:
    """The repo modules a module imports, at the top or inside a function (a lazy import is
    still a dependency)."""
    tree = ast.parse(path.read_text())
    package = name if path.name == "__init__.py" else name.rpartition(".")[0]
    found: set[str] = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            targets = [alias.name for alias in node.names]
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                anchor = package.split(".")[: len(package.split(".")) - node.level + 1]
                base = ".".join([*anchor, base] if base else anchor)
            targets = [f"{base}.{alias.name}" for alias in node.names] + [base]
        else:
            continue
        for target in targets:
            while target and target not in known:
                target = target.rpartition(".")[0]
            if target and target != name:
                found.add(target)
    return found


def core_modules() -> dict[str, Path]:
    """The tick core's modules: aiohal's, outside the rooms kept apart from it."""
    return {m: path for m, path in module_files().items() if within(m, ("aiohal",)) and not within(m, APART)}


def test_core_imports_no_driver_fieldbus_or_hardware_library():
    core = [m for m in core_modules() if not m.endswith("__main__")]
    code = (f"import sys, importlib\nfor m in {core!r}: importlib.import_module(m)\n"
            f"print(sorted(m for m in sys.modules if m.startswith({CORE_ONLY!r})))")
    proc = subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0, proc.stderr
    assert proc.stdout.strip() == "[]"


def test_core_imports_no_simulation_module_even_lazily():
    known = set(module_files())
    for name, path in core_modules().items():
        simulation = {m for m in imports_of(name, path, known) if within(m, ("aiohal.simulation",))}
        assert not simulation, f"{name} imports {sorted(simulation)}"


def test_neither_bus_imports_the_other_and_shared_code_imports_no_driver():
    files = module_files()
    known = set(files)
    for name, path in files.items():
        imported = imports_of(name, path, known)
        for bus in BUSES:
            if within(name, (bus,)):
                others = tuple(b for b in BUSES if b != bus)
                crossing = {m for m in imported if within(m, others)}
                assert not crossing, f"{name} imports {sorted(crossing)}"
        if within(name, ("aiohal.fieldbus", "aiohal.simulation")):
            drivers = {m for m in imported if within(m, ("aiohal.drivers",))}
            assert not drivers, f"{name} imports {sorted(drivers)}"


def test_controllers_import_no_driver():
    files = module_files()
    known = set(files)
    for name, path in files.items():
        if name.startswith("aiohal.controllers"):
            drivers = {m for m in imports_of(name, path, known) if m.startswith("aiohal.drivers")}
            assert not drivers, f"{name} imports {sorted(drivers)}"


def test_no_import_cycles():
    files = module_files()
    known = set(files)
    graph = {name: imports_of(name, path, known) for name, path in files.items()}
    # a package's __init__ importing its own submodules is not a cycle of the design
    for name in graph:
        graph[name] = {m for m in graph[name] if not name.startswith(m + ".")}
    state: dict[str, int] = {}
    stack: list[str] = []

    def visit(node: str) -> None:
        state[node] = 1
        stack.append(node)
        for nxt in sorted(graph.get(node, ())):
            if state.get(nxt) == 1:
                cycle = [*stack[stack.index(nxt):], nxt]
                raise AssertionError("import cycle: " + " -> ".join(cycle))
            if nxt not in state:
                visit(nxt)
        stack.pop()
        state[node] = 2

    for node in sorted(graph):
        if node not in state:
            visit(node)


CORE_FILES = (ROOT / "aiohal" / "core" / "loop.py", ROOT / "aiohal" / "safety")


def private_names(path: Path, classes: set[str]) -> set[str]:
    """The private attributes (``_name``, not dunder) a class of ``path`` sets or defines."""
    names: set[str] = set()
    for cls in ast.walk(ast.parse(path.read_text())):
        if isinstance(cls, ast.ClassDef) and cls.name in classes:
            for node in ast.walk(cls):
                if isinstance(node, ast.Attribute) and isinstance(node.value, ast.Name) and node.value.id == "self":
                    name = node.attr
                elif isinstance(node, ast.FunctionDef):
                    name = node.name
                else:
                    continue
                if name.startswith("_") and not name.endswith("__"):
                    names.add(name)
    return names


def test_outside_the_core_no_private_attribute_of_the_loop_is_read():
    """The loop and its supervisor keep their privates: the rest of aiohal reads their public
    face (the doors and outputs, only the port's: aiohal.outside.port). Drivers and
    controllers are never given the loop (they get views of the robot)."""
    private = private_names(ROOT / "aiohal" / "core" / "loop.py", {"ControlLoop"})
    private |= private_names(ROOT / "aiohal" / "safety" / "supervisor.py", {"Supervisor"})
    assert {"_publishers", "_missed_before", "_faults_reset_at"} <= private  # the scan sees them
    found = []
    for name, path in module_files().items():
        if not name.startswith("aiohal.") or name.startswith(("aiohal.drivers", "aiohal.controllers")):
            continue
        if any(path == core or core in path.parents for core in CORE_FILES):
            continue
        for node in ast.walk(ast.parse(path.read_text())):
            if (isinstance(node, ast.Attribute) and node.attr in private
                    and not (isinstance(node.value, ast.Name) and node.value.id in ("self", "cls"))):
                found.append(f"{path.relative_to(ROOT)}:{node.lineno} .{node.attr}")
    assert not found, found


def test_outside_the_tick_nothing_imports_the_loop():
    """Everything in aiohal.outside is given a LoopPort, never the loop (not even as a type)."""
    files = module_files()
    known = set(files)
    for name, path in files.items():
        if name.startswith("aiohal.outside"):
            assert "aiohal.core.loop" not in imports_of(name, path, known), f"{name} imports aiohal.core.loop"


def test_every_package_is_listed_for_the_wheel():
    """setuptools installs only the packages pyproject.toml lists: a subpackage left out works
    in the editable install the tests use and is missing from a wheel."""
    import tomllib

    listed = set(tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["setuptools"]["packages"])
    found = set()
    for package, folder in SOURCES.items():
        for init in folder.rglob("__init__.py"):
            parts = init.parent.relative_to(folder).parts
            found.add(".".join([package, *parts]))
    assert found - listed == set()


def test_every_name_aiohal_exports_resolves():
    """``aiohal``'s names are imported lazily from a table of module paths: each must lead to
    its object (a module moved and a path left behind fails only when the name is used)."""
    code = "import aiohal\nfor name in aiohal.__all__: getattr(aiohal, name)\nprint(len(aiohal.__all__))"
    proc = subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0, proc.stderr
    assert int(proc.stdout) >= 20
