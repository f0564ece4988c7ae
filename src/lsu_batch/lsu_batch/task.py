"""One bag reprocessed into files: the body of a batch task (runs in a Ray worker, or in any process).

The bag goes through the code path of `lsu run replay BAG` (`lsu_tools.direct_replay.DirectReplay`): the
``laser_extractor``, ``stereo_matcher`` and ``face_processor`` nodes of the ``replay`` launch file, with its
parameters, built in this process; the bag's images and events handed to the extractor and matcher
directly, the scan cloud the matcher publishes taken as the message it is, written as ``cloud.ply`` the way
the scan coordinator writes it, and handed to the face processor's own ``on_cloud`` (mesh files,
nose, signature). So a batch gives what the replay gives, to the bit (`test_batch` compares).

Output, in ``<out>/<name>/`` (only once complete: everything is written in ``<out>/.partial/`` and the folder
renamed into place, `DONE_FILE` last before the rename):

- ``cloud.ply`` (steps extract+match): the scan's points, as ``lsu scan`` writes them;
- ``lines.npz`` (step extract without match): every laser line, one row per detected image row;
- ``mesh.ply``, ``mesh.obj``, ``render_*.png`` (step mesh): the face processor's files;
- ``signature.bin`` (step face): `lsu_faces.signature.Signature.to_bytes`; the driver enrols it;
- ``result.json``: what was done (counts, times, notes); ``done.json``: the steps done (the marker).

The process keeps one rclpy context and one ROS domain of its own (claimed, `lsu_scan.rosenv.isolate`) for
all the bags it processes: nothing it builds sees another process's nodes, and nodes are built fresh per
bag (a replay's nodes hold the scan's state). OpenCV runs on one thread: the tasks are the parallelism.
Arrays never leave the process: the task returns a small dict (`BagResult.to_dict`).
"""

from __future__ import annotations

import io
import json
import os
import shutil
import tempfile
import time
import traceback
import uuid
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

__all__ = ["STEPS", "DONE_FILE", "PARTIAL_DIR", "BagJob", "BagResult", "BagFailure", "process_bag", "done_steps",
           "parse_steps", "process_context"]

STEPS = ("extract", "match", "mesh", "face")
DONE_FILE = "done.json"
PARTIAL_DIR = ".partial"  # under the output folder: bags being written (a killed run leaves some; the next removes them)
RESULT_FILE = "result.json"


class BagFailure(Exception):
    """The bag cannot be reprocessed; the message says why (and what to do where there is something to do)."""


def parse_steps(text: str) -> tuple[str, ...]:
    """``"extract,match,mesh"`` -> the steps in pipeline order; raises ValueError naming what is wrong."""
    names = [s.strip() for s in text.split(",") if s.strip()]
    unknown = [s for s in names if s not in STEPS]
    if unknown or not names:
        raise ValueError(f"unknown step(s) {', '.join(unknown) or '(none given)'}: choose from {','.join(STEPS)}")
    steps = tuple(s for s in STEPS if s in names)
    # each step works on what the one before made: points need lines, a mesh or a signature needs the points
    if "extract" not in steps:
        raise ValueError("every batch starts with 'extract' (the laser lines are made again from the images)")
    if ("mesh" in steps or "face" in steps) and "match" not in steps:
        raise ValueError("'mesh' and 'face' need the points: add 'match' (e.g. --steps extract,match,mesh,face)")
    return steps


@dataclass(frozen=True)
class BagJob:
    """What a task gets: paths and settings, never data."""

    bag: str                    # bag folder (or its .mcap/.db3 file)
    out_dir: str                # the batch's output folder
    name: str                   # the bag's folder under ``out_dir``
    steps: tuple[str, ...] = STEPS
    launch: str = "replay"      # launch file whose nodes (and parameters) process the bag
    launch_args: tuple[tuple[str, str], ...] = ()


@dataclass
class BagResult:
    """What a task returns (small; the files are in ``out_dir/name``)."""

    name: str
    bag: str
    status: str                  # "done" | "failed"
    reason: str = ""             # failed: why, one line
    detail: str = ""             # failed unexpectedly: the traceback
    scan_id: str = ""
    snaps: int = 0
    points: int = 0
    seconds: float = 0.0         # wall, whole task (nodes built, replay, files)
    cpu_s: float = 0.0           # CPU of the task's process during it
    replay_s: float = 0.0        # wall of the replay (`ReplayStats.seconds`)
    replay_cpu_s: float = 0.0    # its CPU (`ReplayStats.cpu_s`)
    face_s: float = 0.0          # wall of meshing, face and signature (and the mesh files)
    face_cpu_s: float = 0.0      # their CPU
    setup_s: float = 0.0         # wall of building the nodes (and, first time in a process, rclpy)
    is_face: bool = False
    notes: list[str] = field(default_factory=list)
    node_id: str = ""            # the Ray node that ran it (empty outside Ray)
    pid: int = 0

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)


_PROCESS: dict[str, Any] = {}  # this process's rclpy context and domain claim (module doc)


def process_context() -> Any:
    """The process's rclpy context, made on first use after claiming a ROS domain of its own."""
    if "context" not in _PROCESS:
        from lsu_scan import rosenv

        _PROCESS["claim"] = rosenv.isolate()  # before rclpy starts: DDS reads the domain at its first context
        import rclpy
        from rclpy.signals import SignalHandlerOptions

        context = rclpy.Context()
        # no signal handlers: the process belongs to Ray (or to its caller), which decides how it ends
        rclpy.init(context=context, signal_handler_options=SignalHandlerOptions.NO)
        _PROCESS["context"] = context
    return _PROCESS["context"]


def done_steps(folder: Path) -> tuple[str, ...] | None:
    """The steps a finished bag folder holds (its marker), or None when it is not finished."""
    try:
        return tuple(json.loads((folder / DONE_FILE).read_text())["steps"])
    except (OSError, ValueError, KeyError, TypeError):
        return None


def process_bag(job: BagJob, context: Any | None = None) -> dict[str, Any]:
    """Reprocess ``job.bag`` into ``job.out_dir/job.name`` (module doc); never raises for a bad bag.

    ``context``: an initialised rclpy context to build the nodes in (default: this process's own, made on
    first use with a ROS domain claimed for it). Returns `BagResult.to_dict`.
    """
    from lsu_extract.extractor import one_opencv_thread

    one_opencv_thread()
    t0, c0 = time.monotonic(), time.process_time()
    result = BagResult(name=job.name, bag=job.bag, status="failed", pid=os.getpid(), node_id=_ray_node_id())
    out = Path(job.out_dir)
    partial = out / PARTIAL_DIR / f"{job.name}.{os.getpid()}-{uuid.uuid4().hex[:8]}"
    # A Ray worker has a process group of its own, so killing a batch's process group leaves it running until
    # it sees its raylet gone; it must not put a bag in place for a run that no longer exists (the next run
    # decides from the done markers what to skip). Its parent changing is the sign.
    parent = os.getppid()
    try:
        partial.mkdir(parents=True)
        _reprocess(job, partial, context, result)
        if os.getppid() != parent:
            raise BagFailure("the batch that started this task ended before it finished; nothing was put in place")
        result.status = "done"
        result.seconds, result.cpu_s = time.monotonic() - t0, time.process_time() - c0
        (partial / RESULT_FILE).write_text(json.dumps(result.to_dict(), indent=1) + "\n")
        (partial / DONE_FILE).write_text(json.dumps({"steps": list(job.steps), "bag": job.bag}) + "\n")
        _commit(partial, out / job.name)
    except BagFailure as exc:
        result.status, result.reason = "failed", str(exc)
    except Exception as exc:  # noqa: BLE001 - one bag's fault is reported in the summary, never stops the others
        from lsu_bags.bags import BagError

        result.status = "failed"
        result.reason = f"{exc}" if isinstance(exc, BagError) else f"{exc.__class__.__name__}: {exc}"
        if not isinstance(exc, BagError):
            result.detail = traceback.format_exc()
    finally:
        shutil.rmtree(partial, ignore_errors=True)
    result.seconds, result.cpu_s = time.monotonic() - t0, time.process_time() - c0
    return result.to_dict()


def _ray_node_id() -> str:
    try:
        import ray

        return str(ray.get_runtime_context().get_node_id()) if ray.is_initialized() else ""
    except Exception:  # noqa: BLE001 - only a label in the summary
        return ""


def _commit(partial: Path, final: Path) -> None:
    """Put the finished folder in place in one rename; an older result of the bag (fewer steps) goes after."""
    old = None
    if final.exists():
        old = final.parent / PARTIAL_DIR / f"{final.name}.old-{uuid.uuid4().hex[:8]}"
        final.rename(old)
    partial.rename(final)
    if old is not None:
        shutil.rmtree(old, ignore_errors=True)


def _reprocess(job: BagJob, folder: Path, context: Any | None, result: BagResult) -> None:
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.parameter import Parameter

    from lsu_bags.ply import write_cloud_ply
    from lsu_bags.pointcloud2 import decode, from_msg
    from lsu_faces.node import FaceProcessorNode
    from lsu_tools.cli import resolve_launch_file
    from lsu_tools.direct_replay import DirectReplay
    from lsu_tools.launch_file import load_launch, select_nodes
    from lsu_tools.nodes_index import resolve_executable
    from lsu_tools.runner import build_nodes

    if not Path(job.bag).exists():
        raise BagFailure(f"bag '{job.bag}' not found (moved or deleted since the batch started?)")
    t0 = time.monotonic()
    context = context if context is not None else process_context()
    wanted = ["laser_extractor", "stereo_matcher"] + (["face_processor"] if "match" in job.steps and
                                                      {"mesh", "face"} & set(job.steps) else [])
    description = select_nodes(load_launch(resolve_launch_file(job.launch), dict(job.launch_args), resolve_executable),
                               wanted, [], {})
    log = io.StringIO()
    with tempfile.TemporaryDirectory(prefix="lsu-batch-params-") as params:
        nodes = build_nodes(description, Path(params), context=context, out=log)
    executor = SingleThreadedExecutor(context=context)
    try:
        for node in nodes:
            executor.add_node(node)
        replay = DirectReplay(nodes)
        faces = [n for n in nodes if isinstance(n, FaceProcessorNode)]
        for node in faces:  # it gets the cloud from this function only
            for sub in list(node.subscriptions):
                node.destroy_subscription(sub)
        clouds: list[Any] = []
        replay.matcher.cloud_pub.publish = clouds.append  # the scan cloud as `lsu run replay` publishes it
        lines: list[tuple[str, int, Any]] = []
        if "match" not in job.steps:
            from lsu_common import stamps

            # extraction only: the lines are kept instead of matched (the replay hands them to this method)
            replay.matcher.on_line_arrays = lambda side, header, arrays: lines.append(  # type: ignore[method-assign]
                (side, stamps.to_ns(header.stamp), arrays))
        result.setup_s = time.monotonic() - t0
        stats = replay.run(job.bag, spin=lambda: executor.spin_once(timeout_sec=0.0), workers=0)
        result.snaps, result.replay_s, result.replay_cpu_s = stats.snaps + stats.sweep_frames, stats.seconds, stats.cpu_s
        if stats.frames_dropped:
            result.notes.append(f"{stats.frames_dropped} frames unreadable")
        if "match" not in job.steps:
            if not stats.images:
                raise BagFailure(f"bag {job.bag} holds no images to extract lines from (it holds laser lines "
                                 f"already: run the 'match' step)")
            _write_lines(folder / "lines.npz", lines)
            return
        scan = replay.matcher.scan
        if scan is None:
            raise BagFailure(f"bag {job.bag} is not a recorded scan: no STARTED event on scan/events "
                             f"({stats.events} scan events, {stats.images} images); record scans with "
                             f"`lsu scan --record`")
        # a scan that ended short is published after the matcher's scan_timeout_s, as in `lsu run replay --exit`
        timeout = float(replay.matcher.get_parameter("scan_timeout_s").value) + 1.0
        deadline = time.monotonic() + timeout
        while replay.scan_pending() and time.monotonic() < deadline:
            executor.spin_once(timeout_sec=0.05)
        if not clouds:
            raise BagFailure(f"bag {job.bag}: scan '{scan.scan_id}' has no end (no FINISHED or ABORTED event): the "
                             f"recording was cut short; its {stats.snaps} snaps are not a scan cloud")
        msg = clouds[-1]
        result.scan_id = scan.scan_id
        if not scan.published or len(scan.snaps) < scan.expected:
            result.notes.append(f"partial scan: {len(scan.snaps)} of {scan.expected} snaps")
        columns = decode(from_msg(msg))
        result.points = len(columns["x"])
        write_cloud_ply(folder / "cloud.ply", columns, comment="lsu scan")
        if faces:
            face = faces[0]
            t1, c1 = time.monotonic(), time.process_time()
            face.set_parameters([Parameter("write_files", value="mesh" in job.steps)])
            face.scan_id, face.scan_dir = scan.scan_id, str(folder)
            face.on_cloud(msg)  # the face processor's own handling: mesh files, nose, signature
            result.face_s, result.face_cpu_s = time.monotonic() - t1, time.process_time() - c1
            if face.latest is None:
                result.notes.append(f"no mesh: {face.last_error}")
            else:
                result.notes.extend(face.latest.messages)
                signature = face.latest.signature
                result.is_face = signature is not None
                if signature is not None and "face" in job.steps:
                    (folder / "signature.bin").write_bytes(signature.to_bytes())
    finally:
        executor.shutdown(timeout_sec=1.0)
        for node in nodes:
            node.destroy_node()


def _write_lines(path: Path, lines: list[tuple[str, int, Any]]) -> None:
    """Every line as one row per detected image row: side (0 left, 1 right), stamp_ns, u, v, peak, width, quality."""
    import numpy as np

    def column(name: str, dtype: Any) -> Any:
        parts = []
        for _, _, arrays in lines:
            values = getattr(arrays, name)
            parts.append(np.full(len(arrays.u), np.nan) if values is None else np.asarray(values, dtype=dtype))
        return np.concatenate(parts).astype(dtype) if parts else np.zeros(0, dtype)

    counts = [len(arrays.u) for _, _, arrays in lines]
    np.savez(path, side=np.repeat(np.array([side == "right" for side, _, _ in lines], dtype=np.uint8), counts),
             stamp_ns=np.repeat(np.array([stamp for _, stamp, _ in lines], dtype=np.int64), counts),
             **{name: column(name, np.float64) for name in ("u", "v", "peak", "width", "quality")})
