"""Camera sources, profiles and calibration files: the good path and one clear error per bad input."""

import cv2
import numpy as np
import pytest

from lsu_cameras.calib_io import CalibrationParseError, CalibrationSizeError, read_calibration_dir, read_camera_yaml
from lsu_cameras.paths import config_dir
from lsu_cameras.profiles import V4L2_CONTROLS, ProfileError, apply_profile, load_profile
from lsu_cameras.sources import CameraError, FolderSource, V4l2Source


def write_pair(folder, name, shape=(480, 640, 3), value=0):
    left = np.full(shape, value, np.uint8)
    right = np.full(shape, value + 1, np.uint8)
    cv2.imwrite(str(folder / f"left_{name}.png"), left)
    cv2.imwrite(str(folder / f"right_{name}.png"), right)


def test_folder_source_replays_pairs_in_order_and_loops(tmp_path):
    for k in range(3):
        write_pair(tmp_path, f"{k:03d}", value=10 * k)
    source = FolderSource(tmp_path)
    values = [int(source.grab_pair().left[0, 0, 0]) for _ in range(4)]
    assert values == [0, 10, 20, 0] and source.image_size == (640, 480)


def test_folder_source_errors(tmp_path):
    with pytest.raises(CameraError, match="not found"):
        FolderSource(tmp_path / "nowhere")
    with pytest.raises(CameraError, match="no left_\\*.png/right_\\*.png pairs"):
        FolderSource(tmp_path)
    write_pair(tmp_path, "a")
    cv2.imwrite(str(tmp_path / "right_a.png"), np.zeros((240, 320, 3), np.uint8))
    with pytest.raises(CameraError, match="a pair must have one size"):
        FolderSource(tmp_path)


@pytest.mark.fault('camera: device missing')
def test_unopenable_v4l2_device_is_a_clear_error():
    with pytest.raises(CameraError, match="cannot open the left camera '/dev/lsu_no_such_video'"):
        V4l2Source(["/dev/lsu_no_such_video", "/dev/lsu_no_such_video2"])
    with pytest.raises(CameraError, match="exactly two devices"):
        V4l2Source(["/dev/video0"])


class FakeCapture:
    """A driver that clamps sharpness to 200 and refuses gamma."""

    def __init__(self):
        self.values = {}

    def set(self, prop, value):
        if prop == V4L2_CONTROLS["gamma"]:
            return False
        self.values[prop] = min(value, 200.0) if prop == V4L2_CONTROLS["sharpness"] else value
        return True

    def get(self, prop):
        return self.values.get(prop, -1.0)


def test_thesis_profiles_load_and_mismatches_are_reported():
    dark, normal = load_profile("dark"), load_profile("normal")
    assert dark.controls["sharpness"] == 255 and dark.controls["saturation"] == 184 and dark.controls["gain"] == 10
    assert normal.controls["auto_exposure"] == 3 and normal.controls["saturation"] == 90
    problems = apply_profile(FakeCapture(), dark)
    assert any(p.startswith("sharpness: set 255, reads back 200") for p in problems)
    assert any(p.startswith("gamma: the driver refused") for p in problems)
    assert len(problems) == 2


def test_unknown_profile_key_and_name_are_errors(tmp_path):
    bad = tmp_path / "bad.yaml"
    bad.write_text("controls:\n  shutter_speed: 5\n")
    with pytest.raises(ProfileError, match="unknown control 'shutter_speed'"):
        load_profile(str(bad))
    with pytest.raises(ProfileError, match="'bright' not found.*known profiles: dark, normal"):
        load_profile("bright")


@pytest.mark.fault('calibration: corrupt YAML')
def test_calibration_files_bad_yaml_and_size_mismatch(tmp_path):
    sim = config_dir() / "calibration" / "sim"
    for name in ("left.yaml", "right.yaml", "stereo.yaml"):
        (tmp_path / name).write_text((sim / name).read_text())
    assert read_calibration_dir(tmp_path).image_size == (640, 480)
    (tmp_path / "right.yaml").write_text((sim / "right.yaml").read_text().replace("image_width: 640", "image_width: 320"))
    with pytest.raises(CalibrationSizeError, match="image sizes differ.*right.yaml 320x480"):
        read_calibration_dir(tmp_path)
    (tmp_path / "left.yaml").write_text("camera_matrix: [1, 2\n")
    with pytest.raises(CalibrationParseError, match="left.yaml: not valid YAML"):
        read_camera_yaml(tmp_path / "left.yaml")
    (tmp_path / "left.yaml").write_text("image_width: 640\nimage_height: 480\ncamera_matrix: {data: [1, 2, 3]}\n")
    with pytest.raises(CalibrationParseError, match="'camera_matrix' has 3 numbers, expected 9"):
        read_camera_yaml(tmp_path / "left.yaml")


def test_folder_source_streams_its_pairs_in_order_on_the_slots_stamps(tmp_path):
    for k in range(2):
        write_pair(tmp_path, f"{k:03d}", value=10 * k)
    source = FolderSource(tmp_path)
    pairs = [source.pair_at(100.0 + k / 30, k) for k in range(3)]
    assert [int(p.left[0, 0, 0]) for p in pairs] == [0, 10, 0] and [p.time_s for p in pairs] == [100.0, 100.0 + 1 / 30,
                                                                                                 100.0 + 2 / 30]
    assert source.clocked and source.exposure_s == 0.0


class FakeStreamingCamera:
    """A V4L2 camera running free: each grab delivers the next buffer, stamped by the driver (monotonic ms)."""

    def __init__(self, driver_ms):
        self.driver_ms = iter(driver_ms)
        self.current = 0.0
        self.props = {}

    def isOpened(self):
        return True

    def set(self, prop, value):
        self.props[prop] = value
        return True

    def get(self, prop):
        return self.current if prop == cv2.CAP_PROP_POS_MSEC else self.props.get(prop, 0.0)

    def grab(self):
        self.current = next(self.driver_ms, None)
        return self.current is not None

    def retrieve(self):
        return True, np.zeros((480, 640, 3), np.uint8)

    def release(self):
        pass


def test_v4l2_stream_is_stamped_from_the_buffers_and_a_missing_frame_counts_as_dropped():
    from lsu_cameras.stream import count_drops, frame_period_ns
    from lsu_common.stamps import seconds_to_ns

    slots = [0, 1, 2, 4, 5]  # the devices run at 30 fps; the pair of slot 3 never arrived
    left_ms = [5000.0 + k * 1000.0 / 30 for k in slots]
    cameras = iter([FakeStreamingCamera(left_ms), FakeStreamingCamera([ms + 2.0 for ms in left_ms])])
    wall_minus_mono = 1_764_633_600.0
    arrivals = iter(ms / 1000.0 + 0.012 for pair in zip(left_ms, left_ms) for ms in pair)  # 12 ms after each buffer

    def clocks():
        mono = next(arrivals)
        return wall_minus_mono + mono, mono

    source = V4l2Source(["/dev/video0", "/dev/video1"], opener=lambda *_: next(cameras), clocks=clocks)
    assert not source.clocked and source.start_stream(30.0) == 30.0
    pairs = [source.next_pair(1.0) for _ in slots]
    for k, pair in zip(slots, pairs):
        assert pair.time_s == pytest.approx(wall_minus_mono + 5.0 + k / 30, abs=1e-6)  # the left buffer's time
        assert pair.right_offset_s == pytest.approx(0.002, abs=1e-6) and pair.left_offset_s == 0.0
    tally = count_drops([seconds_to_ns(p.time_s) for p in pairs], frame_period_ns(30.0))
    assert (tally.expected, tally.published, tally.dropped) == (6, 5, 1)
    with pytest.raises(CameraError, match="left camera '/dev/video0' returned no frame"):
        source.next_pair(1.0)
