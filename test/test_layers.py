"""The package layers: no import (top-level or inside a function) points from a lower package to a higher one.

Ground truth is the layering written down below (docs/ARCHITECTURE.md draws the same): each
package lists the LSU packages it may import. The test reads every module's imports with
``ast`` (so an import hidden inside a function counts too) and checks them against that list,
and checks that the list itself has no circle. Inside the packages, no module imports itself
through others either (a circle between modules: one of them cannot be read without the other).
"""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

SRC = Path(__file__).resolve().parents[1] / "src"

_BASE = {"lsu_interfaces", "tf2_msgs", "lsu_common", "lsu_config"}
# package -> the LSU packages it may import (lower layers only)
ALLOWED: dict[str, set[str]] = {
    "lsu_common": set(),
    "lsu_config": set(),
    "lsu_bags": {"lsu_interfaces", "lsu_common"},
    "lsu_driver": _BASE,
    "lsu_cameras": _BASE,
    # the simulator: above the cameras (it writes its rig's calibration with their calib_io and is their
    # ``sim`` source through the lsu.camera_sources entry point), below whoever renders test scenes with it
    "lsu_sim": _BASE | {"lsu_cameras", "lsu_extract"},  # lsu_extract: devdata (the ICT face model's folder)
    "lsu_extract": _BASE,
    "lsu_reconstruct": _BASE | {"lsu_bags", "lsu_cameras", "lsu_extract", "lsu_sim"},
    "lsu_faces": _BASE | {"lsu_bags", "lsu_cameras", "lsu_sim"},
    "lsu_view": _BASE | {"lsu_bags"},
    "lsu_scan": _BASE | {"lsu_bags", "lsu_cameras", "lsu_driver", "lsu_extract", "lsu_reconstruct"},
    "lsu_accuracy": _BASE | {"lsu_bags", "lsu_cameras", "lsu_extract", "lsu_reconstruct", "lsu_faces", "lsu_sim"},
    "lsu_tools": _BASE | {"lsu_bags", "lsu_cameras", "lsu_extract", "lsu_reconstruct", "lsu_scan", "lsu_accuracy",
                          "lsu_sim"},
    "lsu_testing": _BASE | {"lsu_bags", "lsu_cameras", "lsu_scan", "lsu_accuracy", "lsu_tools", "lsu_sim"},
    "lsu_web": _BASE | {"lsu_bags", "lsu_cameras", "lsu_reconstruct", "lsu_faces", "lsu_scan"},
    "lsu_batch": _BASE | {"lsu_bags", "lsu_extract", "lsu_reconstruct", "lsu_faces", "lsu_scan", "lsu_tools"},
}


def python_packages():
    return sorted(p.name for p in SRC.iterdir() if (p / p.name / "__init__.py").is_file())


def imported_lsu_packages(package: str, src: Path = SRC) -> dict[str, set[str]]:
    """LSU package -> the modules of ``package`` that import it (tests excluded)."""
    found: dict[str, set[str]] = {}
    for path in sorted((src / package / package).rglob("*.py")):
        for node in ast.walk(ast.parse(path.read_text(), str(path))):
            if isinstance(node, ast.Import):
                names = [alias.name for alias in node.names]
            elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
                names = [node.module]
            else:
                continue
            for name in names:
                top = name.split(".")[0]
                if top != package and (top.startswith("lsu_") or top == "tf2_msgs"):
                    found.setdefault(top, set()).add(str(path.relative_to(src)))
    return found


def _module_name(path: Path, src: Path) -> str:
    parts = list(path.relative_to(src).parts[1:])
    parts[-1] = parts[-1][: -len(".py")]
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def module_imports(src: Path = SRC) -> dict[str, set[str]]:
    """Every LSU module -> the LSU modules it imports (relative or absolute, in functions too; tests excluded).

    ``from pkg import name`` counts as an import of ``pkg.name`` when that is a module, else of ``pkg``.
    """
    paths = {_module_name(p, src): p for p in sorted(src.glob("*/lsu_*/**/*.py"))}
    paths.update({_module_name(p, src): p for p in sorted(src.glob("*/lsu_*/*.py"))})
    graph: dict[str, set[str]] = {}
    for module, path in paths.items():
        package = module if path.name == "__init__.py" else module.rpartition(".")[0]
        found = set()
        for node in ast.walk(ast.parse(path.read_text(), str(path))):
            if isinstance(node, ast.Import):
                names = [alias.name for alias in node.names]
            elif isinstance(node, ast.ImportFrom):
                base = node.module or ""
                if node.level:
                    parent = package.split(".")[: len(package.split(".")) - (node.level - 1)]
                    base = ".".join(parent + ([base] if base else []))
                names = [f"{base}.{alias.name}" if f"{base}.{alias.name}" in paths else base for alias in node.names]
            else:
                continue
            for name in names:
                while name and name not in paths:
                    name = name.rpartition(".")[0]
                if name and name != module:
                    found.add(name)
        graph[module] = found
    return graph


def find_circle(graph: dict[str, set[str]]) -> list[str]:
    """One circle of ``graph`` (its nodes in order, the first repeated at the end), or [] when it has none."""
    state: dict[str, str] = {}

    def visit(node: str, path: list[str]) -> list[str]:
        if state.get(node) == "open":
            return path[path.index(node):] + [node]
        if state.get(node) == "done":
            return []
        state[node] = "open"
        for dep in sorted(graph.get(node, ())):
            circle = visit(dep, path + [node])
            if circle:
                return circle
        state[node] = "done"
        return []

    for node in sorted(graph):
        circle = visit(node, [])
        if circle:
            return circle
    return []


def test_every_python_package_has_a_layer():
    assert set(python_packages()) == set(ALLOWED) - {"lsu_interfaces", "tf2_msgs"}


@pytest.mark.parametrize("package", sorted(ALLOWED))
def test_imports_only_point_down(package):
    if not (SRC / package / package).is_dir():
        pytest.skip(f"{package} has no Python sources")
    upward = {dep: sorted(files) for dep, files in imported_lsu_packages(package).items() if dep not in ALLOWED[package]}
    assert not upward, f"{package} imports packages above it (or beside it): {upward}"


def test_the_layers_have_no_circle():
    state: dict[str, str] = {}

    def visit(package: str, path: tuple) -> None:
        if state.get(package) == "done":
            return
        assert state.get(package) != "open", f"circle: {' -> '.join(path + (package,))}"
        state[package] = "open"
        for dep in ALLOWED.get(package, set()):
            visit(dep, path + (package,))
        state[package] = "done"

    for package in ALLOWED:
        visit(package, ())


def test_no_module_imports_itself_through_others():
    circle = find_circle(module_imports())
    assert not circle, f"import circle between modules: {' -> '.join(circle)} (move what both need into a module of its own)"


def test_the_module_checker_finds_a_circle_through_an_import_inside_a_function(tmp_path):
    """The checker's own ground truth: cli -> tool at the top, tool -> cli inside a function, is a circle."""
    pkg = tmp_path / "lsu_x" / "lsu_x"
    pkg.mkdir(parents=True)
    (pkg / "__init__.py").write_text("")
    (pkg / "cli.py").write_text("from .tool import f\nTYPE = 1\n")
    (pkg / "tool.py").write_text("def f():\n    from .cli import TYPE\n    return TYPE\n")
    (pkg / "other.py").write_text("from lsu_x import tool\n")
    graph = module_imports(tmp_path)
    assert graph == {"lsu_x": set(), "lsu_x.cli": {"lsu_x.tool"}, "lsu_x.tool": {"lsu_x.cli"}, "lsu_x.other": {"lsu_x.tool"}}
    assert find_circle(graph) == ["lsu_x.cli", "lsu_x.tool", "lsu_x.cli"]
    (pkg / "tool.py").write_text("def f():\n    return 1\n")
    assert find_circle(module_imports(tmp_path)) == []


def test_the_checker_sees_an_import_inside_a_function(tmp_path):
    """The checker's own ground truth: an in-function import of a higher package is found."""
    pkg = tmp_path / "lsu_bags" / "lsu_bags"
    pkg.mkdir(parents=True)
    (pkg / "__init__.py").write_text("")
    (pkg / "x.py").write_text("def f():\n    from lsu_tools.cli import main\n    return main\n")
    assert imported_lsu_packages("lsu_bags", tmp_path) == {"lsu_tools": {"lsu_bags/lsu_bags/x.py"}}
