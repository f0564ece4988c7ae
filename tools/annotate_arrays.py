"""Replace bare ``np.ndarray`` annotations with the aliases of ``lsu_common.arrays``.

    python tools/annotate_arrays.py            # rewrite the files, print what changed
    python tools/annotate_arrays.py --check    # change nothing; exit 1 if a bare annotation is left

Only annotations change (parameters, returns, annotated assignments and dataclass fields, and
string annotations); ``isinstance(x, np.ndarray)`` and ``np.ndarray(...)`` stay. A bare
``np.ndarray`` says nothing of the dtype, so it becomes ``AnyArray`` (``NDArray[Any]``); where the
dtype is known, a person narrows it to ``FloatArray``, ``U8Image``, ... by hand, and this script
leaves those alone. Idempotent: a second run changes nothing. The import it adds is sorted by
``ruff check --fix --select I001`` afterwards (``make lint`` reports it otherwise).

Hand-written on ``ast`` positions rather than a regex, because the same text ``np.ndarray``
appears outside annotations, and rather than libcst, which the workspace does not otherwise need.
"""

from __future__ import annotations

import argparse
import ast
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
# what the script scans: every Python file of the packages, their tests, the cross-package tests
# and the benchmarks (patterns, so moved or new packages are included)
PATTERNS = ("src/*/lsu_*/**/*.py", "src/*/test/**/*.py", "test/**/*.py", "bench/**/*.py")
ALIAS = "AnyArray"
MODULE = "lsu_common.arrays"
NUMPY_NAMES = {"np", "numpy"}


def _is_bare_ndarray(node: ast.AST) -> bool:
    return (isinstance(node, ast.Attribute) and node.attr == "ndarray"
            and isinstance(node.value, ast.Name) and node.value.id in NUMPY_NAMES)


def _annotations(tree: ast.AST) -> list[ast.expr]:
    found: list[ast.expr] = []
    for node in ast.walk(tree):
        if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
            a = node.args
            for arg in [*a.posonlyargs, *a.args, *a.kwonlyargs, a.vararg, a.kwarg]:
                if arg is not None and arg.annotation is not None:
                    found.append(arg.annotation)
            if node.returns is not None:
                found.append(node.returns)
        elif isinstance(node, ast.AnnAssign):
            found.append(node.annotation)
    # module-level type aliases: `Frame = tuple[np.ndarray, np.ndarray]`, `Fn = Callable[...]`
    for stmt in getattr(tree, "body", []):
        if (isinstance(stmt, ast.Assign) and len(stmt.targets) == 1 and isinstance(stmt.targets[0], ast.Name)
                and stmt.targets[0].id[:1].isupper() and isinstance(stmt.value, ast.Subscript)):
            found.append(stmt.value)
    return found


def _offsets(text: str) -> list[int]:
    """Character offset of the start of each line (ast positions are line + column)."""
    starts = [0]
    for line in text.splitlines(keepends=True):
        starts.append(starts[-1] + len(line))
    return starts


def _spans(text: str, tree: ast.AST) -> list[tuple[int, int, str]]:
    """(start, end, replacement) of every bare np.ndarray inside an annotation."""
    starts = _offsets(text)
    spans: list[tuple[int, int, str]] = []

    def pos(line: int, col: int) -> int:
        # ast columns count UTF-8 bytes
        line_text = text[starts[line - 1]:starts[line]]
        return starts[line - 1] + len(line_text.encode()[:col].decode())

    for ann in _annotations(tree):
        # np.ndarray[...] is already parametrized: not bare
        typed = {id(n.value) for n in ast.walk(ann) if isinstance(n, ast.Subscript)}
        for node in ast.walk(ann):
            if _is_bare_ndarray(node) and id(node) not in typed:
                assert node.end_lineno is not None and node.end_col_offset is not None
                spans.append((pos(node.lineno, node.col_offset), pos(node.end_lineno, node.end_col_offset), ALIAS))
            elif isinstance(node, ast.Constant) and isinstance(node.value, str) and "ndarray" in node.value:
                # a string annotation: parse it and rewrite the string's text
                try:
                    inner = ast.parse(node.value, mode="eval")
                except SyntaxError:
                    continue
                inner_typed = {id(n.value) for n in ast.walk(inner) if isinstance(n, ast.Subscript)}
                if not any(_is_bare_ndarray(n) and id(n) not in inner_typed for n in ast.walk(inner)):
                    continue
                assert node.end_lineno is not None and node.end_col_offset is not None
                s, e = pos(node.lineno, node.col_offset), pos(node.end_lineno, node.end_col_offset)
                literal = text[s:e]  # keeps the quotes as written
                for name in NUMPY_NAMES:
                    if f"{name}.ndarray[" not in literal:
                        literal = literal.replace(f"{name}.ndarray", ALIAS)
                spans.append((s, e, literal))
    return spans


def _with_import(text: str, tree: ast.Module) -> str:
    """Text with ALIAS imported from MODULE (added to an existing import of MODULE if there is one)."""
    for node in tree.body:
        if isinstance(node, ast.ImportFrom) and node.module == MODULE and node.level == 0:
            names = {a.name for a in node.names}
            if ALIAS in names or any(a.asname == ALIAS for a in node.names):
                return text
            lines = text.splitlines(keepends=True)
            assert node.end_lineno is not None
            stmt = f"from {MODULE} import {', '.join(sorted(names | {ALIAS}))}\n"
            return "".join(lines[:node.lineno - 1] + [stmt] + lines[node.end_lineno:])
    # after the last top-level import (ruff's isort then moves it into its group); an import that
    # follows other code (sys.path set-up, environment set before numpy loads) keeps that order
    head = []  # the statements before the first definition (annotations are evaluated from there on)
    for n in tree.body:
        if isinstance(n, (ast.FunctionDef, ast.AsyncFunctionDef, ast.ClassDef)):
            break
        head.append(n)
    imports = [n for n in head if isinstance(n, (ast.Import, ast.ImportFrom))]
    lines = text.splitlines(keepends=True)
    stmt = f"from {MODULE} import {ALIAS}\n"
    if not imports:
        # no import at all: after the docstring
        at = 0
        if tree.body and isinstance(tree.body[0], ast.Expr) and isinstance(tree.body[0].value, ast.Constant):
            at = tree.body[0].end_lineno or 0
        return "".join(lines[:at] + ["\n", stmt] + lines[at:])
    last = imports[-1]
    before = tree.body[:tree.body.index(last)]
    docstring = (before[:1] if before and isinstance(before[0], ast.Expr)
                 and isinstance(before[0].value, ast.Constant) else [])
    if any(not isinstance(n, (ast.Import, ast.ImportFrom)) for n in before if n not in docstring):
        stmt = f"from {MODULE} import {ALIAS}  # noqa: E402\n"
    assert last.end_lineno is not None
    return "".join(lines[:last.end_lineno] + [stmt] + lines[last.end_lineno:])


def rewrite(text: str) -> tuple[str, int]:
    """The text with every bare annotation replaced, and how many were replaced."""
    tree = ast.parse(text)
    spans = _spans(text, tree)
    if not spans:
        return text, 0
    for s, e, r in sorted(spans, reverse=True):
        text = text[:s] + r + text[e:]
    return _with_import(text, ast.parse(text)), len(spans)


def files() -> list[Path]:
    seen: set[Path] = set()
    for pattern in PATTERNS:
        seen.update(p for p in ROOT.glob(pattern) if p.is_file())
    return sorted(seen)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--check", action="store_true", help="change nothing; exit 1 if a bare annotation is left")
    args = parser.parse_args(argv)
    changed: list[Path] = []
    total = 0
    for path in files():
        text = path.read_text()
        new, n = rewrite(text)
        if n:
            total += n
            changed.append(path)
            print(f"{path.relative_to(ROOT)}: {n}")
            if not args.check:
                path.write_text(new)
    print(f"{total} bare np.ndarray annotation(s) in {len(changed)} file(s)"
          + (" left" if args.check else f" replaced with {ALIAS}"))
    if args.check:
        return 1 if total else 0
    if changed:
        ruff = Path(sys.executable).with_name("ruff")
        if ruff.exists():
            # place the new import where isort wants it; nothing else is touched
            subprocess.run([str(ruff), "check", "--fix", "--select", "I001", "--quiet", "--exit-zero",
                            *map(str, changed)], cwd=ROOT, check=False)
        else:
            print("ruff not found beside this Python: run `ruff check --fix --select I001` on the files above")
    return 0


if __name__ == "__main__":
    sys.exit(main())
