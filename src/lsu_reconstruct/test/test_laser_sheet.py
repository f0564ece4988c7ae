"""Laser sheet calibration: known answers from the simulated rig's geometry (config/sim_rig.yaml)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from lsu_common.arrays import AnyArray
from lsu_extract.extractor import extract_laser_line
from lsu_reconstruct.laser_sheet import LaserSheetError, fit_laser_sheet, read_laser_yaml, write_laser_yaml
from lsu_reconstruct.matching import LineArrays
from lsu_reconstruct.pipeline import reconstruct_snap
from lsu_reconstruct.stereo import StereoModel
from lsu_sim import SimulatedRig, build_scene, load_rig, write_true_calibration

POSITIONS = np.arange(150, 331, 15)


def sheet_line_on_plane(geometry, position: float, plane_n: AnyArray, plane_d: float, heights_m: AnyArray):
    """Exact points where the rig's true sheet at ``position`` crosses the plane ``plane_n . X = plane_d``."""
    n, c = geometry.laser_plane(position)
    direction = np.cross(n, plane_n)
    direction /= np.linalg.norm(direction)
    # a point on both planes: least-norm solution of the 2x3 system
    base = np.linalg.lstsq(np.stack([n, plane_n]), np.array([c, plane_d]), rcond=None)[0]
    # walk along the line so that the points span `heights_m` in y (the sheet is vertical)
    t = (heights_m - base[1]) / direction[1]
    return base + t[:, None] * direction


def synthetic_points(geometry, planes, noise_mm: float, seed: int):
    rng = np.random.default_rng(seed)
    pts, pos = [], []
    for plane_n, plane_d in planes:
        for p in POSITIONS:
            line = sheet_line_on_plane(geometry, float(p), plane_n, plane_d, np.linspace(-0.06, 0.06, 120))
            pts.append(line + rng.normal(0.0, noise_mm / 1000.0, line.shape))
            pos.append(np.full(len(line), float(p)))
    return np.concatenate(pts), np.concatenate(pos)


def plane_at(depth_m: float, tilt_deg: float = 0.0):
    t = np.deg2rad(tilt_deg)
    n = np.array([np.sin(t), 0.0, np.cos(t)])
    return n, depth_m * n[2]


def assert_matches_truth(sheet, geometry, angle_deg: float, offset_mm: float) -> None:
    n_true = geometry.laser_normal
    n = np.asarray(sheet.normal)
    assert np.degrees(np.arccos(min(1.0, abs(float(n @ n_true))))) < angle_deg
    for p in (POSITIONS[0], POSITIONS[-1]):
        # the two planes compared where the scans were: along the sheet, at the targets' depths
        n_fit, c_fit = sheet.plane(float(p))
        probe = geometry.laser_origin(float(p)) + 0.3 * geometry.rig_axes[2]
        assert abs(float(n_fit @ probe) - c_fit) * 1000.0 < offset_mm


def test_two_boards_at_two_distances_give_the_rigs_sheet():
    geometry = load_rig()
    points, positions = synthetic_points(geometry, [plane_at(0.26, 10.0), plane_at(0.34, -15.0)], 0.05, seed=1)
    sheet = fit_laser_sheet(points, positions)
    assert_matches_truth(sheet, geometry, angle_deg=0.05, offset_mm=0.02)
    # the step size along the normal is the track's step (1/60 inch) times the sheet's cosine to the track
    assert sheet.m_per_step == pytest.approx(geometry.step_m * abs(float(geometry.laser_normal @ geometry.rig_axes[0])),
                                             rel=1e-3)
    assert sheet.residual_mm == pytest.approx(0.05, rel=0.2)  # the points' own noise
    assert sheet.positions == (150, 330) and sheet.rejected < 0.01 * len(points)


def test_stray_points_are_trimmed():
    geometry = load_rig()
    points, positions = synthetic_points(geometry, [plane_at(0.26), plane_at(0.34, 20.0)], 0.05, seed=2)
    rng = np.random.default_rng(3)
    bad = rng.choice(len(points), len(points) // 20, replace=False)
    points[bad] += rng.normal(0.0, 0.01, (len(bad), 3))  # 5 % mismatches, ~10 mm off
    sheet = fit_laser_sheet(points, positions)
    assert_matches_truth(sheet, geometry, angle_deg=0.05, offset_mm=0.03)
    assert sheet.rejected >= 0.8 * len(bad)


def test_a_single_flat_board_is_refused_with_what_to_scan():
    geometry = load_rig()
    points, positions = synthetic_points(geometry, [plane_at(0.30)], 0.05, seed=4)
    with pytest.raises(LaserSheetError, match="two or more distances"):
        fit_laser_sheet(points, positions)


def test_points_of_one_position_are_refused():
    geometry = load_rig()
    points, _ = synthetic_points(geometry, [plane_at(0.26), plane_at(0.34, 20.0)], 0.05, seed=5)
    with pytest.raises(LaserSheetError, match="several positions"):
        fit_laser_sheet(points, np.full(len(points), 200.0))


def test_laser_yaml_round_trip_and_a_broken_file_named(tmp_path):
    geometry = load_rig()
    sheet = fit_laser_sheet(*synthetic_points(geometry, [plane_at(0.26), plane_at(0.34, 20.0)], 0.05, seed=6))
    path = write_laser_yaml(sheet, tmp_path / "laser.yaml")
    assert path.stat().st_mode & 0o777 == 0o644
    again = read_laser_yaml(path)
    assert np.allclose(again.normal, sheet.normal, atol=1e-8) and again.c0_m == pytest.approx(sheet.c0_m, abs=1e-9)
    (tmp_path / "bad.yaml").write_text("normal: [1, 2]\n")
    with pytest.raises(LaserSheetError, match="bad.yaml"):
        read_laser_yaml(tmp_path / "bad.yaml")


def test_rays_through_the_sheet_land_on_the_true_line():
    geometry = load_rig()
    sheet = fit_laser_sheet(*synthetic_points(geometry, [plane_at(0.26), plane_at(0.34, 20.0)], 0.0, seed=7))
    plane = plane_at(0.30)
    truth = sheet_line_on_plane(geometry, 240.0, *plane, np.linspace(-0.05, 0.05, 11))
    rays = truth / np.linalg.norm(truth, axis=1, keepdims=True)  # left camera rays through the true points
    hit = sheet.intersect_rays(np.zeros(3), rays, 240.0)
    assert np.abs(hit - truth).max() * 1000.0 < 1e-3


def test_rendered_scans_of_two_planes_calibrate_the_sheet(tmp_path: Path):
    """End to end on rendered frames: rig -> extractor -> stereo matcher -> fit, against the rig's geometry."""
    geometry = load_rig()
    write_true_calibration(geometry, tmp_path)
    model = StereoModel.from_folder(tmp_path)
    points, positions = [], []
    for distance in (0.26, 0.34):
        rig = SimulatedRig(geometry, build_scene("plane", geometry, distance_m=distance), seed=11)
        for p in POSITIONS[::2]:
            frame = rig.render(float(p), seed=int(p))
            lines = []
            for image in (frame.left, frame.right):
                res = extract_laser_line(image)
                lines.append(LineArrays(res.u, res.v, image_width=image.shape[1], image_height=image.shape[0]))
            snap = reconstruct_snap(model, lines[0], lines[1], snap=int(p))
            points.append(snap.xyz)
            positions.append(np.full(len(snap.xyz), float(p)))
    sheet = fit_laser_sheet(np.concatenate(points), np.concatenate(positions))
    # the rendered sheet has a thickness and the points carry the rig's noise: looser than the analytic case
    assert_matches_truth(sheet, geometry, angle_deg=0.2, offset_mm=0.2)
    assert sheet.residual_mm < 0.3


def test_uncertainty_weighting_follows_the_clean_rows():
    # a third of the rows (say the far, speckled ones) are 6x noisier than the rest, and say so: weighting by
    # each point's own sigma puts the sheet nearer the truth than the unweighted fit, and nothing clean is trimmed
    geometry = load_rig()
    points, positions = synthetic_points(geometry, [plane_at(0.26, 10.0), plane_at(0.34, -15.0)], 0.0, seed=8)
    rng = np.random.default_rng(9)
    sigma = np.where(rng.random(len(points)) < 1.0 / 3.0, 0.30e-3, 0.05e-3)
    n_true = geometry.laser_normal
    noisy = points + rng.normal(0.0, 1.0, (len(points), 1)) * sigma[:, None] * n_true[None, :]
    plain = fit_laser_sheet(noisy, positions)
    weighted = fit_laser_sheet(noisy, positions, sigma_m=sigma)

    def error_mm(sheet) -> float:
        return float(np.sqrt(np.mean(sheet.distance_m(points, positions) ** 2)) * 1000.0)

    assert error_mm(weighted) < 0.8 * error_mm(plain)
    # the plain fit trims noisy rows for the noise they were expected to have; the weighted one keeps them
    assert weighted.rejected <= 0.01 * len(points) < plain.rejected
    with pytest.raises(LaserSheetError, match="positive"):
        fit_laser_sheet(noisy, positions, sigma_m=np.zeros(len(points)))
