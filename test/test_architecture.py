"""The architecture's rules, checked on the source tree: small modules, small folders, no
import cycle, cores without ROS, one place for the WGS84 constants, no machine paths, and a
README layout that matches the tree."""

from __future__ import annotations

import ast
import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PACKAGE = ROOT / "vehicle_estimation"
MAX_MODULE_LINES = 600
MAX_MODULES_PER_FOLDER = 10


def _modules() -> list[Path]:
    return sorted(p for p in PACKAGE.rglob("*.py") if "__pycache__" not in p.parts)


def _module_name(path: Path) -> str:
    parts = list(path.relative_to(ROOT).with_suffix("").parts)
    if parts[-1] == "__init__":
        parts.pop()
    return ".".join(parts)


def _imports(path: Path) -> set[str]:
    """The package modules ``path`` imports (at any depth of the file)."""
    tree = ast.parse(path.read_text(encoding="utf-8"))
    found: set[str] = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            found.update(a.name for a in node.names)
        elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            found.add(node.module)
            found.update(f"{node.module}.{a.name}" for a in node.names)
    return {name for name in found if name.startswith("vehicle_estimation")}


def test_no_module_is_over_the_size_limit():
    big = {str(p.relative_to(ROOT)): n for p in _modules()
           if (n := len(p.read_text(encoding="utf-8").splitlines())) > MAX_MODULE_LINES}
    assert not big, big


def test_no_folder_holds_too_many_modules():
    folders: dict[Path, int] = {}
    for p in _modules():
        folders[p.parent] = folders.get(p.parent, 0) + 1
    crowded = {str(f.relative_to(ROOT)): n for f, n in folders.items() if n > MAX_MODULES_PER_FOLDER}
    assert not crowded, crowded


def test_no_import_cycle():
    names = {_module_name(p): p for p in _modules()}
    graph = {name: {m for m in _imports(path) if m in names and m != name} for name, path in names.items()}
    # a package's __init__ importing its own submodules is how packages work, not a cycle
    for name in graph:
        graph[name] = {m for m in graph[name] if not m.startswith(name + ".")}
    state: dict[str, int] = {}
    cycles: list[list[str]] = []

    def visit(node: str, stack: list[str]) -> None:
        state[node] = 1
        for nxt in sorted(graph[node]):
            if state.get(nxt) == 1:
                cycles.append(stack[stack.index(nxt):] + [nxt])
            elif nxt not in state:
                visit(nxt, stack + [nxt])
        state[node] = 2

    for name in sorted(graph):
        if name not in state:
            visit(name, [name])
    assert not cycles, cycles


def _top_level_names(path: Path) -> set[str]:
    """What ``from <module> import name`` can find in ``path`` without running it."""
    names: set[str] = set()
    for node in ast.parse(path.read_text(encoding="utf-8")).body:
        if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef, ast.ClassDef)):
            names.add(node.name)
        elif isinstance(node, (ast.Assign, ast.AnnAssign)):
            targets = node.targets if isinstance(node, ast.Assign) else [node.target]
            names.update(n.id for t in targets for n in ast.walk(t) if isinstance(n, ast.Name))
        elif isinstance(node, (ast.Import, ast.ImportFrom)):
            names.update((a.asname or a.name).split(".")[0] for a in node.names)
    return names


def test_every_package_import_names_something_that_exists():
    # lazy imports inside functions (the CLI's ``python -m`` entry points) run only when a
    # user starts that script, so a name removed from its module would fail nowhere else
    names = {_module_name(p): p for p in _modules()}
    missing: list[str] = []
    for path in _modules():
        for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
            if not (isinstance(node, ast.ImportFrom) and node.level == 0 and node.module in names):
                continue
            defined = _top_level_names(names[node.module])
            missing += [f"{path.relative_to(ROOT)}:{node.lineno} {node.module}.{a.name}" for a in node.names
                        if a.name != "*" and a.name not in defined and f"{node.module}.{a.name}" not in names]
    assert not missing, missing


@pytest.mark.parametrize("path", [p for p in _modules() if "estimators" in p.parts], ids=lambda p: p.name)
def test_estimator_cores_import_no_ros(path):
    tree = ast.parse(path.read_text(encoding="utf-8"))
    ros = {"rclpy", "rosbags", "sensor_msgs", "geometry_msgs", "nav_msgs", "std_msgs", "diagnostic_msgs"}
    bad = [n for n in ast.walk(tree) if isinstance(n, (ast.Import, ast.ImportFrom))
           and any((a.name if isinstance(n, ast.Import) else (n.module or "")).split(".")[0] in ros
                   for a in n.names)]
    assert not bad and "vehicle_estimation.ros" not in _imports(path)


def test_the_wgs84_ellipsoid_is_written_nowhere_in_the_package():
    hits = [str(p) for p in _modules() if re.search(r"6378137|298\.257", p.read_text(encoding="utf-8"))]
    assert not hits, hits


def test_no_machine_path_in_shipped_files():
    shipped = [*_modules(), *(ROOT / "params").rglob("*.yaml"), ROOT / "README.md", ROOT / "setup.py",
               ROOT / "package.xml"]
    pattern = re.compile(r"(?<![\w.])/(home|root|Users|work|mnt|media)/[\w.-]+")
    hits = [f"{p.relative_to(ROOT)}: {m.group(0)}" for p in shipped
            for m in pattern.finditer(p.read_text(encoding="utf-8"))]
    assert not hits, hits


def test_readme_layout_names_every_package_folder():
    text = (ROOT / "README.md").read_text(encoding="utf-8")
    section = text[text.index("## Layout"):]
    block = section[section.index("```"):section.index("```", section.index("```") + 3)]
    listed = set(re.findall(r"^(vehicle_estimation/[\w/]*?)/? +\S", block, re.M))
    folders = {str(p.parent.relative_to(ROOT)) for p in _modules()} | {"vehicle_estimation/models"}
    folders.discard("vehicle_estimation")
    assert listed == folders, f"README lists {sorted(listed - folders)} that do not exist and misses {sorted(folders - listed)}"
