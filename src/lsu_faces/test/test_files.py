"""PLY round trip (lsu reconstruct's cloud -> read_ply), mesh files and renders, `lsu mesh` / `lsu face` offline."""

from __future__ import annotations

import argparse

import cv2
import numpy as np
import open3d as o3d
import pytest

from lsu_bags.ply import PlyError, read_ply


def test_reads_an_lsu_reconstruct_cloud(tmp_path):
    from lsu_bags.ply import write_cloud_ply
    from lsu_bags.pointcloud2 import pack_rgb
    from lsu_reconstruct.pipeline import SnapPoints

    rng = np.random.default_rng(3)
    xyz = rng.normal(size=(40, 3))
    rgb = rng.integers(0, 256, size=(40, 3)).astype(np.uint8)
    cloud = SnapPoints(xyz, rng.uniform(0, 640, 40), rng.uniform(0, 480, 40), np.arange(40, dtype=np.uint32),
                       pack_rgb(rgb))
    cols, faces = read_ply(write_cloud_ply(tmp_path / "c.ply", cloud.fields()))
    assert faces is None
    assert np.allclose(np.stack([cols["x"], cols["y"], cols["z"]], 1), xyz, atol=1e-6)
    assert np.allclose(cols["u"], cloud.u, atol=1e-4) and np.array_equal(cols["snap"], cloud.snap)
    assert np.array_equal(np.stack([cols["red"], cols["green"], cols["blue"]], 1), rgb)


def test_not_a_ply_is_named(tmp_path):
    p = tmp_path / "x.ply"
    p.write_text("hello")
    with pytest.raises(PlyError, match="not a PLY"):
        read_ply(p)


def _person_cloud(seed: int, step: int = 6, **kw):
    sim = pytest.importorskip("lsu_sim")
    people = pytest.importorskip("lsu_sim.people")
    from lsu_faces.synthetic import fast_scan

    rig = sim.load_rig()
    centre = rig.rig_center + (rig.subject_distance_m + 0.10) * rig.rig_axes[2]
    objs = people.person_objects(people.make_person(people.PersonSpec(seed, **kw)), centre)
    return fast_scan(objs, rig, np.arange(0, 471, step), noise_m=5e-5, seed=seed).columns, objs[0].extra


def _write_cloud(path, c):
    from lsu_bags.ply import write_cloud_ply

    return write_cloud_ply(path, c)


def _parser():
    from lsu_faces import cli

    parser = argparse.ArgumentParser()
    cli.register(parser.add_subparsers(dest="command"))
    return parser


def test_lsu_mesh_writes_mesh_and_renders_and_face_cli(tmp_path, capsys):
    c, _ = _person_cloud(11)
    cloud = _write_cloud(tmp_path / "cloud.ply", c)
    parser = _parser()
    args = parser.parse_args(["mesh", str(cloud), "--size", "64"])
    assert args.func(args) == 0
    mesh = o3d.io.read_triangle_mesh(str(tmp_path / "mesh.ply"))
    assert len(mesh.triangles) > 1000 and mesh.has_vertex_colors()
    img = cv2.imread(str(tmp_path / "render_side_shaded.png"))
    assert img.shape == (64, 64, 3) and img.std() > 5     # something was drawn, not a flat background
    gallery = str(tmp_path / "private" / "g.db")
    # the gallery option before and after the action
    for argv in (["face", "--gallery", gallery, "enroll", "zoe", str(cloud)],
                 ["face", "identify", str(cloud), "--gallery", gallery]):
        args = parser.parse_args(argv)
        assert args.func(args) == 0
    out = capsys.readouterr().out
    assert "1. zoe" in out and "score 1.000000" in out


def test_millimetre_and_plain_xyz_clouds(tmp_path, capsys):
    from lsu_faces.pipeline import CloudFileError, load_cloud_file

    c, extra = _person_cloud(12, step=8)
    xyz = np.stack([c["x"], c["y"], c["z"]], 1).astype(np.float64)
    np.save(tmp_path / "mm.npy", xyz * 1000.0)          # a plain x y z cloud in millimetres, no u/v
    parser = _parser()
    gallery = str(tmp_path / "g" / "g.db")
    args = parser.parse_args(["face", "enroll", "ann", str(_write_cloud(tmp_path / "m.ply", c)), "--gallery", gallery])
    assert args.func(args) == 0
    for units in ("mm", "auto"):
        args = parser.parse_args(["face", "identify", str(tmp_path / "mm.npy"), "--units", units, "--gallery", gallery])
        assert args.func(args) == 0
        assert "best: ann" in capsys.readouterr().out
    loaded = load_cloud_file(tmp_path / "mm.npy", "mm")["columns"]
    assert np.allclose(loaded["x"], xyz[:, 0])
    with pytest.raises(CloudFileError, match=r"looks like millimetres \(--units mm\)"):
        load_cloud_file(tmp_path / "mm.npy", "m")
    np.save(tmp_path / "tiny.npy", xyz * 1e-6)
    with pytest.raises(CloudFileError, match="not a head-sized scene"):
        load_cloud_file(tmp_path / "tiny.npy")
    # lsu mesh on the plain cloud: meshed by ball pivoting, and the nose is reported where the generator put it
    args = parser.parse_args(["mesh", str(tmp_path / "mm.npy"), "--units", "mm", "-o", str(tmp_path / "out"),
                              "--no-renders"])
    assert args.func(args) == 0
    mesh = o3d.io.read_triangle_mesh(str(tmp_path / "out" / "mesh.ply"))
    assert len(mesh.triangles) > 0.5 * len(xyz)
    text = capsys.readouterr().out
    nose_mm = [float(v) for v in text.split("nose tip at [")[1].split("]")[0].split(",")]
    assert np.linalg.norm(np.array(nose_mm) / 1000.0 - extra["nose_tip_m"]) < 0.005


_TWO_PROCESS = """
import sys
from pathlib import Path
from lsu_faces.gallery import Gallery
from lsu_faces.pipeline import load_cloud_file, process_cloud
folder = Path(sys.argv[1])
sig = {}
for name in ("a", "b", "probe"):
    loaded = load_cloud_file(folder / f"{name}.ply")
    sig[name] = process_cloud(loaded["columns"], faces=loaded["faces"]).signature
g = Gallery(Path(sys.argv[2]) / "g.db")
g.enroll("a", sig["a"])
g.enroll("b", sig["b"])
ident = g.identify(sig["probe"])
print(ident.accepted, [(m.name, repr(m.distance_m), repr(m.score)) for m in ident.matches],
      sig["probe"].data.tobytes().hex()[:4000])
"""


@pytest.mark.slow
def test_same_enrol_identify_result_in_two_processes(tmp_path):
    import os
    import subprocess
    import sys

    for name, seed, kw in (("a", 13, {}), ("b", 14, {}), ("probe", 13, {"yaw_deg": 20.0, "expression": "smile"})):
        _write_cloud(tmp_path / f"{name}.ply", _person_cloud(seed, step=5, **kw)[0])
    # both processes at once, with different hash seeds: nothing may depend on process state or timing
    runs = [subprocess.Popen([sys.executable, "-c", _TWO_PROCESS, str(tmp_path), str(tmp_path / f"gallery{k}")],
                             stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                             env={**os.environ, "PYTHONHASHSEED": str(k)}) for k in range(2)]
    outs = []
    for run in runs:
        out, err = run.communicate(timeout=250)
        assert run.returncode == 0, err[-2000:]
        outs.append(out)
    assert outs[0] == outs[1]
    assert outs[0].startswith("True [('a',")
