"""The generic face: an average face surface in the face frame, used to verify nose candidates and set the frame.

The template is MakeHuman's neutral base face (CC0, ``config/heads/makehuman_bust.npz``, no identity
morph, no hair), points within ``radius_m`` of the pronasale sampled on a 3.5 mm grid, in the face
frame: origin at the nose tip, x to the image right, y down, z out of the face (towards the camera).
It is mirror-symmetric, so a frame fitted to it has its x = 0 plane on the face's symmetry plane.
``region`` labels each point (nose, eyes, forehead, cheeks, mouth, chin) for weighting.

Built once per process (about 1 s) and kept: it is constant data, not a per-scan cache.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

from lsu_common.arrays import AnyArray

__all__ = ["FaceTemplate", "face_template", "REGIONS"]

REGIONS = ("nose", "eyes", "forehead", "cheeks", "mouth", "chin")


@dataclass
class FaceTemplate:
    """Points, normals and region labels of the generic face (face frame, metres)."""

    points: AnyArray
    normals: AnyArray
    region: AnyArray          # (N,) index into REGIONS
    landmarks: dict[str, AnyArray]
    tree: cKDTree


def region_of(local: AnyArray) -> AnyArray:
    """Region index of face-frame points (x right, y down, from the nose tip) by the face's usual layout."""
    x, y = local[:, 0], local[:, 1]
    ax = np.abs(x)
    reg = np.full(len(local), REGIONS.index("cheeks"))
    reg[y > 0.055] = REGIONS.index("chin")
    reg[(y > 0.012) & (y <= 0.055) & (ax < 0.035)] = REGIONS.index("mouth")
    reg[y < -0.055] = REGIONS.index("forehead")
    reg[(y >= -0.055) & (y < -0.018) & (ax >= 0.012) & (ax < 0.05)] = REGIONS.index("eyes")
    reg[(ax < 0.017) & (y >= -0.055) & (y <= 0.012)] = REGIONS.index("nose")
    return reg


_TEMPLATE: FaceTemplate | None = None


def face_template(radius_m: float = 0.085, voxel_m: float = 0.0035) -> FaceTemplate:
    """The generic face (built on first use, then kept for the process)."""
    global _TEMPLATE
    if _TEMPLATE is not None:
        return _TEMPLATE
    from lsu_sim.people import PersonSpec, make_person

    person = make_person(PersonSpec(identity_seed=0, identity_sigma=0.0, hair_m=0.0))
    skin = person.parts["skin"]
    v = np.asarray(skin.vertices)
    n = np.asarray(skin.vertex_normals)
    nose = person.landmarks["nose_tip"]
    flip = np.array([1.0, 1.0, -1.0])        # person frame (z away from the camera) -> face frame (z out)
    local = (v - nose) * flip
    nl = n * flip
    keep = (np.linalg.norm(local, axis=1) <= radius_m) & (nl[:, 2] > 0.2)   # the front of the face
    local, nl = local[keep], nl[keep]
    keys = np.floor(local / voxel_m).astype(np.int64)
    _, first = np.unique(keys, axis=0, return_index=True)
    first.sort()
    pts, nrm = local[first], nl[first]
    nrm /= np.linalg.norm(nrm, axis=1, keepdims=True)
    marks = {k: (m - nose) * flip for k, m in person.landmarks.items()}
    _TEMPLATE = FaceTemplate(pts, nrm, region_of(pts), marks, cKDTree(pts))
    return _TEMPLATE
