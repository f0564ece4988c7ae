"""The PLY writer: read back by open3d (an independent reader) and by the raw record layout."""

import numpy as np
import pytest

from lsu_bags.ply import PlyError, read_ply, write_cloud_ply, write_ply
from lsu_bags.pointcloud2 import pack_rgb


def _columns(n=50, seed=11):
    rng = np.random.default_rng(seed)
    rgb = rng.integers(0, 256, size=(n, 3)).astype(np.uint8)
    return {"x": rng.normal(size=n), "y": rng.normal(size=n), "z": rng.uniform(0.2, 0.4, n),
            "rgb": pack_rgb(rgb), "u": rng.uniform(0, 640, n), "v": rng.uniform(0, 480, n),
            "snap": np.arange(n, dtype=np.uint32) * 3}, rgb


def test_cloud_is_what_open3d_and_the_record_layout_read(tmp_path):
    o3d = pytest.importorskip("open3d")
    cols, rgb = _columns()
    path = write_cloud_ply(tmp_path / "sub" / "cloud.ply", cols, comment="test")
    pcd = o3d.io.read_point_cloud(str(path))
    xyz = np.stack([cols["x"], cols["y"], cols["z"]], 1)
    assert np.allclose(np.asarray(pcd.points), xyz, atol=1e-6)
    assert np.array_equal(np.round(np.asarray(pcd.colors) * 255).astype(np.uint8), rgb)
    rec = np.frombuffer(path.read_bytes()[-len(xyz) * 27:], dtype=[
        ("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("r", "u1"), ("g", "u1"), ("b", "u1"), ("u", "<f4"),
        ("v", "<f4"), ("snap", "<u4")])
    assert np.array_equal(rec["snap"], cols["snap"]) and np.allclose(rec["u"], cols["u"], atol=1e-4)
    assert b"comment test, frame lsu_left_optical, metres" in path.read_bytes()[:300]


def test_cloud_without_colour_is_white_and_reads_back(tmp_path):
    cols, _ = _columns(7)
    del cols["rgb"]
    vertices, faces = read_ply(write_cloud_ply(tmp_path / "c.ply", cols))
    assert faces is None
    assert np.all(vertices["red"] == 255) and np.all(vertices["blue"] == 255)
    assert np.array_equal(vertices["snap"], cols["snap"])


def test_empty_cloud_is_a_valid_file(tmp_path):
    cols = {k: np.zeros(0) for k in ("x", "y", "z", "u", "v")} | {"snap": np.zeros(0, np.uint32)}
    vertices, _ = read_ply(write_cloud_ply(tmp_path / "e.ply", cols))
    assert len(vertices["x"]) == 0


def test_columns_that_are_no_ply_property_are_refused(tmp_path):
    with pytest.raises(PlyError, match="'n'.*1-D column"):
        write_ply(tmp_path / "x.ply", {"x": np.zeros(3, np.float32), "n": np.zeros((3, 3), np.float32)})
    with pytest.raises(PlyError, match="different lengths"):
        write_ply(tmp_path / "x.ply", {"x": np.zeros(3, np.float32), "y": np.zeros(2, np.float32)})
