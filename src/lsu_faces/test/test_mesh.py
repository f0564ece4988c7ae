"""Meshing in the left image plane: no triangle across a depth step, neighbourhoods, normals, bad input."""

from __future__ import annotations

import numpy as np
import pytest

from lsu_faces.mesh import MeshError, MeshParams, neighbours, triangulate_image_plane, unique_edges

F, CX, CY = 800.0, 320.0, 240.0


def step_scan(seed: int = 0, near_m: float = 0.30, far_m: float = 0.32, noise_m: float = 5e-5):
    """A stop-snap scan of two plates forming a diagonal step, seen by an ideal pinhole camera.

    Each laser sheet x = x_k gives one point per image row; the surface depth is ``near_m`` where
    x + 0.5 y < 0 and ``far_m`` elsewhere (analytic ray-plane intersection).
    """
    rng = np.random.default_rng(seed)
    pts, uv, plate = [], [], []
    for xk in np.linspace(-0.05, 0.05, 60):
        for v in np.arange(100.0, 380.0):
            ray_y = (v - CY) / F
            for z, which in ((near_m, 0), (far_m, 1)):
                y = ray_y * z
                if (xk + 0.5 * y < 0) == (which == 0):
                    p = np.array([xk, y, z]) + rng.normal(0, noise_m, 3) * [0, 0, 1]
                    pts.append(p)
                    uv.append([F * p[0] / p[2] + CX, F * p[1] / p[2] + CY])
                    plate.append(which)
                    break
    return np.array(pts), np.array(uv), np.array(plate)


def test_no_triangle_spans_the_depth_step():
    xyz, uv, plate = step_scan()
    mesh = triangulate_image_plane(xyz, uv)
    labels = plate[mesh.triangles]
    assert mesh.n_triangles > 0.9 * mesh.stats["delaunay_triangles"]
    assert not np.any(labels.min(axis=1) != labels.max(axis=1)), "a triangle joins the two plates"


def test_step_is_bridged_without_culling():
    # the same scan with culling disabled does join the plates: the test above can fail
    xyz, uv, plate = step_scan()
    mesh = triangulate_image_plane(xyz, uv, params=MeshParams(max_edge_factor=1e9, max_stretch=1e9))
    labels = plate[mesh.triangles]
    assert np.any(labels.min(axis=1) != labels.max(axis=1))


def test_normals_face_the_camera_and_neighbours_are_symmetric():
    xyz, uv, _ = step_scan()
    mesh = triangulate_image_plane(xyz, uv)
    n = mesh.normals()
    used = np.linalg.norm(n, axis=1) > 0
    assert np.all(np.einsum("ij,ij->i", n[used], -xyz[used]) > 0)
    # plates face the camera along -z
    assert np.median(n[used][:, 2]) < -0.99
    nb = neighbours(mesh.triangles, mesh.n_vertices)
    edges = unique_edges(mesh.triangles)
    assert nb.counts.sum() == 2 * len(edges)
    i = int(edges[0, 0])
    for j in nb.of(i):
        assert i in nb.of(int(j))


@pytest.mark.parametrize("n", [0, 2, 10])
def test_too_few_points_is_a_clear_error(n):
    with pytest.raises(MeshError, match="fewer than"):
        triangulate_image_plane(np.zeros((n, 3)), np.zeros((n, 2)))


def test_mismatched_and_nan_inputs_are_refused():
    xyz, uv, _ = step_scan()
    with pytest.raises(MeshError, match="u/v"):
        triangulate_image_plane(xyz, uv[:-1])
    bad = xyz.copy()
    bad[3, 2] = np.nan
    with pytest.raises(MeshError, match="NaN"):
        triangulate_image_plane(bad, uv)


def test_pixels_on_one_line_are_degenerate():
    xyz = np.column_stack([np.zeros(100), np.linspace(0, 0.1, 100), np.full(100, 0.3)])
    uv = np.column_stack([np.full(100, 320.0), np.linspace(0, 300, 100)])
    with pytest.raises(MeshError, match="degenerate"):
        triangulate_image_plane(xyz, uv)
