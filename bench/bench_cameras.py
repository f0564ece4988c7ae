"""Cameras benchmark: simulated pair render time, calibration accuracy on the sim rig, capture service round trip.

Figures (ARCHITECTURE.md): render_pair_ms_median, capture_roundtrip_ms_median, calib_focal_err_pct,
calib_baseline_err_pct, calib_rotation_err_deg (+ extras). The render is timed with the rig's
physics (speckle, skin, blooming) and, interleaved in the same run, without it
(``render_pair_no_physics_ms_median``, ``render_physics_over_no_physics``). The render's CPU per pair
(process time) of the head, moving at the fastest sweep rate and settled, with both views on one thread
as the camera stream renders them, beside the reference render's (``SimulatedRig(reference=True)``, also
on one thread) and the two-thread render's (a single capture's) in interleaved blocks of the same run:
sim_render_cpu_ms_{moving,settled}, sim_render_cpu_over_reference_{moving,settled},
sim_render_parallel_cpu_ms_{moving,settled}, sim_render_parallel_cpu_over_serial_{moving,settled}.
Writes bench/results/cameras.json.
"""

from __future__ import annotations

import os
import sys
from pathlib import Path

os.environ.setdefault("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")  # DDS stays on this machine

import dataclasses  # noqa: E402
import time  # noqa: E402

import cv2  # noqa: E402
import numpy as np  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parent))
from common import median, percentile, time_calls, write_result  # noqa: E402

from lsu_cameras.calibration import BoardSpec, calibrate_stereo  # noqa: E402
from lsu_sim import CarriageState, SimulatedRig, build_scene, load_rig  # noqa: E402
from lsu_sim.boards import random_board_poses, render_board_pairs  # noqa: E402


def _no_physics(geometry, scene: str) -> SimulatedRig:
    """The same scene without speckle, blooming and skin scattering (the reference of the physics' cost)."""
    plain = dataclasses.replace(geometry, speckle=dataclasses.replace(geometry.speckle, contrast=0.0),
                                sensor=dataclasses.replace(geometry.sensor, blooming=0.0))
    objects = [dataclasses.replace(o, material="surface") for o in build_scene(scene, plain)]
    return SimulatedRig(plain, objects, seed=1)


def bench_render(geometry) -> dict:
    out = {}
    for scene in ("plane", "head"):
        rig = SimulatedRig(geometry, build_scene(scene, geometry), seed=1)
        ref = _no_physics(geometry, scene)
        positions = iter(np.linspace(100, 370, 1000))
        ref_positions = iter(np.linspace(100, 370, 1000))
        with_physics, without = [], []
        for _ in range(3):  # interleaved blocks: a loaded host slows both alike
            with_physics += time_calls(lambda: rig.render(float(next(positions))), repeat=10)
            without += time_calls(lambda: ref.render(float(next(ref_positions))), repeat=10)
        out[scene], out[f"{scene}_no_physics"] = with_physics, without
    vib = SimulatedRig(geometry, build_scene("head", geometry), seed=1)
    state = CarriageState(235.0, stopped_at_s=0.0, vibration_amplitude_steps=2.0, vibration_tau_s=0.06,
                          vibration_freq_hz=25.0)
    out["vibrating"] = time_calls(lambda: vib.render(state, capture_time_s=0.005), repeat=20)
    out["truth"] = time_calls(lambda: vib.laser_truth(200.0), repeat=10)
    return out


def _cpu_ms(fn, count: int) -> float:
    """CPU time [ms] per call (this process, all threads) of ``count`` calls."""
    c0 = time.process_time()
    for i in range(count):
        fn(i)
    return 1000.0 * (time.process_time() - c0) / count


def bench_render_cpu(geometry, blocks: int = 5, per_block: int = 6) -> dict:
    """CPU per pair of the render (one thread, two threads) and of the reference render (one thread), head 7
    moving at 180 steps/s and settled."""
    objects = build_scene("head:7", geometry)
    rigs = {"serial": SimulatedRig(geometry, objects, seed=1, parallel=False),
            "parallel": SimulatedRig(geometry, objects, seed=1, parallel=True),
            "reference": SimulatedRig(geometry, objects, seed=1, reference=True, parallel=False)}

    def moving(rig):
        return lambda i: rig.render(CarriageState(120.0 + 7 * i, velocity_steps_per_s=180.0, position_time_s=0.0),
                                    capture_time_s=0.003 * i, seed=i)

    def settled(rig):
        return lambda i: rig.render(121.0 + 7 * i, seed=i)

    out: dict = {}
    for name, make in (("moving", moving), ("settled", settled)):
        for rig in rigs.values():
            make(rig)(0)  # warm-up: caches, the noise bank, the thread pool
        for _ in range(blocks):  # interleaved: a loaded host slows all alike
            for kind, rig in rigs.items():
                out.setdefault((name, kind), []).append(_cpu_ms(make(rig), per_block))
    figures = {}
    for name in ("moving", "settled"):
        fast, ref, par = (median(out[(name, kind)]) for kind in ("serial", "reference", "parallel"))
        figures[f"sim_render_cpu_ms_{name}"] = fast
        figures[f"sim_render_reference_cpu_ms_{name}"] = ref
        figures[f"sim_render_cpu_over_reference_{name}"] = fast / ref
        figures[f"sim_render_parallel_cpu_ms_{name}"] = par
        figures[f"sim_render_parallel_cpu_over_serial_{name}"] = par / fast
    return figures


def bench_calibration(geometry) -> dict:
    board = BoardSpec(9, 6, 0.020)
    poses = random_board_poses(geometry, 14, seed=8, square_m=board.square_m)
    pairs = render_board_pairs(geometry, poses, seed=8, square_m=board.square_m)
    result = calibrate_stereo(pairs, board)
    focal = []
    for cal, cam in ((result.left, geometry.left), (result.right, geometry.right)):
        focal += [abs(cal.camera_matrix[0, 0] / cam.K[0, 0] - 1), abs(cal.camera_matrix[1, 1] / cam.K[1, 1] - 1)]
    centre = []
    for cal, cam in ((result.left, geometry.left), (result.right, geometry.right)):
        centre += [abs(cal.camera_matrix[0, 2] - cam.K[0, 2]), abs(cal.camera_matrix[1, 2] - cam.K[1, 2])]
    baseline = abs(result.stereo.baseline_m / np.linalg.norm(geometry.translation) - 1)
    dR = result.stereo.rotation @ geometry.rotation.T
    return {"calib_focal_err_pct": 100 * max(focal), "calib_baseline_err_pct": 100 * baseline,
            "calib_rotation_err_deg": float(np.degrees(np.linalg.norm(cv2.Rodrigues(dR)[0]))),
            "calib_principal_err_px": max(centre), "calib_stereo_rms_px": result.stereo.rms_px,
            "calib_views": float(sum(v.used for v in result.views))}


def bench_capture() -> list:
    import rclpy
    from rclpy.context import Context
    from rclpy.executors import MultiThreadedExecutor
    from rclpy.parameter import Parameter

    from lsu_cameras.node import StereoCameraNode
    from lsu_interfaces.srv import CaptureStereo

    context = Context()
    rclpy.init(context=context)
    try:
        node = StereoCameraNode(context=context, parameter_overrides=[Parameter("sim_scene", value="head")])
        helper = rclpy.create_node("bench_cameras_client", context=context)
        executor = MultiThreadedExecutor(context=context)
        executor.add_node(node)
        executor.add_node(helper)
        client = helper.create_client(CaptureStereo, "/lsu/stereo/capture")
        while not client.service_is_ready():
            executor.spin_once(timeout_sec=0.05)

        def call() -> None:
            future = client.call_async(CaptureStereo.Request(publish=True))
            while not future.done():
                executor.spin_once(timeout_sec=0.01)
            assert future.result().success, future.result().message

        times = time_calls(call, repeat=30)
        executor.shutdown(timeout_sec=2.0)
        helper.destroy_node()
        node.destroy_node()
        return times
    finally:
        rclpy.try_shutdown(context=context)


def main() -> int:
    load_at_start = os.getloadavg()[0]
    geometry = load_rig()
    render_cpu = bench_render_cpu(geometry)
    render = bench_render(geometry)
    calib = bench_calibration(geometry)
    capture = bench_capture()
    figures = {
        "render_pair_ms_median": median(render["head"]),
        "render_pair_ms_p99": percentile(render["head"], 99),
        "render_pair_no_physics_ms_median": median(render["head_no_physics"]),
        "render_physics_over_no_physics": median(render["head"]) / median(render["head_no_physics"]),
        "render_pair_plane_ms_median": median(render["plane"]),
        "render_pair_plane_no_physics_ms_median": median(render["plane_no_physics"]),
        "render_pair_vibrating_ms_median": median(render["vibrating"]),
        "laser_truth_ms_median": median(render["truth"]),
        "capture_roundtrip_ms_median": median(capture),
        "capture_roundtrip_ms_p99": percentile(capture, 99),
        **render_cpu,
        **calib,
    }
    units = {k: "ms" for k in figures if k.endswith("_ms_median") or k.endswith("_ms_p99")}
    units["render_physics_over_no_physics"] = "ratio"
    units.update({k: "ms" for k in render_cpu if "_cpu_ms_" in k})
    units.update({k: "ratio" for k in render_cpu if "_over_" in k})
    units.update({"calib_focal_err_pct": "%", "calib_baseline_err_pct": "%", "calib_rotation_err_deg": "deg",
                  "calib_principal_err_px": "px", "calib_stereo_rms_px": "px", "calib_views": "views"})
    notes = ("Simulated rig (config/sim_rig.yaml), 640x480 stereo pair: render = laser term (speckle; skin "
             "scattering on the head) + blur + blooming + noise + quantisation on cached ray casts (head scene ~130k "
             "triangles), one position per call; no_physics = the same scene with speckle contrast 0, blooming 0 and "
             "surface material, timed in interleaved blocks in the same run. sim_render_cpu_ms_moving/settled: "
             "CPU per pair (process time) of head 7, moving at 180 steps/s (the fastest sweep, 8 sub-exposures "
             "in the reference) and settled, both views on one thread (parallel=False, as the camera stream "
             "renders); the reference render (reference=True: every sub-exposure, fresh noise over the whole "
             "image, every sensor step on the full image; also on one thread) and the two-thread render "
             "(parallel=True, a single capture's default; sim_render_parallel_cpu_*) in interleaved blocks of "
             "the same run, medians of 5 blocks of 6 pairs. Calibration: "
             "14 seeded random 9x6/20 mm board poses rendered by the sim, OpenCV calibrateCamera (k3 fixed) + "
             "stereoCalibrate; errors vs the rig's true geometry (focal = worst of fx, fy of both cameras). "
             "Capture round trip: CaptureStereo (publish=true, head scene) through an in-process "
             "MultiThreadedExecutor, client and node in one process. Host load average "
             f"{load_at_start:.1f} at the start, {os.getloadavg()[0]:.1f} at the end (2 cores, shared).")
    write_result("cameras", figures, units, notes)
    return 0


if __name__ == "__main__":
    sys.exit(main())
