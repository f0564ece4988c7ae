"""Stereo camera sources behind one interface: ``v4l2`` (OpenCV), ``folder`` (recorded pairs) and plug-ins.

A source returns a `StereoPair`: two BGR images exposed *after* the request, the capture time and
the measured left/right skew. Streams (`lsu_cameras.stream`): a *clocked* source (sim, folder) makes
the pair of a given frame slot (`StereoSource.pair_at`); a free-running one (v4l2) delivers pairs
at the devices' rate with their buffer stamps (`StereoSource.start_stream` / `next_pair`).
Other sources are plug-ins: a package registers a factory under the ``lsu.camera_sources`` entry point
group (the simulated rig: ``sim = lsu_sim.source:open_sim_source``), found by name with `open_plugin_source`,
so that this package never imports them.
Pure module (no rclpy): the node maps it onto topics and services.
"""

from __future__ import annotations

import abc
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from importlib.metadata import entry_points
from pathlib import Path
from typing import Any

import cv2

from lsu_common.arrays import AnyArray
from lsu_common.stamps import ns_to_seconds

from .profiles import Profile, apply_profile
from .stream import buffer_stamp_s


class CameraError(RuntimeError):
    """A camera cannot be opened or read (missing device/folder/file, unreadable image, size mismatch)."""


@dataclass
class StereoPair:
    """One synchronized pair."""

    left: AnyArray            # HxWx3 uint8 BGR
    right: AnyArray
    time_s: float               # capture time (source clock: wall or sim time) given to both images
    skew_s: float = 0.0         # right - left exposure time difference
    label: str = ""             # e.g. the folder pair's file suffix
    left_offset_s: float = 0.0  # left exposure start - time_s (the right one starts skew_s later)

    @property
    def right_offset_s(self) -> float:
        """Right exposure start - time_s."""
        return self.left_offset_s + self.skew_s


class StereoSource(abc.ABC):
    """A pair of cameras."""

    #: its pairs' ``time_s`` is the node's own clock (a simulated rig), not a device's wall time
    stamps_on_node_clock: bool = False
    #: clocked sources: how much later than `ready_after_s` a stream makes a frame (a source that renders from
    #: truth published late, see lsu_sim.source) [s]
    render_delay_s: float = 0.0

    @property
    @abc.abstractmethod
    def image_size(self) -> tuple[int, int]:
        """(width, height) of both images."""

    @abc.abstractmethod
    def grab_pair(self, timeout_s: float = 2.0) -> StereoPair:
        """A fresh pair exposed after this call started."""

    #: streams on a frame clock (`pair_at`) rather than at the devices' own rate (`next_pair`)
    clocked: bool = True

    @property
    def exposure_s(self) -> float:
        """Each camera's exposure time [s]; 0 when the source does not know it."""
        return 0.0

    @property
    def ready_after_s(self) -> float:
        """Clocked sources: how long after its slot a frame can exist (the end of its later exposure)."""
        return self.exposure_s

    def pair_at(self, stamp_ns: int, index: int) -> StereoPair:
        """Clocked sources: the pair of stream frame ``index`` exposed from ``stamp_ns`` (its stamp, integer ns)."""
        raise CameraError(f"{type(self).__name__} runs at its own rate and cannot make a frame for a given time")

    def start_stream(self, rate_hz: float) -> float:
        """Free-running sources: start delivering pairs at ``rate_hz``; returns the rate the devices run at."""
        raise CameraError(f"{type(self).__name__} streams on a frame clock (pair_at)")

    def next_pair(self, timeout_s: float) -> StereoPair:
        """Free-running sources: the next pair of the stream, stamped with its exposure start."""
        raise CameraError(f"{type(self).__name__} streams on a frame clock (pair_at)")

    def stop_stream(self) -> None:  # noqa: B027 (optional: clocked sources have nothing to stop)
        """Free-running sources: end the stream."""

    def close(self) -> None:  # noqa: B027 (optional: a source without devices keeps this no-op)
        """Release devices."""

    def report(self) -> list[str]:
        """Problems found while opening (e.g. profile read-back mismatches)."""
        return []


class FolderSource(StereoSource):
    """Replays ``left_*.png`` / ``right_*.png`` pairs in name order, looping."""

    def __init__(self, folder: str | Path, loop: bool = True) -> None:
        self.folder = Path(folder)
        if not self.folder.is_dir():
            raise CameraError(f"image folder '{self.folder}' not found (parameter 'folder')")
        lefts = {p.name[5:]: p for p in self.folder.glob("left_*.png")}
        rights = {p.name[6:]: p for p in self.folder.glob("right_*.png")}
        self.keys = sorted(set(lefts) & set(rights))
        if not self.keys:
            raise CameraError(f"'{self.folder}' holds no left_*.png/right_*.png pairs "
                              f"({len(lefts)} left, {len(rights)} right images)")
        self._paths = [(lefts[k], rights[k]) for k in self.keys]
        self.loop = loop
        self.index = 0
        first = self._read(*self._paths[0])
        self._size = (first[0].shape[1], first[0].shape[0])

    def _read(self, left: Path, right: Path) -> tuple[AnyArray, AnyArray]:
        images = []
        for path in (left, right):
            image = cv2.imread(str(path), cv2.IMREAD_COLOR)
            if image is None:
                raise CameraError(f"{path}: cannot be read as an image")
            images.append(image)
        if images[0].shape != images[1].shape:
            raise CameraError(f"{left.name} is {images[0].shape[1]}x{images[0].shape[0]} but {right.name} is "
                              f"{images[1].shape[1]}x{images[1].shape[0]}: a pair must have one size")
        return images[0], images[1]

    @property
    def image_size(self) -> tuple[int, int]:
        return self._size

    def pair_at(self, stamp_ns: int, index: int) -> StereoPair:
        """The folder's next pair, stamped with its slot (a folder streams its pairs in name order at the rate)."""
        pair = self.grab_pair()
        pair.time_s = ns_to_seconds(stamp_ns)
        return pair

    def grab_pair(self, timeout_s: float = 2.0) -> StereoPair:
        if self.index >= len(self._paths):
            if not self.loop:
                raise CameraError(f"'{self.folder}': all {len(self._paths)} pairs replayed")
            self.index = 0
        left_path, right_path = self._paths[self.index]
        label = self.keys[self.index]
        self.index += 1
        left, right = self._read(left_path, right_path)
        if (left.shape[1], left.shape[0]) != self._size:
            raise CameraError(f"{left_path.name} is {left.shape[1]}x{left.shape[0]}, the folder's first pair "
                              f"{self._size[0]}x{self._size[1]}")
        return StereoPair(left, right, time.time(), 0.0, Path(label).stem)


class V4l2Source(StereoSource):
    """Two UVC/V4L2 cameras through OpenCV (``cv2.CAP_V4L2``).

    To minimise skew both cameras are *grabbed* first (the exposure is latched) and only then
    *retrieved* (decoded); buffered frames that predate the request are flushed by grabbing and
    discarding ``flush_frames`` frames first. The skew is measured from the drivers' frame
    timestamps when they exist, else from the host time of each grab.
    """

    clocked = False

    def __init__(self, devices: Sequence[str | int], size: tuple[int, int] = (640, 480),
                 profile: Profile | None = None, flush_frames: int = 2,
                 opener: Callable[..., cv2.VideoCapture] = cv2.VideoCapture, latency_s: float = 0.0,
                 clocks: Callable[[], tuple[float, float]] = lambda: (time.time(), time.monotonic())) -> None:
        if len(devices) != 2:
            raise CameraError(f"need exactly two devices (left, right), got {list(devices)}")
        self.devices = list(devices)
        self.flush_frames = flush_frames
        self.latency_s = float(latency_s)
        self.clocks = clocks  # (wall, monotonic) read together, to move the drivers' monotonic stamps to wall time
        # V4L2's exposure_time_absolute (OpenCV CAP_PROP_EXPOSURE on CAP_V4L2) counts 100 us units; it is the
        # exposure only in manual mode (auto_exposure 1, V4L2_EXPOSURE_MANUAL); otherwise the source does not know it
        controls = profile.controls if profile is not None else {}
        exposure = float(controls.get("exposure", 0)) if controls.get("auto_exposure") == 1 else 0.0
        self._exposure_s = exposure * 1e-4 if exposure > 0 else 0.0
        self._problems: list[str] = []
        self._caps = []
        try:
            for side, dev in zip(("left", "right"), self.devices):
                target = int(dev) if isinstance(dev, int) or str(dev).isdigit() else str(dev)
                cap = opener(target, cv2.CAP_V4L2)
                if cap is None or not cap.isOpened():
                    raise CameraError(f"cannot open the {side} camera '{dev}' with V4L2: check that it is plugged "
                                      f"in, that `ls /dev/video*` lists it and that you may read it (group video)")
                self._caps.append(cap)
                cap.set(cv2.CAP_PROP_FRAME_WIDTH, size[0])
                cap.set(cv2.CAP_PROP_FRAME_HEIGHT, size[1])
                cap.set(cv2.CAP_PROP_BUFFERSIZE, 1)
                if profile is not None:
                    self._problems += [f"{side} camera: {p}" for p in apply_profile(cap, profile)]
            self._size = (int(self._caps[0].get(cv2.CAP_PROP_FRAME_WIDTH)), int(self._caps[0].get(cv2.CAP_PROP_FRAME_HEIGHT)))
            other = (int(self._caps[1].get(cv2.CAP_PROP_FRAME_WIDTH)), int(self._caps[1].get(cv2.CAP_PROP_FRAME_HEIGHT)))
            if other != self._size:
                raise CameraError(f"left camera gives {self._size[0]}x{self._size[1]} but right gives "
                                  f"{other[0]}x{other[1]}: set both to one size")
            if self._size != tuple(size):
                self._problems.append(f"requested {size[0]}x{size[1]}, cameras give {self._size[0]}x{self._size[1]}")
        except Exception:
            self.close()
            raise

    @property
    def image_size(self) -> tuple[int, int]:
        return self._size

    def report(self) -> list[str]:
        return list(self._problems)

    @property
    def exposure_s(self) -> float:
        return self._exposure_s

    def start_stream(self, rate_hz: float) -> float:
        rates = []
        for cap in self._caps:
            cap.set(cv2.CAP_PROP_FPS, float(rate_hz))
            rates.append(float(cap.get(cv2.CAP_PROP_FPS)))
        if min(rates) <= 0:
            return float(rate_hz)  # the driver does not say: the requested rate is the best guess
        if abs(rates[0] - rates[1]) > 1e-6 * max(rates):
            self._problems.append(f"left camera runs at {rates[0]:g} fps, right at {rates[1]:g} fps")
        return min(rates)

    def next_pair(self, timeout_s: float) -> StereoPair:
        """Grab both cameras (the exposures are latched first), stamp each from its buffer, then decode."""
        deadline = time.monotonic() + timeout_s
        starts: list[float] = []
        for side, dev, cap in zip(("left", "right"), self.devices, self._caps):
            if not cap.grab():
                raise CameraError(f"{side} camera '{dev}' returned no frame (unplugged?)")
            wall, mono = self.clocks()
            starts.append(buffer_stamp_s(float(cap.get(cv2.CAP_PROP_POS_MSEC)), wall, mono, self.latency_s))
            if time.monotonic() > deadline:
                raise CameraError(f"grabbing the pair took longer than {timeout_s} s")
        images = self._retrieve_pair()
        return StereoPair(images[0], images[1], starts[0], starts[1] - starts[0])

    def _retrieve_pair(self) -> list[AnyArray]:
        """Decode the frames both cameras have grabbed (left, right)."""
        images = []
        for side, cap in zip(("left", "right"), self._caps):
            ok, image = cap.retrieve()
            if not ok or image is None:
                raise CameraError(f"{side} camera: frame could not be decoded")
            images.append(image)
        return images

    def grab_pair(self, timeout_s: float = 2.0) -> StereoPair:
        deadline = time.monotonic() + timeout_s
        for _ in range(self.flush_frames):
            for cap in self._caps:
                cap.grab()
        stamps: list[tuple[float, float]] = []  # (host time, driver ms) per camera
        for side, cap in zip(("left", "right"), self._caps):
            if not cap.grab():
                raise CameraError(f"{side} camera '{self.devices[len(stamps)]}' returned no frame (unplugged?)")
            host = time.time()
            driver_ms = cap.get(cv2.CAP_PROP_POS_MSEC)
            stamps.append((host, driver_ms))
            if time.monotonic() > deadline:
                raise CameraError(f"grabbing the pair took longer than {timeout_s} s")
        images = self._retrieve_pair()
        if stamps[0][1] > 0 and stamps[1][1] > 0:
            skew = (stamps[1][1] - stamps[0][1]) / 1000.0
        else:
            skew = stamps[1][0] - stamps[0][0]
        return StereoPair(images[0], images[1], stamps[0][0], float(skew))

    def close(self) -> None:
        for cap in self._caps:
            cap.release()
        self._caps = []


PLUGIN_GROUP = "lsu.camera_sources"


@dataclass
class SourceContext:
    """What a plug-in source gets from the node that opens it (no rclpy types: plug-ins stay pure)."""

    parameter: Callable[[str], Any]   # the node's parameter value by name
    clock: Callable[[], float]        # the node's clock [s]
    # the ``sim/truth`` sample (lsu_interfaces/SimTruth) that held at t_ns (None before the first) and those after
    # it up to the end of the pair's exposures
    truth_at: Callable[[int], tuple[Any, list[Any]]]


def plugin_source_names() -> list[str]:
    """The names registered under ``lsu.camera_sources``."""
    return sorted({ep.name for ep in entry_points(group=PLUGIN_GROUP)})


def open_plugin_source(kind: str, context: SourceContext) -> StereoSource:
    """The plug-in source ``kind`` opened with ``context`` (CameraError when no installed package offers it)."""
    found = [ep for ep in entry_points(group=PLUGIN_GROUP) if ep.name == kind]
    if not found:
        names = ", ".join(["v4l2", "folder", *plugin_source_names()])
        raise CameraError(f"unknown source '{kind}': use one of {names} (plug-in sources are the packages' "
                          f"'{PLUGIN_GROUP}' entry points; is the package that offers '{kind}' installed?)")
    source = found[0].load()(context)
    if not isinstance(source, StereoSource):
        raise CameraError(f"source plug-in '{kind}' ({found[0].value}) made a {type(source).__name__}, not a StereoSource")
    return source
