"""The package layers: no import (top-level or inside a function) points from a lower package to a higher one.

Ground truth is the layering written down below (docs/ARCHITECTURE.md draws the same): each
package lists the LSU packages it may import. The test reads every module's imports with
``ast`` (so an import hidden inside a function counts too) and checks them against that list,
and checks that the list itself has no circle.
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
    "lsu_extract": _BASE,
    "lsu_reconstruct": _BASE | {"lsu_bags", "lsu_cameras", "lsu_extract"},
    "lsu_faces": _BASE | {"lsu_bags", "lsu_cameras"},
    "lsu_view": _BASE | {"lsu_bags"},
    "lsu_scan": _BASE | {"lsu_bags", "lsu_cameras", "lsu_driver", "lsu_extract", "lsu_reconstruct"},
    "lsu_accuracy": _BASE | {"lsu_bags", "lsu_cameras", "lsu_extract", "lsu_reconstruct", "lsu_faces"},
    "lsu_tools": _BASE | {"lsu_bags", "lsu_cameras", "lsu_extract", "lsu_reconstruct", "lsu_scan", "lsu_accuracy"},
    "lsu_testing": _BASE | {"lsu_bags", "lsu_cameras", "lsu_scan", "lsu_accuracy", "lsu_tools"},
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


def test_the_checker_sees_an_import_inside_a_function(tmp_path):
    """The checker's own ground truth: an in-function import of a higher package is found."""
    pkg = tmp_path / "lsu_bags" / "lsu_bags"
    pkg.mkdir(parents=True)
    (pkg / "__init__.py").write_text("")
    (pkg / "x.py").write_text("def f():\n    from lsu_tools.cli import main\n    return main\n")
    assert imported_lsu_packages("lsu_bags", tmp_path) == {"lsu_tools": {"lsu_bags/lsu_bags/x.py"}}
