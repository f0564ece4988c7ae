"""Calibration board views for the simulated rig: seeded random poses seen whole by both cameras."""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
from scipy.spatial.transform import Rotation

from lsu_common.arrays import AnyArray

from .geometry import RigGeometry
from .rig import CarriageState, SimulatedRig
from .scenes import make_board


def random_board_poses(geometry: RigGeometry, count: int, seed: int, inner_corners: tuple[int, int] = (9, 6),
                       square_m: float = 0.020, distance_m: tuple[float, float] = (0.33, 0.50),
                       max_tilt_deg: float = 35.0, border_px: float = 12.0) -> list[tuple[AnyArray, AnyArray]]:
    """``count`` board poses (R, t of the first corner, left frame) varied like a careful calibration session.

    Tilts up to ``max_tilt_deg`` about both board axes (needed to separate focal length from
    distance), distances in ``distance_m``, the board shifted around the field; every pose keeps
    the whole board (corners + one square of margin) ``border_px`` inside both images.
    """
    rng = np.random.default_rng(seed)
    cols, rows = inner_corners
    axes = geometry.rig_axes
    W, H = geometry.image_size
    j, i = np.mgrid[-1:rows + 1, -1:cols + 1]
    outline = np.stack([i.ravel(), j.ravel(), np.zeros(i.size)], axis=1) * square_m
    poses: list[tuple[AnyArray, AnyArray]] = []
    for _ in range(200 * count):
        if len(poses) == count:
            break
        d = rng.uniform(*distance_m)
        tilt = Rotation.from_euler("xyz", [rng.uniform(-max_tilt_deg, max_tilt_deg),
                                           rng.uniform(-max_tilt_deg, max_tilt_deg), rng.uniform(-12, 12)],
                                   degrees=True).as_matrix()
        R = axes.T @ tilt
        center = geometry.rig_center + d * axes[2] + rng.uniform(-0.05, 0.05) * axes[0] + rng.uniform(-0.035, 0.035) * axes[1]
        t = center - R @ np.array([(cols - 1) / 2 * square_m, (rows - 1) / 2 * square_m, 0.0])
        pts = outline @ R.T + t
        inside = True
        for cam in (geometry.left, geometry.right):
            px = cam.project(pts)
            inside &= bool(np.all((px[:, 0] > border_px) & (px[:, 0] < W - border_px)
                                  & (px[:, 1] > border_px) & (px[:, 1] < H - border_px)))
        if inside:
            poses.append((R, t))
    if len(poses) < count:
        raise ValueError(f"found only {len(poses)} board poses visible in both cameras; use a smaller board")
    return poses


def render_board_pairs(geometry: RigGeometry, poses: Sequence[tuple[AnyArray, AnyArray]], seed: int,
                       inner_corners: tuple[int, int] = (9, 6),
                       square_m: float = 0.020) -> list[tuple[str, AnyArray, AnyArray]]:
    """Render each pose (laser off) as ``(name, left, right)``, noise seeded per view."""
    out = []
    rig = None
    for k, (R, t) in enumerate(poses):
        scene = [make_board(R, t, inner_corners, square_m)]
        if rig is None:
            rig = SimulatedRig(geometry, scene, seed=seed)
        else:
            rig.set_scene(scene)
        frame = rig.render(CarriageState(0.0, laser_on=False), seed=seed * 1000 + k)
        out.append((f"{k:03d}", frame.left, frame.right))
    return out
