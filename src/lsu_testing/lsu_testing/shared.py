"""Expensive test inputs made once per test run and shared by the modules (and pytest-xdist workers) that use them.

A module-scoped fixture is built once per module; two modules that render the same views would render
them twice, on two workers at once. ``shared_result`` keeps a result under a key of its inputs in a
folder of this run only (the run's base temporary folder, which every xdist worker of the run has
under it), so nothing outlives the run: a changed renderer never meets an old result.
"""

from __future__ import annotations

import dataclasses
import fcntl
import hashlib
import os
import pickle
from collections.abc import Callable
from pathlib import Path
from typing import Any, TypeVar

import pytest

__all__ = ["shared_result", "board_pairs"]

T = TypeVar("T")


def _run_dir(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The folder of this test run: under xdist the workers' base folders (``popen-gwN``) share its parent."""
    base = tmp_path_factory.getbasetemp()
    return base.parent if os.environ.get("PYTEST_XDIST_WORKER") else base


def shared_result(tmp_path_factory: pytest.TempPathFactory, name: str, key: Any, build: Callable[[], T]) -> T:
    """``build()``, called once per test run for ``name`` and ``key`` (plain data and numpy arrays: every input
    the result depends on); a second caller, in any worker, waits for the first and loads its result."""
    folder = _run_dir(tmp_path_factory) / "lsu-shared"
    folder.mkdir(exist_ok=True)
    stem = f"{name}-{hashlib.sha256(pickle.dumps(key, protocol=4)).hexdigest()[:20]}"
    path = folder / f"{stem}.pickle"
    with open(folder / f"{stem}.lock", "w") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)  # released when the file closes, also when build() raises
        if path.exists():
            loaded: T = pickle.loads(path.read_bytes())
            return loaded
        value = build()
        tmp = path.with_suffix(".part")
        tmp.write_bytes(pickle.dumps(value, protocol=pickle.HIGHEST_PROTOCOL))
        tmp.replace(path)
        return value


def board_pairs(tmp_path_factory: pytest.TempPathFactory, count: int, seed: int, square_m: float) -> list:
    """``render_board_pairs`` of ``random_board_poses(load_rig(), count, seed)``: (name, left, right) per view,
    rendered once per run. The poses are drawn one after another from ``seed`` and each view's noise is seeded
    by its index, so the first k views of ``count`` are the views of k."""
    from lsu_sim import load_rig
    from lsu_sim.boards import random_board_poses, render_board_pairs

    geometry = load_rig()
    poses = random_board_poses(geometry, count, seed=seed, square_m=square_m)
    key = (dataclasses.asdict(geometry), poses, seed, square_m)  # the rig's fields (cameras, lighting, sensor, ...)
    return shared_result(tmp_path_factory, "board_pairs", key,
                         lambda: render_board_pairs(geometry, poses, seed=seed, square_m=square_m))
