"""The tree keeps its layout: pure maths, one I/O package, no import circles, no benchmarks on the robot."""

import ast
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
PACKAGES = ("wfnn_common", "wfnn_io", "wfnn_client", "wfnn_server", "wfnn_bench", "sims")
# A thread, a clock, a file, a socket or Zenoh: none belongs in the maths.
NOT_IN_MATHS = {
    "wfnn_io", "wfnn_client", "wfnn_server", "wfnn_bench", "sims", "zenoh", "threading", "_thread",
    "multiprocessing", "concurrent", "asyncio", "sched", "time", "datetime", "socket", "select", "selectors",
    "os", "io", "pathlib", "tempfile", "shutil", "subprocess", "signal", "pickle",
}  # fmt: skip


def modules() -> dict[str, Path]:
    """Every module of the project's packages, by dotted name."""
    found = {}
    for package in PACKAGES:
        for path in sorted((ROOT / package).rglob("*.py")):
            name = ".".join(path.relative_to(ROOT).with_suffix("").parts).removesuffix(".__init__")
            found[name] = path
    return found


def imported(path: Path) -> set[str]:
    """Dotted names a module imports anywhere (top level, functions, TYPE_CHECKING blocks)."""
    names = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.Import):
            names.update(alias.name for alias in node.names)
        elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
            names.add(node.module)
            names.update(f"{node.module}.{alias.name}" for alias in node.names)
        elif isinstance(node, ast.ImportFrom):
            raise AssertionError(f"{path}: relative import (the project imports by absolute name)")
    return names


def project_graph() -> dict[str, set[str]]:
    """Module -> the project modules it imports (a name inside a module counts as the module)."""
    mods = modules()

    def owner(name: str) -> str | None:
        while name and name not in mods:
            name = name.rpartition(".")[0]
        return name or None

    return {m: {o for n in imported(p) if (o := owner(n)) is not None and o != m} for m, p in mods.items()}


def test_the_maths_imports_no_io_thread_clock_file_or_zenoh():
    offences = []
    for name, path in modules().items():
        if not name.startswith("wfnn_common"):
            continue
        for dotted in imported(path):
            if dotted.split(".")[0] in NOT_IN_MATHS:
                offences.append(f"{name} imports {dotted}")
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.Call) and isinstance(node.func, ast.Name) and node.func.id == "open":
                offences.append(f"{name} opens a file (line {node.lineno})")
    assert offences == []


def test_the_purity_check_catches_an_offence(tmp_path):
    module = tmp_path / "m.py"
    module.write_text("def f():\n    import threading\n    from wfnn_io.persist import write_json\n")
    assert {"threading", "wfnn_io.persist", "wfnn_io.persist.write_json"} <= imported(module)


def test_no_import_circle():
    graph = project_graph()
    state: dict[str, int] = {}  # 1: on the current path, 2: done
    circles = []

    def visit(module: str, path: list[str]) -> None:
        state[module] = 1
        for dep in sorted(graph[module]):
            if state.get(dep) == 1:
                circles.append(" -> ".join([*path[path.index(dep) :], dep]))
            elif dep not in state:
                visit(dep, [*path, dep])
        state[module] = 2

    for module in sorted(graph):
        if module not in state:
            visit(module, [module])
    assert circles == []


def test_the_layers_point_one_way():
    """Maths <- I/O <- robot side and server; the robot side never reaches the server or the benchmarks."""
    allowed = {
        "wfnn_common": {"wfnn_common"},
        "wfnn_io": {"wfnn_common", "wfnn_io"},
        "sims": {"wfnn_common", "sims"},
        "wfnn_client": {"wfnn_common", "wfnn_io", "sims", "wfnn_client"},
        "wfnn_server": {"wfnn_common", "wfnn_io", "wfnn_server"},
    }
    wrong = [
        f"{module} imports {dep}"
        for module, deps in project_graph().items()
        for dep in deps
        if module.split(".")[0] in allowed and dep.split(".")[0] not in allowed[module.split(".")[0]]
    ]
    assert wrong == []
