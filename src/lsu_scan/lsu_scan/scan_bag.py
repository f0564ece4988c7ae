"""The scan's bag: its topics recorded into ``<scan folder>/bag`` on a private node with its own executor."""

from __future__ import annotations

import threading
from pathlib import Path
from typing import Any

import rclpy
from rclpy.executors import SingleThreadedExecutor

from lsu_bags.bags import LOW_SPACE_BYTES

# Not /lsu/sim/truth: simulation only, and ~1 ms of executor time per message in this process
# while the scan loop needs the CPU. The bag is for replaying the processing and for placing it
# in the rig's frames (/tf_static: rig, cameras, laser origin; /tf: the laser per driver state);
# `lsu bag record --all` still takes everything.
TOPICS = ["/lsu/scan/events", "/lsu/stereo/left/image_raw", "/lsu/stereo/right/image_raw",
          "/lsu/stereo/left/camera_info", "/lsu/stereo/right/camera_info", "/lsu/stereo/extrinsics",
          "/lsu/stereo/left/laser_line", "/lsu/stereo/right/laser_line", "/lsu/points", "/lsu/scan/cloud",
          "/lsu/scan/motion",
          "/lsu/driver/state", "/lsu/stereo/exposure", "/lsu/driver/carriage", "/tf", "/tf_static"]


def _open_elsewhere(file: Path) -> bool:
    """Some process (this one too) has ``file`` open (Linux /proc; elsewhere: assumed not)."""
    import os

    target = str(file.resolve())
    for fd_dir in Path("/proc").glob("[0-9]*/fd"):
        try:
            if any(os.readlink(fd) == target for fd in fd_dir.iterdir()):
                return True
        except OSError:
            continue
    return False


def recover_killed_scans(parent: Path, log: Any, quiet_s: float = 1.0) -> list[Path]:
    """The scans under ``parent`` whose bag recording was killed (the coordinator SIGKILLed mid-scan): each bag
    made whole again (`lsu_bags.bags.recover_bag`: every message stored before the kill) and, where the scan
    never wrote scan.json, one marked partial saying so; returns their folders. A bag still open by a process,
    or written to in the last ``quiet_s``, belongs to a running recording and is left alone."""
    import time

    from lsu_bags.bags import BagError, recover_bag, unfinished

    from .scan_plan import ScanRecord

    done: list[Path] = []
    for bag in sorted(parent.glob("*/bag")) if parent.is_dir() else []:
        if not unfinished(bag):
            continue
        file = next(bag.glob("*.mcap"))
        if time.time() - file.stat().st_mtime < quiet_s or _open_elsewhere(file):
            continue
        try:
            counts = recover_bag(bag)
        except (BagError, OSError) as exc:
            log.error(f"the bag {bag} of a scan that was killed could not be recovered: {exc}")
            continue
        folder = bag.parent
        if not (folder / "scan.json").exists():
            images = sum(n for topic, n in counts.items() if topic.endswith("image_raw")) // 2
            ScanRecord(scan_id=folder.name, started="", goal={}, parameters={}, calibration="", partial=True,
                       status=f"partial: the scan coordinator ended during this scan (killed); its bag was recovered "
                              f"with {sum(counts.values())} messages ({images} image pairs)",
                       files=[str(bag)]).write(folder)
        log.warning(f"scan {folder.name} was interrupted by a killed scan coordinator: its bag {bag} was recovered "
                    f"({sum(counts.values())} messages); scan.json marks it partial")
        done.append(folder)
    return done


# a scan stops before its next snap when less is free on the bag's disk: the images of the snap in flight (two
# ~1 MB frames) and the bag's own reserve (`lsu_bags.bags.LOW_SPACE_BYTES`) still fit
NEARLY_FULL_BYTES = LOW_SPACE_BYTES + (8 << 20)


def storage_problem(bag: ScanBag | None, folder: Path) -> str | None:
    """Why a scan cannot go on storing its data, or None: its folder is gone, or its bag stopped taking
    messages (a full disk). Checked before every snap: capturing on would only lose what is captured."""
    if not folder.is_dir():
        return (f"the scan folder {folder} was deleted during the scan; the scan stopped and wrote its files there "
                "again (the bag from its open file, with every image)" if bag is not None else
                f"the scan folder {folder} was deleted during the scan; the scan stopped and wrote scan.json there again")
    error = None if bag is None else bag.recorder.writer.error
    if error is not None:
        return f"the scan's bag cannot take more images: {error}; free space and scan again"
    free = None if bag is None else bag.recorder.writer.free_bytes
    if free is not None and free < NEARLY_FULL_BYTES:
        # stopped one snap before the bag must refuse images: the snap in flight is still stored whole
        return (f"the disk of {folder} is nearly full ({free / 1e6:.1f} MB free); the scan stopped with every "
                "captured image in its bag: free space and scan again")
    return None


class ScanBag:
    """Records `TOPICS` on a private node spun by its own single-threaded executor, from `start` to `stop`.

    Why not on the coordinator's node: the recorder's subscriptions would be destroyed (on close) while the
    multi-threaded executor builds its wait set in another thread, which rclpy answers with
    InvalidHandle out of spin(): the coordinator died after the scan and the result was lost.
    Its own executor is stopped before the subscriptions go; a single-threaded executor also
    costs less than half as much per recorded message.
    """

    def __init__(self, recorder: Any, node: Any, executor: SingleThreadedExecutor) -> None:
        self.recorder, self.node, self.executor = recorder, node, executor
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._spin, name="lsu-scan-bag", daemon=True)

    @classmethod
    def start(cls, parent: Any, folder: Path) -> ScanBag:
        """Start recording into ``folder/bag`` beside ``parent`` (the coordinator: its namespace, context, log)."""
        from lsu_bags.bag_cli import BagRecorder

        # no global arguments: the process's `-r __node:=scan_coordinator` would give it our name
        node = rclpy.create_node("_scan_coordinator_bag", namespace=parent.get_namespace(), context=parent.context,
                                 use_global_arguments=False, start_parameter_services=False)
        executor = SingleThreadedExecutor(context=parent.context)
        executor.add_node(node)
        try:
            # uncompressed (rosbag2's default): the sensor noise leaves camera images ~1.8x compressible
            # with zstd, and decompressing them costs a replay ~6x the CPU of reading them plain
            recorder = BagRecorder(node, TOPICS, folder / "bag", "mcap", compress=False,
                                   log=lambda text: parent.get_logger().info(text))
        except BaseException:
            executor.shutdown()
            node.destroy_node()
            raise
        bag = cls(recorder, node, executor)
        bag._thread.start()
        return bag

    def _spin(self) -> None:
        while not self._stop.is_set() and self.node.context.ok():
            self.executor.spin_once(timeout_sec=0.1)

    def stop(self) -> str:
        """Close the bag (its executor first); returns its path."""
        self._stop.set()
        self._thread.join(timeout=5.0)  # its executor no longer waits on the subscriptions closing below
        try:
            self.recorder.close()
        finally:
            self.executor.shutdown()
            self.node.destroy_node()
        return str(self.recorder.path)
