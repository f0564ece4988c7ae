"""PLY round trip (lsu reconstruct's cloud -> read_ply), mesh files and renders, `lsu mesh` / `lsu face` offline."""

from __future__ import annotations

import argparse

import cv2
import numpy as np
import open3d as o3d
import pytest

from lsu_faces.plyio import PlyError, read_ply


def test_reads_an_lsu_reconstruct_cloud(tmp_path):
    from lsu_reconstruct.cli import write_ply
    from lsu_reconstruct.pipeline import SnapPoints
    from lsu_reconstruct.pointcloud2 import pack_rgb

    rng = np.random.default_rng(3)
    xyz = rng.normal(size=(40, 3))
    rgb = rng.integers(0, 256, size=(40, 3)).astype(np.uint8)
    cloud = SnapPoints(xyz, rng.uniform(0, 640, 40), rng.uniform(0, 480, 40), np.arange(40, dtype=np.uint32),
                       pack_rgb(rgb))
    cols, faces = read_ply(write_ply(tmp_path / "c.ply", cloud))
    assert faces is None
    assert np.allclose(np.stack([cols["x"], cols["y"], cols["z"]], 1), xyz, atol=1e-6)
    assert np.allclose(cols["u"], cloud.u, atol=1e-4) and np.array_equal(cols["snap"], cloud.snap)
    assert np.array_equal(np.stack([cols["red"], cols["green"], cols["blue"]], 1), rgb)


def test_not_a_ply_is_named(tmp_path):
    p = tmp_path / "x.ply"
    p.write_text("hello")
    with pytest.raises(PlyError, match="not a PLY"):
        read_ply(p)


def test_lsu_mesh_writes_mesh_and_renders_and_face_cli(tmp_path, capsys):
    sim = pytest.importorskip("lsu_cameras.sim")
    from lsu_faces import cli
    from lsu_faces.synthetic import fast_scan
    from lsu_reconstruct.cli import write_ply
    from lsu_reconstruct.pipeline import SnapPoints

    rig = sim.load_rig()
    objs = sim.build_scene("head:11", rig)
    c = fast_scan(objs, rig, np.arange(0, 471, 6), noise_m=5e-5, seed=11).columns
    cloud = write_ply(tmp_path / "cloud.ply", SnapPoints(np.stack([c["x"], c["y"], c["z"]], 1).astype(np.float64),
                                                         c["u"], c["v"], c["snap"], c["rgb"]))
    parser = argparse.ArgumentParser()
    cli.register(parser.add_subparsers(dest="command"))
    args = parser.parse_args(["mesh", str(cloud), "--size", "64"])
    assert args.func(args) == 0
    mesh = o3d.io.read_triangle_mesh(str(tmp_path / "mesh.ply"))
    assert len(mesh.triangles) > 1000 and mesh.has_vertex_colors()
    img = cv2.imread(str(tmp_path / "render_side_shaded.png"))
    assert img.shape == (64, 64, 3) and img.std() > 5     # something was drawn, not a flat background
    gallery = str(tmp_path / "g.db")
    for argv in (["face", "--gallery", gallery, "enroll", "zoe", str(cloud)],
                 ["face", "--gallery", gallery, "identify", str(cloud)]):
        args = parser.parse_args(argv)
        assert args.func(args) == 0
    assert "1. zoe" in capsys.readouterr().out
