"""tools/annotate_arrays.py rewrites only annotations, adds its import once and is idempotent."""

import ast
import importlib.util
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def annotate():
    spec = importlib.util.spec_from_file_location("annotate_arrays", ROOT / "tools" / "annotate_arrays.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


SOURCE = '''"""A module."""

from __future__ import annotations

import numpy as np

Pair = tuple[np.ndarray, np.ndarray]


def f(a: np.ndarray, b: "np.ndarray | None" = None, *rest: np.ndarray) -> list[np.ndarray]:
    c: np.ndarray = np.ndarray((3,))
    typed: np.ndarray[tuple[int], np.dtype[np.float64]] = np.zeros(1)
    return [a] if isinstance(a, np.ndarray) else [c, typed]
'''


def test_annotations_become_the_alias_and_nothing_else_changes(annotate):
    new, count = annotate.rewrite(SOURCE)
    assert count == 7  # the alias (2), a, b, *rest, the return, c
    assert "Pair = tuple[AnyArray, AnyArray]" in new
    assert 'def f(a: AnyArray, b: "AnyArray | None" = None, *rest: AnyArray) -> list[AnyArray]:' in new
    assert "c: AnyArray = np.ndarray((3,))" in new                       # a call stays
    assert "isinstance(a, np.ndarray)" in new                              # a class test stays
    assert "typed: np.ndarray[tuple[int], np.dtype[np.float64]]" in new    # already parametrized
    assert new.count("from lsu_common.arrays import AnyArray\n") == 1
    ast.parse(new)


def test_a_second_run_changes_nothing(annotate):
    once, _ = annotate.rewrite(SOURCE)
    twice, count = annotate.rewrite(once)
    assert (twice, count) == (once, 0)


def test_an_existing_import_of_the_module_is_extended(annotate):
    source = "import numpy as np\nfrom lsu_common.arrays import FloatArray\n\n\ndef g(x: np.ndarray) -> FloatArray: ...\n"
    new, count = annotate.rewrite(source)
    assert count == 1
    assert "from lsu_common.arrays import AnyArray, FloatArray\n" in new
    assert new.count("lsu_common.arrays") == 1


def test_an_import_after_set_up_code_keeps_its_place(annotate):
    source = ("import os\n\nos.environ.setdefault('X', '1')  # before numpy\n\nimport numpy as np  # noqa: E402\n\n\n"
              "def g(x: np.ndarray) -> None: ...\n")
    new, _ = annotate.rewrite(source)
    lines = new.splitlines()
    assert lines.index("from lsu_common.arrays import AnyArray  # noqa: E402") > lines.index("import numpy as np  # noqa: E402")


def test_the_workspace_has_no_bare_annotation_left(annotate):
    left = {str(p.relative_to(ROOT)): n for p in annotate.files() if (n := annotate.rewrite(p.read_text())[1])}
    assert left == {}, f"run python tools/annotate_arrays.py: {left}"
