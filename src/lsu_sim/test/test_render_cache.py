"""The camera stream's render against the renderer it replaced, on seeded frames of a person.

``data/render_digests.npz`` holds, for every image of `_frames` (a 60 fps face sweep's frames, a settling
carriage, a moved subject), its row and column sums per channel as the renderer made them before the
per-pose shadow cache and the track-position coefficients of the laser's distance and incidence: written by
``python src/lsu_sim/test/test_render_cache.py write`` run on that renderer. Rewrite it only for a change of
the physics, never to make a speed change pass.
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest

from lsu_common.arrays import AnyArray

DIGESTS = Path(__file__).parent / "data" / "render_digests.npz"
SWEEP_RATE = 114.3       # steps/s: bench_scan's 60 fps face sweep


def _frames(shadow_cache: bool | None) -> list[AnyArray]:
    """Left and right images of the seeded frames (``shadow_cache`` None: the rig's default arguments)."""
    from lsu_sim import CarriageState, SimulatedRig, build_scene, load_rig
    from lsu_sim.motion import scene_motion

    g = load_rig(None)
    scene = build_scene("person:2", g)
    rig = SimulatedRig(g, scene, seed=0) if shadow_cache is None else SimulatedRig(g, scene, seed=0,
                                                                                   shadow_cache=shadow_cache)
    sweep = CarriageState(82.0, True, velocity_steps_per_s=SWEEP_RATE, position_time_s=100.0)
    out: list[AnyArray] = []
    for k, t in enumerate((100.0, 100.39, 100.78)):
        frame = rig.render(sweep, capture_time_s=t, seed=k, parallel=False)
        out += [frame.left, frame.right]
    settling = CarriageState(260.0, True, stopped_at_s=99.99, vibration_amplitude_steps=0.5)
    frame = rig.render(settling, capture_time_s=100.0, seed=5, parallel=False)
    out += [frame.left, frame.right]
    pose = scene_motion("standing", 3, g, scene).pose(0.3)
    rig.set_subject_pose(pose.R, pose.translation)
    frame = rig.render(sweep, capture_time_s=100.6, seed=7, parallel=False)
    return out + [frame.left, frame.right]


def _digest(images: list[AnyArray]) -> tuple[AnyArray, AnyArray]:
    """Row sums (n, H, 3) and column sums (n, W, 3) of each image, int64."""
    return (np.stack([im.astype(np.int64).sum(axis=1) for im in images]),
            np.stack([im.astype(np.int64).sum(axis=0) for im in images]))


@pytest.fixture(scope="module")
def uncached() -> list[AnyArray]:
    return _frames(shadow_cache=False)


def test_render_without_the_shadow_cache_is_the_previous_renderer_to_the_last_bit(uncached):
    with np.load(DIGESTS) as z:
        rows, cols = z["rows"], z["cols"]
    new_rows, new_cols = _digest(uncached)
    assert new_rows.shape == rows.shape and new_rows.sum() > 0
    # bit for bit on the processor the digests were written on; another processor's vector maths (numpy's
    # exp/sin kernels per instruction set, e.g. AVX-512 against AVX2) rounds a few values the other way by
    # one ulp, which moves a pixel that sits on a DN boundary by 1 DN: allowed, a handful of sums off by 1,
    # never more (a change of the render moves thousands of sums by more)
    for new, old in ((new_rows, rows), (new_cols, cols)):
        off = np.abs(new - old)
        assert off.max() <= 1 and np.count_nonzero(off) <= 1e-3 * off.size, (
            f"{np.count_nonzero(off)} of {off.size} sums differ, by up to {off.max()}: at {np.argwhere(off)[:10].tolist()}")


def test_shadow_cache_changes_only_a_few_pixels_at_the_shadow_edges(uncached):
    cached = _frames(shadow_cache=True)
    line_pixels = 0
    for a, b in zip(cached, uncached):
        diff = np.abs(a.astype(np.int16) - b.astype(np.int16))
        # the stated tolerance: at most 1e-4 of an image's values differ (a shadow edge crossing a pixel's
        # few millimetres of band; the cache casts from the band's centre), never the laser line as a whole
        assert np.count_nonzero(diff) <= 1e-4 * diff.size
        assert int(diff[..., 2].sum()) <= 1e-4 * int(np.clip(b[..., 2].astype(np.int64) - 40, 0, None).sum())
        line_pixels += int(np.count_nonzero(b[..., 2] > 60))
    assert line_pixels > 1000   # the frames do show the line


def _write() -> None:
    import inspect

    from lsu_sim import SimulatedRig

    # the per-frame shadow rays where the renderer has the choice (the digests are what the uncached render must give)
    uncached = False if "shadow_cache" in inspect.signature(SimulatedRig).parameters else None
    rows, cols = _digest(_frames(shadow_cache=uncached))
    DIGESTS.parent.mkdir(exist_ok=True)
    np.savez_compressed(DIGESTS, rows=rows, cols=cols)
    print(f"wrote {DIGESTS} ({len(rows)} images)")


if __name__ == "__main__" and sys.argv[1:] == ["write"]:
    _write()
