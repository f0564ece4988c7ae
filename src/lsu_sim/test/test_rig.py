"""The simulated rig: exact ground truth, physically plausible images, deterministic synthetic heads."""


import cv2
import numpy as np
import pytest
import yaml
from scipy.spatial.transform import Rotation

from lsu_cameras.calib_io import read_calibration_dir
from lsu_cameras.paths import config_dir
from lsu_common.arrays import AnyArray
from lsu_sim import (
    CarriageState,
    SceneError,
    SimulatedRig,
    build_scene,
    load_rig,
    make_head,
    make_plane,
    write_true_calibration,
)

RIG_YAML = config_dir() / "sim_rig.yaml"


@pytest.fixture(scope="module")
def rig_numbers():
    """The rig as plain numbers straight from the YAML (independent of the code under test)."""
    data = yaml.safe_load(RIG_YAML.read_text())
    R, _ = cv2.Rodrigues(np.array(data["stereo"]["rotation_vector"], dtype=float))
    return {
        "K_l": np.array(data["left"]["camera_matrix"]).reshape(3, 3),
        "D_l": np.array(data["left"]["distortion_coefficients"]),
        "K_r": np.array(data["right"]["camera_matrix"]).reshape(3, 3),
        "D_r": np.array(data["right"]["distortion_coefficients"]),
        "R": R, "T": np.array(data["stereo"]["translation_m"]),
        "step_m": data["track"]["step_m"], "center_step": data["track"]["center_step"],
    }


@pytest.fixture(scope="module")
def plane_rig():
    geometry = load_rig()
    return SimulatedRig(geometry, [make_plane((0.0, 0.0, 0.30), (0.0, 0.0, -1.0))], seed=7)


def laser_centroids(image: AnyArray, columns: AnyArray, rows: AnyArray, half: int = 7):
    """Red-minus-background centroid and second-moment width around the given columns (test's own estimator)."""
    red = image[:, :, 2].astype(float)
    out_c, out_w = [], []
    for r, c in zip(rows, columns):
        lo = int(round(c)) - half
        window = red[r, lo:lo + 2 * half + 1]
        w = np.clip(window - np.median(red[r]) - 6.0, 0.0, None)
        u = np.arange(lo, lo + 2 * half + 1)
        m = w.sum()
        out_c.append((w * u).sum() / m if m > 0 else np.nan)
        out_w.append(np.sqrt((w * (u - out_c[-1]) ** 2).sum() / m) if m > 0 else np.nan)
    return np.array(out_c), np.array(out_w)


def test_plane_ground_truth_lies_on_both_planes(plane_rig, rig_numbers):
    position = 180.0
    truth = plane_rig.laser_truth(position)
    R, T = rig_numbers["R"], rig_numbers["T"]
    c_right = -R.T @ T
    baseline_dir = c_right / np.linalg.norm(c_right)
    laser_origin = c_right / 2 + (position - rig_numbers["center_step"]) * rig_numbers["step_m"] * baseline_dir
    for cam in (truth.left, truth.right):
        assert len(cam.points_m) > 400  # one sample per image row, nearly all rows see the plane
        assert np.abs(cam.points_m[:, 2] - 0.30).max() < 1e-6
        assert np.abs((cam.points_m - laser_origin) @ baseline_dir).max() < 1e-6


def test_plane_ground_truth_reprojects_to_its_pixels(plane_rig, rig_numbers):
    truth = plane_rig.laser_truth(300.0)
    n = rig_numbers
    left, _ = cv2.projectPoints(truth.left.points_m, np.zeros(3), np.zeros(3), n["K_l"], n["D_l"])
    right, _ = cv2.projectPoints(truth.left.points_m, cv2.Rodrigues(n["R"])[0], n["T"], n["K_r"], n["D_r"])
    assert np.abs(left.reshape(-1, 2) - truth.left.pixels).max() < 1e-3
    assert np.abs(right.reshape(-1, 2) - truth.left.other_pixels).max() < 1e-3
    # one sample per image row: the row coordinate is an integer
    for cam in (truth.left, truth.right):
        assert np.abs(cam.pixels[:, 1] - np.round(cam.pixels[:, 1])).max() < 1e-3
    assert truth.left.other_visible.mean() > 0.9


def test_rendered_laser_line_is_centred_on_the_ground_truth(plane_rig):
    frame = plane_rig.render(235.0, with_truth=True, seed=3)
    for image, cam in ((frame.left, frame.truth.left), (frame.right, frame.truth.right)):
        rows = np.round(cam.pixels[:, 1]).astype(int)
        centres, widths = laser_centroids(image, cam.pixels[:, 0], rows)
        err = centres - cam.pixels[:, 0]
        assert abs(np.nanmean(err)) < 0.05 and np.nanstd(err) < 0.15
        assert 0.6 < np.nanmedian(widths) < 2.5  # a ~1 mm sheet is a few pixels wide at 0.3 m
        # 671 nm: the line is red, the green channel barely sees it
        r, c = rows[len(rows) // 2], int(round(cam.pixels[len(rows) // 2, 0]))
        assert int(image[r, c, 2]) - int(image[r, c + 12, 2]) > 80
        assert int(image[r, c, 1]) - int(image[r, c + 12, 1]) < 25


def test_capture_5ms_after_stop_is_blurred_and_shifted_vs_settled(plane_rig):
    state = CarriageState(235.0, stopped_at_s=10.0, vibration_amplitude_steps=3.0, vibration_tau_s=0.06,
                          vibration_freq_hz=25.0)
    truth = plane_rig.laser_truth(235.0).left
    rows = np.round(truth.pixels[:, 1]).astype(int)[::8]
    cols = truth.pixels[::8, 0]
    shaky = plane_rig.render(state, capture_time_s=10.005, seed=1)
    settled = plane_rig.render(state, capture_time_s=10.600, seed=1)
    c_shaky, w_shaky = laser_centroids(shaky.left, cols, rows, half=9)
    c_settled, w_settled = laser_centroids(settled.left, cols, rows, half=9)
    assert np.nanmean(np.abs(c_settled - cols)) < 0.1
    assert np.nanmean(np.abs(c_shaky - cols)) > 0.5                 # shifted
    assert np.nanmedian(w_shaky) > 1.3 * np.nanmedian(w_settled)     # widened
    assert abs(shaky.laser_offset_steps) > 0.2 and abs(settled.laser_offset_steps) < 1e-3


def test_laser_off_shows_no_line_and_noise_is_seeded(plane_rig):
    truth = plane_rig.laser_truth(235.0).left
    r, c = int(round(truth.pixels[200, 1])), int(round(truth.pixels[200, 0]))
    off = plane_rig.render(CarriageState(235.0, laser_on=False), seed=5)
    assert abs(int(off.left[r, c, 2]) - int(off.left[r, c + 15, 2])) < 20
    again = plane_rig.render(CarriageState(235.0, laser_on=False), seed=5)
    other = plane_rig.render(CarriageState(235.0, laser_on=False), seed=6)
    assert np.array_equal(off.left, again.left)
    assert not np.array_equal(off.left, other.left)
    assert off.left.dtype == np.uint8 and off.left.shape == (480, 640, 3)


def test_serial_and_parallel_renders_give_the_same_images():
    # each view has its own generator, so the images do not depend on the threads they were rendered on
    geometry = load_rig()
    rig = SimulatedRig(geometry, build_scene("head:7", geometry), seed=2)
    moving = CarriageState(180.0, velocity_steps_per_s=180.0, position_time_s=1.0)
    for state, t in ((moving, 1.004), (CarriageState(260.0), None)):
        a = rig.render(state, capture_time_s=t, seed=9, parallel=True)
        b = rig.render(state, capture_time_s=t, seed=9, parallel=False)
        assert np.array_equal(a.left, b.left) and np.array_equal(a.right, b.right)
        assert a.left[:, :, 2].max() > 150  # the line is there


def test_laser_band_candidates_are_every_pixel_within_its_reach_of_the_sheet():
    # the render reads the laser's pixels from a table binned by n . P; brute force over the whole image
    # (every pixel that hits, its n . P and reach from the view's per-pixel arrays) must give the same set
    geometry = load_rig()
    rig = SimulatedRig(geometry, build_scene("head:7", geometry), seed=2)
    for view in rig._views:
        pn, reach = view.pn, view.reach
        centre = float(np.nanmedian(pn))
        for lo, hi in ((centre, centre), (centre - 7e-4, centre + 8e-4), (centre + 0.01, centre + 0.0103)):
            chosen = np.sort(view.band_order[rig._band_candidates(view, lo, hi)])
            with np.errstate(invalid="ignore"):
                brute = np.flatnonzero(view.hit & (pn > lo - reach) & (pn < hi + reach))
            assert len(brute) > 1000
            assert np.array_equal(chosen, brute)


def test_bright_laser_saturates_at_255():
    geometry = load_rig()
    geometry.laser.power = 5.0
    rig = SimulatedRig(geometry, [make_plane((0.0, 0.0, 0.30), (0.0, 0.0, -1.0))], seed=1)
    frame = rig.render(235.0, seed=1)
    assert frame.left[:, :, 2].max() == 255
    assert (frame.left[:, :, 2] == 255).sum() > 400   # the line's core is clipped, not wrapped


def test_head_generator_is_deterministic_and_identities_differ():
    a, b, c = make_head(3), make_head(3), make_head(4)
    va, vb, vc = (np.asarray(h.mesh.vertices) for h in (a, b, c))
    assert np.array_equal(va, vb) and np.array_equal(a.nose_tip_m, b.nose_tip_m)
    assert np.abs(va - vc).max() > 2e-3
    # the nose tip is the frontal head's most prominent point (towards the camera, -z)
    front = va[np.abs(va[:, 0]) < 0.03]
    assert a.nose_tip_m[2] == pytest.approx(front[:, 2].min())
    # closed surface: every edge is shared by exactly two triangles
    tris = np.asarray(a.mesh.triangles)
    edges = np.sort(np.concatenate([tris[:, [0, 1]], tris[:, [1, 2]], tris[:, [2, 0]]]), axis=1)
    _, counts = np.unique(edges, axis=0, return_counts=True)
    assert np.all(counts == 2)


def test_head_pose_rotates_the_nose_tip_about_the_head_centre():
    frontal = make_head(11)
    turned = make_head(11, yaw_deg=30.0, pitch_deg=-10.0)
    expected = Rotation.from_euler("xy", [-10.0, 30.0], degrees=True).apply(frontal.nose_tip_m)
    assert np.allclose(turned.nose_tip_m, expected, atol=1e-12)
    assert turned.nose_tip_m[0] < -0.02  # positive yaw turns the face towards -x


def test_committed_sim_calibration_is_the_rigs_truth(tmp_path, rig_numbers):
    committed = read_calibration_dir(config_dir() / "calibration" / "sim")
    assert np.allclose(committed.left.camera_matrix, rig_numbers["K_l"])
    assert np.allclose(committed.right.distortion_coefficients, rig_numbers["D_r"])
    assert np.allclose(committed.stereo.rotation, rig_numbers["R"], atol=1e-12)
    assert np.allclose(committed.stereo.translation, rig_numbers["T"])
    write_true_calibration(load_rig(), tmp_path)
    for name in ("left.yaml", "right.yaml", "stereo.yaml"):
        assert (tmp_path / name).read_text() == (config_dir() / "calibration" / "sim" / name).read_text()


def test_unknown_scene_and_missing_mesh_are_clear_errors(tmp_path):
    geometry = load_rig()
    with pytest.raises(SceneError, match="unknown scene 'cube'"):
        build_scene("cube", geometry)
    with pytest.raises(SceneError, match="mesh file not found"):
        build_scene(str(tmp_path / "nothing.ply"), geometry)


def test_lsu_render_writes_pairs_and_truth(tmp_path):
    import argparse

    from lsu_sim import LaserTruth
    from lsu_sim.cli import cmd_render

    args = argparse.Namespace(scene="sphere", position=[200.0, 260.0], distance=None, yaw=0.0, pitch=0.0,
                              laser_off=False, vibration=0.0, after_stop=0.005, tau=0.06, freq=25.0, seed=0,
                              rig=None, output=str(tmp_path))
    assert cmd_render(args) == 0
    names = sorted(p.name for p in tmp_path.iterdir())
    assert names == ["left_000.png", "left_001.png", "right_000.png", "right_001.png", "truth_000.npz", "truth_001.npz"]
    truth = LaserTruth.from_npz(tmp_path / "truth_001.npz")
    assert truth.position_steps == 260.0 and len(truth.left.points_m) > 100
    # every truth point lies on the 6 cm sphere at the subject point
    centre = load_rig().subject_center
    assert np.abs(np.linalg.norm(truth.left.points_m - centre, axis=1) - 0.06).max() < 2e-4


def test_every_pixel_ray_reprojects_onto_its_pixel():
    # the ground truth of every render starts at these rays: each must land back on its own pixel centre
    # (through OpenCV's forward model, independent of the iterative undistortion that made it)
    geometry = load_rig()
    for camera in (geometry.left, geometry.right):
        u, v = np.meshgrid(np.arange(camera.width, dtype=np.float64), np.arange(camera.height, dtype=np.float64))
        pixels = np.stack([u.ravel(), v.ravel()], axis=1)
        rays = camera.pixel_rays(pixels)
        back = camera.project(camera.center + 0.3 * rays)
        assert np.abs(back - pixels).max() < 1e-9
