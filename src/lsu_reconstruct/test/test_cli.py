"""`lsu reconstruct` on a rosbag2 written with rosbags: PLY back, read with open3d, lies on the true plane."""

import argparse

import numpy as np
import pytest

from lsu_bags.bags import BagTypes
from lsu_reconstruct import synthetic as S
from lsu_reconstruct.cli import BagError, register


def lsu_typestore():
    types = BagTypes()
    for msgtype in ("lsu_interfaces/msg/LaserLine", "lsu_interfaces/msg/ScanEvent"):
        types.ensure(msgtype)
    return types.typestore


def write_bag(path, rig, plane, xs, with_events=True):
    from rosbags.rosbag2 import Writer

    store = lsu_typestore()
    T = store.types
    Time, Header = T["builtin_interfaces/msg/Time"], T["std_msgs/msg/Header"]
    Line, Event = T["lsu_interfaces/msg/LaserLine"], T["lsu_interfaces/msg/ScanEvent"]

    def line(samples, stamp):
        n = len(samples)
        return Line(header=Header(stamp=stamp, frame_id="cam"), image_width=640, image_height=480, method="sim",
                    u=samples.u.astype(np.float32), v=samples.v.astype(np.float32), peak=np.zeros(n, np.float32),
                    width=np.zeros(n, np.float32), quality=np.ones(n, np.float32), rows_searched=480,
                    rows_ambiguous=0, rows_saturated=0)

    with Writer(path, version=9) as writer:
        conns = {side: writer.add_connection(f"/lsu/stereo/{side}/laser_line", "lsu_interfaces/msg/LaserLine",
                                             typestore=store) for side in ("left", "right")}
        events = writer.add_connection("/lsu/scan/events", "lsu_interfaces/msg/ScanEvent", typestore=store)
        t = 1_000_000_000
        for index, x in enumerate(xs):
            stamp = Time(sec=10 + index, nanosec=0)
            laser = S.Laser.at(x)
            if with_events:
                ev = Event(header=Header(stamp=stamp, frame_id=""), type=2, scan_id="bag", expected_snaps=len(xs),
                           index=index + 5, position_steps=index, image_stamp=stamp, snaps_captured=0, partial=False,
                           reason="", output_dir="")
                writer.write(events, t, store.serialize_cdr(ev, "lsu_interfaces/msg/ScanEvent"))
            for side in ("left", "right"):
                samples = S.laser_samples(rig, [plane], laser, side)
                writer.write(conns[side], t + 1, store.serialize_cdr(line(samples, stamp), "lsu_interfaces/msg/LaserLine"))
            t += 100_000_000
    return path


def run_cli(argv):
    parser = argparse.ArgumentParser(prog="lsu")
    register(parser.add_subparsers(dest="command"))
    args = parser.parse_args(["reconstruct", *argv])
    return args.func(args)


def test_bag_to_ply_gives_the_plane(tmp_path, capsys):
    o3d = pytest.importorskip("open3d")
    rig = S.default_rig()
    plane = S.Plane.facing(0.3)
    bag = write_bag(tmp_path / "scan_bag", rig, plane, (-0.02, 0.0, 0.02))
    calib = rig.write_calibration(tmp_path / "calib")
    out = tmp_path / "cloud.ply"
    assert run_cli(["--calib", str(calib), "--bag", str(bag), "-o", str(out), "--smooth-window-rows", "0"]) == 0
    assert "points from 3 stereo pairs" in capsys.readouterr().out
    pts = np.asarray(o3d.io.read_point_cloud(str(out)).points)
    assert len(pts) > 1300
    assert np.abs(pts @ plane.normal - plane.offset).max() < 2e-5
    snaps = np.frombuffer(out.read_bytes()[-len(pts) * 27:], dtype=[("x", "<f4"), ("y", "<f4"), ("z", "<f4"),
                                                                   ("r", "u1"), ("g", "u1"), ("b", "u1"),
                                                                   ("u", "<f4"), ("v", "<f4"), ("snap", "<u4")])["snap"]
    assert set(snaps.tolist()) == {5, 6, 7}  # indices from the SNAP events


def test_bag_without_laser_lines_is_a_clear_error(tmp_path):
    from rosbags.rosbag2 import Writer

    store = lsu_typestore()
    with Writer(tmp_path / "empty", version=9) as writer:
        writer.add_connection("/other", "std_msgs/msg/String", typestore=store)
    calib = S.default_rig().write_calibration(tmp_path / "calib")
    with pytest.raises(BagError, match="no stereo/.*laser_line"):
        run_cli(["--calib", str(calib), "--bag", str(tmp_path / "empty"), "-o", str(tmp_path / "x.ply")])


def test_missing_bag_and_swapped_calibration(tmp_path):
    rig = S.default_rig()
    with pytest.raises(FileNotFoundError, match="nowhere"):
        run_cli(["--calib", str(rig.write_calibration(tmp_path / "c")), "--bag", str(tmp_path / "nowhere"),
                 "-o", str(tmp_path / "x.ply")])
    with pytest.raises(ValueError, match="swapped"):
        run_cli(["--calib", str(rig.write_calibration(tmp_path / "s", swap=True)), "--bag", str(tmp_path),
                 "-o", str(tmp_path / "x.ply")])


def draw_line(samples, sigma_px=1.2):
    """A bgr8 laser image: a Gaussian red profile centred on the true u of every row (dark background)."""
    img = np.full((480, 640, 3), 12, np.uint8)
    cols = np.arange(640.0)
    for u, v in zip(samples.u, samples.v):
        img[int(v), :, 2] = np.clip(12 + 230 * np.exp(-0.5 * ((cols - u) / sigma_px) ** 2), 0, 255).astype(np.uint8)
    return img


def test_image_pairs_through_the_extractor(tmp_path):
    pytest.importorskip("lsu_extract.extractor")
    cv2 = pytest.importorskip("cv2")
    rig = S.default_rig()
    plane = S.Plane.facing(0.3)
    shots = tmp_path / "shots"
    shots.mkdir()
    for i, x in enumerate((-0.02, 0.02)):
        laser = S.Laser.at(x)
        for side in ("left", "right"):
            cv2.imwrite(str(shots / f"{side}_{i:03d}.png"), draw_line(S.laser_samples(rig, [plane], laser, side)))
    out = tmp_path / "pairs.ply"
    assert run_cli(["--calib", str(rig.write_calibration(tmp_path / "c")), "--pairs", str(shots), "-o", str(out)]) == 0
    o3d = pytest.importorskip("open3d")
    pts = np.asarray(o3d.io.read_point_cloud(str(out)).points)
    assert len(pts) > 500
    # 8-bit rendering and a real detector: sub-pixel, so well under a millimetre from the true plane
    assert np.median(np.abs(pts @ plane.normal - plane.offset)) < 2e-4
