"""Tests of the accuracy study (`lsu_accuracy.accuracy`, `lsu accuracy`).

Ground truth: analytic geometry (planes, normal and uniform distributions, straight lines) and the
renderer's scene (the board's true plane). One small study (3 poses, coarse carriage step) runs
in-process through the `lsu` command and is shared by the end-to-end tests.
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest

from lsu_accuracy import accuracy as A
from lsu_tools.cli import main as lsu_main


# ---------------------------------------------------------------- pure helpers
def test_gaussian_table_of_normal_samples_matches_the_normal_fractions():
    rng = np.random.default_rng(1)
    got = A.gaussian_table(rng.normal(3.0, 0.2, 200_000))
    for pct, expected in zip(got, (68.27, 95.45, 99.73)):
        assert abs(pct - expected) < 0.4


def test_gaussian_table_of_uniform_samples_differs_from_normal():
    # uniform on [-1, 1]: sigma = 1/sqrt(3), so 1 sigma holds 57.7 % and 2 sigma holds everything
    rng = np.random.default_rng(2)
    one, two, three = A.gaussian_table(rng.uniform(-1.0, 1.0, 200_000))
    assert abs(one - 100.0 / math.sqrt(3.0)) < 0.5
    assert two == 100.0 and three == 100.0


def test_fit_plane_recovers_a_known_plane():
    rng = np.random.default_rng(3)
    n = np.array([0.2, -0.1, -1.0]) / np.linalg.norm([0.2, -0.1, -1.0])
    a = np.cross(n, [0.0, 1.0, 0.0])
    a /= np.linalg.norm(a)
    b = np.cross(n, a)
    p0 = np.array([0.01, 0.02, 0.3])
    st = rng.uniform(-0.05, 0.05, (5000, 2))
    pts = p0 + st[:, :1] * a + st[:, 1:] * b + rng.normal(0, 1e-5, (5000, 1)) * n
    c, nf = A.fit_plane(pts)
    assert abs(abs(float(nf @ n)) - 1.0) < 1e-6
    assert abs(float((c - p0) @ n)) < 1e-6
    d = A.plane_distances_mm(pts, p0, n)
    assert abs(d.std() - 0.01) < 0.001  # 1e-5 m noise = 0.01 mm


def test_linear_fit_and_error_stats_are_exact_on_analytic_data():
    slope, icpt = A.linear_fit([200, 300, 400], [0.1, 0.2, 0.3])
    assert slope == pytest.approx(0.001) and icpt == pytest.approx(-0.1)
    s = A.error_stats(np.array([-1.0, 1.0, -1.0, 1.0]) + 0.5)
    assert s["sigma_mm"] == pytest.approx(1.0) and s["mean_mm"] == pytest.approx(0.5)
    assert s["bound_mm"] == pytest.approx(3.5) and s["three_sigma_mm"] == pytest.approx(3.0)
    with pytest.raises(A.AccuracyError):
        A.linear_fit([300, 300], [1, 2])
    with pytest.raises(A.AccuracyError, match="no points"):
        A.error_stats(np.zeros(0))


def test_default_poses_span_the_range_and_include_300_mm_facing():
    poses = A.default_poses(10)
    d = [p.distance_m for p in poses]
    assert min(d) == pytest.approx(0.20) and max(d) == pytest.approx(0.45)
    assert any(p.distance_m == 0.30 and p.yaw_deg == 0 and p.pitch_deg == 0 for p in poses)
    assert len({(p.yaw_deg, p.pitch_deg) for p in poses}) >= 5  # tilts vary


def test_board_pose_normal_is_tilted_by_the_pose_angles():
    from lsu_sim import load_rig

    g = load_rig()
    z = g.rig_axes[2]
    board = A.plane_pose_object(g, A.Pose(0.35, yaw_deg=20.0))
    n = board.extra["normal"]
    assert math.degrees(math.acos(float(n @ -z))) == pytest.approx(20.0, abs=1e-6)
    assert float((board.extra["point"] - g.rig_center) @ z) == pytest.approx(0.35)


# ---------------------------------------------------------------- end to end
@pytest.fixture(scope="module")
def small_study(tmp_path_factory):
    out = tmp_path_factory.mktemp("accuracy")
    rc = lsu_main(["accuracy", "--sim", "-o", str(out), "--poses", "3", "--step", "40"])
    assert rc == 0
    return out, json.loads((out / "accuracy.json").read_text())


def test_report_files_exist(small_study):
    out, _ = small_study
    text = (out / "report.md").read_text()
    assert "Gaussian table" in text and "thesis chain" in text and "Smoothing study" in text
    for name in ("gaussian_table.png", "error_vs_distance.png", "smoothing.png"):
        data = (out / name).read_bytes()
        assert data[:8] == b"\x89PNG\r\n\x1a\n" and len(data) > 5000


def test_every_pose_ours_beats_the_thesis_chain(small_study):
    _, r = small_study
    assert len(r["poses"]) == 3
    for pose in r["poses"]:
        assert pose["ours"]["raw"]["points"] > 1000 and pose["thesis"]["raw"]["points"] > 1000
        assert pose["ours"]["raw"]["sigma_mm"] < pose["thesis"]["raw"]["sigma_mm"]
        assert pose["ours"]["smoothed"]["bound_mm"] < pose["thesis"]["smoothed"]["bound_mm"]
        # the free fit absorbs bias and tilt error, so it can only be as tight as the true-plane spread
        assert pose["ours"]["free_fit"]["sigma_mm"] <= pose["ours"]["raw"]["rms_mm"] + 1e-9
    f = r["figures"]
    assert f["three_sigma_mm_300_smoothed"] < f["thesis_three_sigma_mm_300"]
    # The renders carry laser speckle: one point cannot beat the speckle limit (about 0.10 mm at 300 mm,
    # f/2), so the clean rig's 0.15 mm target for |bias| + 3 sigma is out of reach and not asserted.
    # What physics allows: smoothing helps, and the raw sigma sits within the goal of 1.5 x
    # the optics' limit and above what averaging independent rows can take from speckle: the
    # renderer's lens blur (limit with it / without: 0.73) times the matcher's row smoothing (a
    # quadratic fit over 9 rows keeps 0.255 of the variance of independent rows, std 0.505): 0.37.
    assert f["three_sigma_mm_300_smoothed"] < f["three_sigma_mm_300_raw"]
    assert 0.37 <= f["plane_sigma_over_speckle_limit"] <= 1.5
    assert f["speckle_limit_mm_300_with_lens_blur"] == pytest.approx(0.727 * f["speckle_limit_mm_300"], rel=0.01)


def test_speckle_limit_is_reported_beside_the_measured_sigma(small_study):
    import yaml

    from lsu_cameras.paths import config_dir
    from lsu_reconstruct.speckle import speckle_limit

    out, r = small_study
    f = r["figures"]
    # the closed form from the YAML's own numbers (not through the study's code)
    rig = yaml.safe_load((config_dir() / "sim_rig.yaml").read_text())
    lim = speckle_limit(rig["laser"]["wavelength_nm"], rig["sensor"]["f_number"], rig["left"]["camera_matrix"][0],
                        rig["sensor"]["pixel_size_m"], float(np.linalg.norm(rig["stereo"]["translation_m"])), 0.30,
                        rig["laser"]["sheet_fwhm_m"] / (2 * math.sqrt(2 * math.log(2))), rig["speckle"]["contrast"])
    assert f["speckle_limit_mm_300"] == pytest.approx(lim.depth_mm, rel=1e-9)
    assert f["speckle_limit_px"] == pytest.approx(lim.line_px, rel=1e-9)
    assert f["plane_sigma_over_speckle_limit"] == pytest.approx(f["plane_sigma_mm_300"] / lim.depth_mm, rel=1e-9)
    text = (out / "report.md").read_text()
    assert "## Speckle limit (300 mm)" in text and f"{f['plane_sigma_over_speckle_limit']:.2f}" in text


def test_gaussian_fractions_are_sensible(small_study):
    _, r = small_study
    for chain in ("ours", "thesis"):
        one, two, three = r["gaussian"][chain]
        assert 0 < one < two <= three <= 100
        assert three > 95.0
    f = r["figures"]
    assert abs(f["gaussian_1sigma_pct"] - 68.2) < 6 and abs(f["gaussian_2sigma_pct"] - 95.4) < 4


def test_error_grows_with_distance_and_smoothing_trades_noise_for_shape(small_study):
    _, r = small_study
    assert r["trends"]["ours_raw_sigma_mm"]["slope_per_mm"] > 0
    assert r["trends"]["thesis_raw_sigma_mm"]["slope_per_mm"] > 0
    board = {row["label"]: row for row in r["smoothing"]["plane_300"]["thesis"]}
    curved = {row["label"]: row for row in r["smoothing"]["curved"]["ours"]}
    # heavy Laplacian smoothing removes noise from a flat board but shrinks the curved truth
    assert board["laplacian 100 x 1"]["sigma_mm"] < board["none"]["sigma_mm"]
    assert curved["laplacian 100 x 1"]["rms_mm"] > curved["none"]["rms_mm"]


def test_bad_arguments_fail_with_a_clear_message(tmp_path, capsys):
    assert lsu_main(["accuracy", "--sim", "-o", str(tmp_path), "--poses", "2"]) == 2
    assert "--poses must be >= 3" in capsys.readouterr().err
    assert lsu_main(["accuracy", "--bag", str(tmp_path), "-o", str(tmp_path)]) == 2
    assert "no rosbag2 folder (metadata.yaml)" in capsys.readouterr().err
    assert lsu_main(["accuracy", "--bag", str(tmp_path / "nowhere"), "-o", str(tmp_path)]) == 2
    assert "no such folder" in capsys.readouterr().err
    assert not (tmp_path / "report.md").exists()


# ---------------------------------------------------------------- recorded board scans (--bag)
SQUARE_M = 0.02
BOARD_POSES = (A.Pose(0.26), A.Pose(0.30), A.Pose(0.35, yaw_deg=15.0, pitch_deg=-10.0))


@pytest.fixture(scope="module")
def board_bags(tmp_path_factory):
    """One scan bag per board pose, written from the simulated rig; the renderer's boards are the truth."""
    from lsu_sim import load_rig
    from lsu_testing.simbags import write_board_scan_bags

    root = tmp_path_factory.mktemp("board_scans")
    geometry = load_rig()
    write_board_scan_bags(root, BOARD_POSES, SQUARE_M, step=10, seed=100, geometry=geometry)
    return root, [A.board_pose_object(geometry, pose, SQUARE_M) for pose in BOARD_POSES]


def test_board_plane_detected_in_the_laser_off_pair_matches_the_renderer(board_bags):
    from lsu_accuracy.accuracy_bag import detect_board_plane, find_bags, read_board_scans
    from lsu_cameras.calibration import BoardSpec
    from lsu_reconstruct.stereo import StereoModel

    root, boards = board_bags
    model = StereoModel.from_folder(Path(A.__file__).resolve().parents[3] / "config" / "calibration" / "sim")
    bags = find_bags(root)
    assert [b.parent.name for b in bags] == ["pose0", "pose1", "pose2"]
    for bag, board in zip(bags, boards):
        (scan,) = list(read_board_scans(bag))
        assert scan.name == bag.parent.name and len(scan.snaps) == 48
        plane = detect_board_plane(scan.texture, model, BoardSpec(9, 6, SQUARE_M), scan.name)
        true_n = board.extra["pose_R"][:, 2]
        assert math.degrees(math.acos(min(1.0, abs(float(plane.normal @ true_n))))) < 0.1
        # the detected centre lies on the rendered board plane, and the board frame's origin is its first corner
        assert abs(float((plane.center - board.extra["pose_t"]) @ true_n)) * 1000 < 0.05
        assert np.linalg.norm(plane.t - board.extra["pose_t"]) * 1000 < 0.5
        assert plane.reprojection_px < 0.2
        assert plane.stereo_offset_mm is None or plane.stereo_offset_mm < 0.1


@pytest.fixture(scope="module")
def board_study(board_bags, tmp_path_factory):
    """One study over the board bags plus an unusable scan (a head recorded by the graph: images and
    events, no board in view), shared by the end-to-end test and the skipped-scan test: the usable
    poses' figures are those of the boards alone, and one run of the study costs as much as the bags."""
    import contextlib
    import io
    import shutil

    root, _ = board_bags
    mixed = tmp_path_factory.mktemp("board_study") / "scans"
    shutil.copytree(root, mixed)
    shutil.copytree(Path(__file__).resolve().parents[3] / "test" / "data" / "bags" / "scan_head", mixed / "head" / "bag")
    out = mixed.parent / "report"
    stdout = io.StringIO()
    with contextlib.redirect_stdout(stdout):
        rc = lsu_main(["accuracy", "--bag", str(mixed), "--square", "20", "-o", str(out)])
    assert rc == 0
    return out, json.loads((out / "accuracy.json").read_text()), stdout.getvalue()


def test_accuracy_from_board_bags_end_to_end(board_study):
    out, r, printed = board_study
    assert r["source"] == "bag" and len(r["poses"]) == 3
    text = (out / "report.md").read_text()
    assert "recorded board scans" in text and "Truth (the detected board)" in text and "curved RMS" not in text
    for name in ("gaussian_table.png", "error_vs_distance.png", "smoothing.png"):
        assert (out / name).read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    for pose in r["poses"]:
        # only points over the board count, and both chains see the same recorded pairs
        assert pose["ours"]["raw"]["points"] > 3000
        assert pose["ours"]["raw"]["sigma_mm"] < pose["thesis"]["raw"]["sigma_mm"] / 3
        assert abs(pose["ours"]["raw"]["mean_mm"]) < 0.05  # no bias against the detected board
    f = r["figures"]
    assert 280 < f["reference_distance_mm"] < 330
    assert f["three_sigma_mm_300_smoothed"] < f["thesis_three_sigma_mm_300"]
    # the bags carry laser speckle: the raw sigma at the reference pose within 1.5 x the rig's speckle
    # limit at that distance (the 0.15 mm target of the clean rig is below what speckle allows)
    from lsu_sim import load_rig

    limit = A.rig_speckle_limit(load_rig(), f["reference_distance_mm"] / 1000.0)["depth_mm"]
    reference = next(p for p in r["poses"] if p["label"] == r["reference_pose"])
    assert reference["ours"]["raw"]["sigma_mm"] <= 1.5 * limit
    assert r["trends"]["thesis_raw_sigma_mm"]["slope_per_mm"] > 0
    assert "thesis chain" in printed


def test_board_bag_without_images_or_board_fails_clearly(tmp_path, capsys):
    from lsu_bags.bags import BagWriter
    from lsu_sim import build_scene, load_rig
    from lsu_testing.simbags import EVENTS_TOPIC, write_sim_scan_bag

    with BagWriter(tmp_path / "events_only" / "bag") as bag:
        bag.add_topic(EVENTS_TOPIC, "lsu_interfaces/msg/ScanEvent")
    assert lsu_main(["accuracy", "--bag", str(tmp_path / "events_only"), "-o", str(tmp_path / "r1")]) == 2
    err = capsys.readouterr().err
    assert "has no stereo/left/image_raw, stereo/right/image_raw" in err and "lsu scan --record" in err
    geometry = load_rig()
    write_sim_scan_bag(tmp_path / "plain" / "bag", build_scene("plane", geometry), [230, 240], seed=3,
                       scan_id="plain", geometry=geometry)
    assert lsu_main(["accuracy", "--bag", str(tmp_path / "plain"), "-o", str(tmp_path / "r2")]) == 2
    assert "no 9x6 chessboard found in the laser-off left image" in capsys.readouterr().err
    write_sim_scan_bag(tmp_path / "dark" / "bag", build_scene("plane", geometry), [230], seed=4, scan_id="dark",
                       geometry=geometry, texture=False)
    assert lsu_main(["accuracy", "--bag", str(tmp_path / "dark"), "-o", str(tmp_path / "r3")]) == 2
    assert "no laser-off (TEXTURE) pair" in capsys.readouterr().err
    assert not any((tmp_path / r).exists() for r in ("r1", "r2", "r3"))


def test_an_unusable_scan_among_good_ones_is_skipped_and_reported(board_study):
    out, r, _ = board_study
    assert len(r["poses"]) == 3 and len(r["skipped"]) == 1 and "no 9x6 chessboard found" in r["skipped"][0]
    assert "Scans left out of every figure" in (out / "report.md").read_text()


def test_a_scan_recorded_by_the_graph_reads_as_a_board_scan(tmp_path, capsys):
    """The committed bag was recorded by scan_coordinator (a head, no board): the reader takes its
    events and images as they are; the study then stops at the board detection, saying so."""
    from lsu_accuracy.accuracy_bag import read_board_scans

    bag = Path(__file__).resolve().parents[3] / "test" / "data" / "bags" / "scan_head"
    (scan,) = list(read_board_scans(bag))
    assert len(scan.snaps) == 6 and [s[0] for s in scan.snaps] == list(range(6))
    assert scan.texture[0].shape == (480, 640, 3) and scan.texture[1].shape == (480, 640, 3)
    # laser off in the texture pair, on in the snaps: the red excess tells them apart
    red = [float((img[..., 2].astype(int) - img[..., :2].max(axis=2)).clip(0).max()) for img in (scan.texture[0],
                                                                                             scan.snaps[0][1])]
    assert red[1] > red[0] + 50
    assert lsu_main(["accuracy", "--bag", str(bag), "-o", str(tmp_path / "r")]) == 2
    assert "no 9x6 chessboard found" in capsys.readouterr().err
