"""rosbag2 folders (mcap or sqlite3) read and written with the `rosbags` library.

Pure module: no rclpy. Messages travel as serialized CDR bytes; the bag carries each
type's message definition, which rosbags takes from its typestore: the built-in ROS 2
Jazzy types plus ``.msg`` files found on disk (``lsu_interfaces`` from the install's
``share`` folder or the source tree). What is written is a standard rosbag2 folder
(``metadata.yaml`` version 9 + one ``.mcap`` / ``.db3`` file), so ``ros2 bag`` and
rosbags' own readers open it, and bags of other tools read here.

Public API:

- :class:`BagWriter` — open a new bag, add topics as they appear, write bytes, close.
- :func:`read_messages` — iterate ``(topic, msgtype, timestamp_ns, cdr_bytes)`` of a bag.
- :func:`bag_info` / :func:`format_info` — what `lsu bag info` prints.
- :class:`BagTypes` — the typestore with ``.msg`` lookup; :func:`deserialize` /
  :func:`deserialize_ros` turn bytes into rosbags dataclasses / rclpy messages.
- :func:`playback_qos` — the QoS a player offers for a topic, from the recorded profiles.

Every failure the user can cause (missing or truncated bag, unknown type, existing output
folder) raises a :class:`BagError` (a ``ValueError``) with one line naming the file or topic,
the cause and what to do.
"""

from __future__ import annotations

import errno
import os
import queue
import re
import struct
import sys
import threading
from collections.abc import Callable, Iterable, Iterator, Sequence
from concurrent.futures import Future
from contextlib import contextmanager
from dataclasses import dataclass
from datetime import UTC, datetime
from pathlib import Path
from typing import Any, NamedTuple

import yaml
from rosbags.interfaces import (
    Connection,
    ConnectionExtRosbag2,
    Nodetype,
    Qos,
    QosDurability,
    QosHistory,
    QosLiveliness,
    QosReliability,
    QosTime,
)
from rosbags.rosbag2 import CompressionFormat, CompressionMode, Reader, ReaderError, StoragePlugin, Writer, WriterError
from rosbags.typesys import Stores, TypesysError, get_types_from_msg, get_typestore

from lsu_common import stamps

#: storage plugins we write (both are read)
STORAGES: tuple[str, ...] = ("mcap", "sqlite3")
#: rosbag2 metadata version written; 9 is what ROS 2 Jazzy's rosbag2 writes
BAG_VERSION = 9
#: a duration that means "infinite" in rosbag2 metadata (rmw's RMW_DURATION_INFINITE)
INFINITE_TIME = QosTime(9223372036, 854775807)
#: history depth offered on playback of volatile topics whose recorded depth is unknown
PLAY_DEPTH = 100


class BagError(ValueError):
    """A bag cannot be read or written; the message is one line for the user."""


class UnknownTypeError(BagError):
    """A message type has no definition: not in the typestore and no ``.msg`` file found."""


class BagMessage(NamedTuple):
    """One recorded message: serialized CDR ``data`` received at ``timestamp_ns``."""

    topic: str
    msgtype: str
    timestamp_ns: int
    data: bytes


@dataclass(frozen=True)
class TopicInfo:
    """One topic of a bag, as `lsu bag info` shows it."""

    name: str
    msgtype: str
    count: int
    serialization_format: str
    qos: tuple[Qos, ...]


@dataclass(frozen=True)
class BagInfo:
    """Summary of a bag (what ``ros2 bag info`` prints)."""

    path: Path
    files: tuple[str, ...]
    size_bytes: int
    storage: str
    ros_distro: str
    compression: str
    start_ns: int
    end_ns: int
    message_count: int
    topics: tuple[TopicInfo, ...]

    @property
    def duration_ns(self) -> int:
        """Time between the first and the last message."""
        return max(0, self.end_ns - self.start_ns) if self.message_count else 0


@dataclass(frozen=True)
class PlaybackQos:
    """QoS a player offers for one topic (rclpy-free; the node maps it onto a QoSProfile)."""

    reliable: bool
    transient_local: bool
    keep_all: bool
    depth: int


# ----------------------------------------------------------------------------- types
def default_msg_dirs() -> list[Path]:
    """Folders laid out ``<dir>/<pkg>/msg/<Name>.msg``: the install's share folders (ament layout)."""
    dirs = [Path(sys.prefix) / "share"]
    for prefix in os.environ.get("AMENT_PREFIX_PATH", "").split(os.pathsep):
        if prefix:
            dirs.append(Path(prefix) / "share")
    return dirs


def _referenced(desc: tuple[Any, Any]) -> Iterator[str]:
    """Type names a rosbags field descriptor refers to (nested through arrays and sequences)."""
    kind, rest = desc
    if kind == Nodetype.NAME:
        yield rest
    elif kind in (Nodetype.ARRAY, Nodetype.SEQUENCE):
        yield from _referenced(rest[0])


class BagTypes:
    """rosbags typestore for ROS 2 Jazzy that learns missing types from ``.msg`` files on disk.

    rosbags needs every type's definition to write a bag (schema + RIHS01 hash) and to
    deserialize; Jazzy's common types are built in, ours and other packages' are found as
    ``<dir>/<pkg>/msg/<Name>.msg`` in ``msg_dirs`` (default :func:`default_msg_dirs`).
    Thread-safe.
    """

    def __init__(self, msg_dirs: Sequence[Path] | None = None) -> None:
        self.typestore = get_typestore(Stores.ROS2_JAZZY)
        self.msg_dirs = [Path(d) for d in (default_msg_dirs() if msg_dirs is None else msg_dirs)]
        self._lock = threading.Lock()

    def known(self, msgtype: str) -> bool:
        """True when the typestore already has ``msgtype``."""
        return msgtype in self.typestore.fielddefs

    def _find_msg(self, msgtype: str) -> Path | None:
        parts = msgtype.split("/")
        if len(parts) != 3 or parts[1] != "msg":
            return None
        for base in self.msg_dirs:
            candidate = base / parts[0] / "msg" / f"{parts[2]}.msg"
            if candidate.is_file():
                return candidate
        return None

    def ensure(self, msgtype: str, topic: str | None = None) -> None:
        """Make ``msgtype`` (and every type it uses) known to the typestore.

        Raises:
            UnknownTypeError: no definition for ``msgtype`` or a type it uses.
            BagError: a ``.msg`` file does not parse or contradicts a known definition.
        """
        with self._lock:
            if self.known(msgtype):
                return
            found: dict[str, Any] = {}
            pending = [msgtype]
            while pending:
                name = pending.pop()
                if name in found or self.known(name):
                    continue
                path = self._find_msg(name)
                if path is None:
                    where = f"topic '{topic}' has type '{name}'" if name == msgtype and topic else \
                        f"type '{name}'" + (f" (used by '{msgtype}' on topic '{topic}')" if topic else
                                            f" (used by '{msgtype}')" if name != msgtype else "")
                    raise UnknownTypeError(
                        f"{where}, which is neither a ROS 2 Jazzy type nor defined by a .msg file in "
                        f"{', '.join(str(d) for d in self.msg_dirs)}; install its interface package "
                        f"(share/<pkg>/msg/<Name>.msg) or leave the topic out")
                try:
                    types = get_types_from_msg(path.read_text(), name)
                except (TypesysError, OSError, UnicodeDecodeError) as exc:
                    raise BagError(f"{path}: cannot parse the definition of '{name}': {exc}") from None
                found.update(types)
                for _consts, fields in types.values():
                    for _fname, desc in fields:
                        pending.extend(_referenced(desc))
            try:
                self.typestore.register(found)
            except TypesysError as exc:
                raise BagError(f"cannot register '{msgtype}': {exc}") from None

    def msgdef(self, msgtype: str) -> tuple[str, str]:
        """``(ros2msg definition text, RIHS01 hash)`` of a known type, as stored in the bag."""
        text, _ = self.typestore.generate_msgdef(msgtype, ros_version=2)
        return text, self.typestore.hash_rihs01(msgtype)


# ------------------------------------------------------------------------------- QoS
def make_qos(reliability: str, durability: str, history: str = "unknown", depth: int = 0) -> Qos:
    """A rosbags Qos from policy names (rclpy's enum names in lower case) with infinite times."""
    def member(enum: Any, value: str) -> Any:
        try:
            return enum.__members__[value.upper()]
        except KeyError:
            return enum.UNKNOWN

    return Qos(member(QosHistory, history), int(depth), member(QosReliability, reliability),
               member(QosDurability, durability), INFINITE_TIME, INFINITE_TIME, QosLiveliness.AUTOMATIC,
               INFINITE_TIME, False)


def playback_qos(profiles: Sequence[Qos]) -> PlaybackQos:
    """QoS to offer when playing a topic recorded with these publisher profiles.

    Like rosbag2: reliable only when every recorded publisher was reliable (a best-effort
    subscriber still matches), transient-local only when every one latched (so latched
    topics stay latched). History/depth: DDS discovery does not carry them, so bags made
    from the graph say "unknown"; then a latched topic keeps 1 (the project's convention
    for latched outputs) and a volatile one PLAY_DEPTH, so a burst at a high --rate does not
    overwrite reliable samples still in flight. A recorded depth is never lowered.
    """
    if not profiles:
        return PlaybackQos(reliable=True, transient_local=False, keep_all=False, depth=PLAY_DEPTH)
    reliable = all(p.reliability == QosReliability.RELIABLE for p in profiles)
    transient = all(p.durability == QosDurability.TRANSIENT_LOCAL for p in profiles)
    keep_all = any(p.history == QosHistory.KEEP_ALL for p in profiles)
    recorded = max((p.depth for p in profiles if p.history == QosHistory.KEEP_LAST), default=0)
    depth = max(recorded, 1 if transient else PLAY_DEPTH)
    return PlaybackQos(reliable=reliable, transient_local=transient, keep_all=keep_all, depth=depth)


# ----------------------------------------------------------------------------- writer
class _WriterThread:
    """One thread that runs the bag's storage calls in submission order.

    Why not ``concurrent.futures.ThreadPoolExecutor``: its workers quit when the interpreter starts
    exiting (and the executor then refuses work), but a scan thread still running after the
    main thread returned on Ctrl-C must be able to finish the bag -- it did not, and the scan's
    bag and scan.json were lost. This thread is a daemon so a bag nobody closes never blocks exit.
    """

    def __init__(self, name: str) -> None:
        self._queue: queue.SimpleQueue[tuple[Future, Callable[..., Any], tuple, dict] | None] = \
            queue.SimpleQueue()
        self._closed = False
        self._thread = threading.Thread(target=self._run, name=name, daemon=True)
        self._thread.start()

    def _run(self) -> None:
        while True:
            item = self._queue.get()
            if item is None:
                return
            future, fn, args, kwargs = item
            if not future.set_running_or_notify_cancel():
                continue
            try:
                future.set_result(fn(*args, **kwargs))
            except BaseException as exc:  # noqa: BLE001 - handed to whoever waits on the future
                future.set_exception(exc)

    def submit(self, fn: Callable[..., Any], *args: Any, **kwargs: Any) -> Future:
        """Queue ``fn(*args, **kwargs)``; its result or exception arrives in the returned future."""
        if self._closed:
            raise RuntimeError("the bag's writer thread was stopped")
        future: Future = Future()
        self._queue.put((future, fn, args, kwargs))
        return future

    def shutdown(self, wait: bool = True) -> None:
        """Let the queued calls finish, then stop the thread (joined with ``wait``)."""
        if not self._closed:
            self._closed = True
            self._queue.put(None)
        if wait and self._thread is not threading.current_thread():
            self._thread.join()


# a message that would leave less free on the bag's disk is not written and the bag stops there (`BagWriter.error`):
# the open chunk (up to ~2 MiB with an image), the index and metadata.yaml must still fit when it is closed, or
# the whole bag could not be opened
LOW_SPACE_BYTES = 8 << 20


class BagWriter:
    """A new rosbag2 folder, written while topics appear; thread-safe.

    ``with BagWriter(out_dir, "mcap", compress=True) as bag: bag.add_topic(...); bag.write(...)``.
    Compression (zstd) is what rosbag2 does per storage: mcap compresses its chunks
    (readers decompress transparently), sqlite3 compresses each message
    (``compression_mode: message`` in metadata.yaml).

    Every rosbags call runs on one private thread: sqlite connections only work in the thread
    that made them (subscription callbacks of a MultiThreadedExecutor come from many), and
    disk I/O then never stalls a callback. :meth:`write` only queues; :meth:`close` drains.
    """

    def __init__(self, out_dir: Path | str, storage: str = "mcap", *, compress: bool = False,
                 types: BagTypes | None = None) -> None:
        if storage not in STORAGES:
            raise BagError(f"unknown storage '{storage}'; use one of: {', '.join(STORAGES)}")
        self.path = Path(out_dir)
        if self.path.exists():
            raise BagError(f"output folder {self.path} exists already; choose another -o or remove it "
                           f"(a bag is never overwritten)")
        self.storage = storage
        self.types = types or BagTypes()
        self._io = _WriterThread("lsu-bag-writer")
        self._connections: dict[str, Connection] = {}
        self._lock = threading.Lock()
        self.counts: dict[str, int] = {}
        self._error: BaseException | None = None
        self._open = False
        self._kept_fd: int | None = None  # the storage file, read-only: its data outlives a deleted folder
        self.free_bytes: int | None = None  # free on the bag's disk at the last write (None before the first)
        plugin = StoragePlugin.MCAP if storage == "mcap" else StoragePlugin.SQLITE3
        mode = (CompressionMode.STORAGE if storage == "mcap" else CompressionMode.MESSAGE) if compress else None
        try:
            self._writer: Writer = self._io.submit(self._create, plugin, mode).result()
        except (WriterError, OSError) as exc:
            self._io.shutdown(wait=False)
            raise BagError(f"cannot create bag {self.path}: {exc}") from None
        self._open = True

    def _create(self, plugin: StoragePlugin, mode: CompressionMode | None) -> Writer:
        writer = Writer(self.path, version=BAG_VERSION, storage_plugin=plugin)
        if mode is not None:
            writer.set_compression(mode, CompressionFormat.ZSTD)
        writer.open()
        storage = getattr(writer.storage, "path", None)
        if storage is not None and self.storage == "mcap":  # sqlite keeps journals beside its file: not kept
            self._kept_fd = os.open(storage, os.O_RDONLY)
        return writer

    @property
    def error(self) -> str | None:
        """Why the bag stopped taking messages (a write failed, the disk is nearly full), or None: said at once
        so that a caller stops capturing data that cannot be stored (`close` raises it too)."""
        return None if self._error is None else str(self._error)

    def __enter__(self) -> BagWriter:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    @property
    def topics(self) -> dict[str, str]:
        """Topic -> type of every topic added so far."""
        with self._lock:
            return {name: conn.msgtype for name, conn in self._connections.items()}

    def add_topic(self, topic: str, msgtype: str, qos_profiles: Sequence[Qos] = ()) -> None:
        """Declare a topic (its definition goes into the bag); ``qos_profiles``: the publishers' QoS.

        Raises:
            UnknownTypeError: no definition for ``msgtype``.
            BagError: the topic was already added with another type, or the bag is closed.
        """
        self.types.ensure(msgtype, topic)
        msgdef, rihs01 = self.types.msgdef(msgtype)
        with self._lock:
            if not self._open:
                raise BagError(f"bag {self.path} is closed; cannot add topic '{topic}'")
            if topic in self._connections:
                if self._connections[topic].msgtype != msgtype:
                    raise BagError(f"topic '{topic}' is already recorded as {self._connections[topic].msgtype}, "
                                   f"not {msgtype}")
                return
            self._connections[topic] = self._io.submit(
                self._writer.add_connection, topic, msgtype, msgdef=msgdef, rihs01=rihs01,
                offered_qos_profiles=list(qos_profiles)).result()
            self.counts[topic] = 0

    def write(self, topic: str, timestamp_ns: int, data: bytes | memoryview) -> None:
        """Queue one serialized message of an added topic (written in call order)."""
        with self._lock:
            if not self._open:
                return  # late callbacks after close are dropped on purpose: the bag is final
            try:
                connection = self._connections[topic]
            except KeyError:
                raise BagError(f"topic '{topic}' was not added to bag {self.path} (call add_topic first)") from None
            self._io.submit(self._write, connection, int(timestamp_ns), bytes(data))
            self.counts[topic] += 1

    def _write(self, connection: Connection, timestamp_ns: int, data: bytes) -> None:
        if self._error is not None:
            return
        try:
            vfs = os.statvfs(self.path) if self._kept_fd is None else os.fstatvfs(self._kept_fd)
            free = self.free_bytes = vfs.f_bavail * vfs.f_frsize
            if free - len(data) < LOW_SPACE_BYTES:
                raise OSError(errno.ENOSPC, f"the disk of {self.path} is full ({free / 1e6:.1f} MB free, "
                                            f"{LOW_SPACE_BYTES >> 20} MiB are kept to close the bag); the bag holds "
                                            "the messages before")
            self._writer.write(connection, timestamp_ns, data)
        except Exception as exc:  # kept and raised by close(): a write has no caller left to tell
            self._error = exc

    def _restore(self) -> None:
        """The storage file, deleted with its folder while open and finished since, copied back beside the new
        metadata.yaml (atomically: a copy cut short is never taken for the bag)."""
        assert self._kept_fd is not None
        target = self.path / f"{self.path.name}.mcap"
        tmp = target.with_suffix(".mcap.tmp")
        with open(os.dup(self._kept_fd), "rb") as src, open(tmp, "wb") as dst:
            src.seek(0)
            while chunk := src.read(1 << 20):
                dst.write(chunk)
        tmp.replace(target)

    def close(self) -> None:
        """Write what is queued, finish the storage file and write metadata.yaml; idempotent.

        Raises:
            BagError: a queued write failed (disk full, ...); the bag is closed anyway.
        """
        with self._lock:
            if not self._open:
                return
            self._open = False
        deleted = self._kept_fd is not None and os.fstat(self._kept_fd).st_nlink == 0
        try:
            if deleted:  # deleted while recording (the folder, or the file): the data is still in the open file
                self.path.mkdir(parents=True, exist_ok=True)
            self._io.submit(self._writer.close).result()
            if deleted:
                self._restore()
        except (WriterError, OSError) as exc:
            raise BagError(f"bag {self.path}: cannot finish the bag ({exc})") from None
        finally:
            self._io.shutdown(wait=True)
            if self._kept_fd is not None:
                os.close(self._kept_fd)
                self._kept_fd = None
        if self._error is not None:
            raise BagError(f"bag {self.path}: writing a message failed ({self._error}); the bag was closed "
                           f"with the messages before it")


# ----------------------------------------------------------------------------- reader
_READ_ERRORS: tuple[type[Exception], ...] = (ReaderError, OSError, EOFError, KeyError, IndexError, AssertionError,
                                  struct.error, ValueError, TypeError)
try:  # sqlite3 storage errors come from apsw (a rosbags dependency)
    import apsw

    _READ_ERRORS += (apsw.Error,)
except ImportError:  # pragma: no cover - rosbags without sqlite support
    pass


def _storage_files(path: Path) -> str:
    """Names of the storage files a bag folder lists (for error messages); the folder if unknown."""
    try:
        meta = yaml.safe_load((path / "metadata.yaml").read_text())
        files = meta["rosbag2_bagfile_information"]["relative_file_paths"]
        return ", ".join(str(path / Path(f).name) for f in files) or str(path)
    except Exception:  # any problem here is reported by the reader itself; this is only a label
        return str(path)


@contextmanager
def open_bag(bag_dir: Path | str) -> Iterator[Reader]:
    """An open rosbags ``Reader`` of a bag folder (or a single .mcap/.db3 file).

    Raises:
        BagError: the path is missing, has no metadata.yaml, or a file is truncated/corrupt.
    """
    path = Path(bag_dir)
    if not path.exists():
        raise BagError(f"bag {path} does not exist (give the folder `lsu bag record -o` created)")
    if path.is_dir() and not (path / "metadata.yaml").is_file():
        raise BagError(f"{path / 'metadata.yaml'} is missing: not a rosbag2 folder, or its recording was killed "
                       f"before it could close (stop `lsu bag record` with Ctrl-C or SIGTERM; a killed recording "
                       f"is made whole by `lsu_bags.bags.recover_bag`, which the scan coordinator runs on its scans "
                       f"when it starts)")
    try:
        reader = Reader(path)
        reader.open()
    except _READ_ERRORS as exc:
        if path.is_dir() and (problem := _metadata_problem(path, exc)):
            raise BagError(problem) from None
        raise BagError(f"{_storage_files(path) if path.is_dir() else path}: cannot open the bag, the file is "
                       f"truncated or corrupt ({_cause(exc)})") from None
    try:
        yield reader
    finally:
        reader.close()


#: rosbags' words for a metadata.yaml it cannot use (any other open error is the storage's)
_METADATA_ERRORS = ("Could not load YAML", "A metadata key is missing", "Invalid bag metadata", "Rosbag2 version",
                    "Storage plugin", "Some database files are missing", "Could not read metadata")


def _metadata_problem(path: Path, exc: BaseException) -> str | None:
    """The message for a bag folder whose metadata.yaml (not its storage) is broken, else None.

    The storage file of a rosbag2 folder holds every message with its topic and type (mcap also
    the definitions), so it is readable without the metadata: say so, and whether it opens.
    """
    meta = path / "metadata.yaml"
    try:
        yaml.safe_load(meta.read_text())
    except yaml.YAMLError as err:
        mark = getattr(err, "problem_mark", None)
        cause = f"not valid YAML{f' at line {mark.line + 1}' if mark is not None else ''}: {getattr(err, 'problem', err)}"
    except (OSError, UnicodeDecodeError) as err:
        cause = f"cannot be read ({err})"
    else:
        if not str(exc).startswith(_METADATA_ERRORS):
            return None
        cause = _cause(exc)
    storage = sorted(p for p in path.iterdir() if p.suffix in (".mcap", ".db3"))
    if not storage:
        return f"{meta}: {cause}; and the folder holds no .mcap or .db3 storage file to read instead"
    readable = []
    for file in storage:
        try:
            direct = Reader(file)
            direct.open()
            direct.close()
            readable.append(file)
        except _READ_ERRORS:
            continue
    if readable:
        return (f"{meta}: {cause}; the storage file can be opened directly: `lsu bag play {readable[0]}` "
                f"(or `lsu bag info {readable[0]}`)")
    return (f"{meta}: {cause}; the storage file{'s' if len(storage) > 1 else ''} "
            f"{', '.join(str(f) for f in storage)} can be given directly, but do{'' if len(storage) > 1 else 'es'} "
            f"not open either (truncated or corrupt)")


def _cause(exc: BaseException) -> str:
    text = str(exc).strip().rstrip(".") or type(exc).__name__
    # rosbags repeats the file name we already lead with
    text = re.sub(r"^Cannot open database [^:]+: ", "", text)
    return text.splitlines()[0]


def read_messages(bag_dir: Path | str, topics: Iterable[str] | None = None) -> Iterator[BagMessage]:
    """Messages of a bag in timestamp order, optionally only those of ``topics``.

    Raises:
        BagError: missing/corrupt bag (also mid-way: a file cut short), or a requested topic
            that the bag does not have.
    """
    path = Path(bag_dir)
    with open_bag(path) as reader:
        connections = _select(reader, path, topics)
        if not connections:
            return
        iterator = reader.messages(connections=connections)
        seen: dict[int, int] = {}
        while True:
            try:
                connection, timestamp, data = next(iterator)
            except StopIteration:
                break
            except _READ_ERRORS as exc:
                raise BagError(f"{_storage_files(path) if path.is_dir() else path}: cannot read a message, the file "
                               f"is truncated or corrupt ({_cause(exc)})") from None
            seen[connection.id] = seen.get(connection.id, 0) + 1
            yield BagMessage(connection.topic, connection.msgtype, timestamp, bytes(data))
        # a storage file that lost rows without breaking its structure reads "fine": the counts tell
        for connection in connections:
            if path.is_dir() and seen.get(connection.id, 0) != connection.msgcount:
                raise BagError(f"{_storage_files(path)}: topic {connection.topic} has {seen.get(connection.id, 0)} of "
                               f"the {connection.msgcount} messages metadata.yaml lists; the file is truncated or "
                               f"corrupt")


def read_message_views(bag_dir: Path | str, topics: Iterable[str] | None = None) -> Iterator[BagMessage]:
    """`read_messages`, with each message's ``data`` a read-only memoryview into the storage file, not a copy.

    For a bag of one uncompressed MCAP file (what the scan coordinator records): the file is mapped
    and each message's CDR bytes are handed out where they lie, so a 900 KB image reaches the
    extractor without being copied. Hand-written because rosbags copies every message three times
    (chunk, record, payload) and checksums each chunk, about a tenth of what extracting the image
    costs; the `mcap` library copies too. Any other bag (compressed chunks, sqlite3, several files)
    is read by `read_messages`. The views keep the mapping alive; the file must not be rewritten
    while they are in use. The same messages in the same order as `read_messages` (by receive time,
    file order among equal times), and the same errors.
    """
    path = Path(bag_dir)
    with open_bag(path) as reader:  # the same checks and errors as read_messages (missing topics, metadata)
        connections = _select(reader, path, topics)
        whole_file_compressed = reader.compression_mode not in (None, "", "none")
    files = sorted(path.glob("*.mcap")) if path.is_dir() else [path]
    plain = len(files) == 1 and files[0].suffix == ".mcap" and not whole_file_compressed
    located = _mcap_views(files[0], {c.topic: c for c in connections}) if plain and connections else None
    if located is None:
        yield from read_messages(path, topics)
        return
    for connection in connections:
        count = sum(1 for m in located if m.topic == connection.topic)
        if path.is_dir() and count != connection.msgcount:
            raise BagError(f"{_storage_files(path)}: topic {connection.topic} has {count} of the "
                           f"{connection.msgcount} messages metadata.yaml lists; the file is truncated or corrupt")
    located.sort(key=lambda m: m.timestamp_ns)  # stable: file order among equal receive times, as rosbags gives
    yield from located


_MCAP_MAGIC = b"\x89MCAP0\r\n"
_MCAP_SCHEMA, _MCAP_CHANNEL, _MCAP_MESSAGE, _MCAP_CHUNK, _MCAP_DATA_END = 0x03, 0x04, 0x05, 0x06, 0x0F
_U16, _U32, _U64 = struct.Struct("<H"), struct.Struct("<I"), struct.Struct("<Q")


class _McapCut(Exception):
    """A record runs past the end of its buffer (the file is cut short or corrupt there); ``at``: its offset."""

    def __init__(self, at: int) -> None:
        super().__init__(at)
        self.at = at


class _McapCompressed(Exception):
    """A compressed chunk, met where the records are wanted in place (no view can point into it)."""


def _mcap_records(buffer: Any, start: int, stop: int, decompress: bool = False) -> Iterator[tuple[int, Any, int, int]]:
    """Every record of ``buffer[start:stop]`` as (opcode, buffer, body start, body end), in file order, with the
    records of each chunk in its place, up to the Data End record.

    MCAP: magic, then records (opcode u8, length u64, content); Chunk records hold start/end time, uncompressed
    size, crc, compression (string) and records. A compressed chunk is decompressed (rosbags' decompressors)
    with ``decompress``, else raises `_McapCompressed`; a record that runs past ``stop`` raises `_McapCut`.
    Hand-written: rosbags reads only finished files, and neither reader hands out views of the mapped file.
    """
    pos = start
    while pos + 9 <= stop:
        op, length = buffer[pos], _U64.unpack_from(buffer, pos + 1)[0]
        body, pos = pos + 9, pos + 9 + length
        if op == _MCAP_CHUNK and pos <= stop:
            compression_length = _U32.unpack_from(buffer, body + 28)[0]
            if compression_length and not decompress:
                raise _McapCompressed()
            inner = body + 32 + compression_length
            size = _U64.unpack_from(buffer, inner)[0]
            if inner + 8 + size > pos:
                raise _McapCut(body - 9)
            if not compression_length:
                yield from _mcap_records(buffer, inner + 8, inner + 8 + size, decompress)
                continue
            from rosbags.rosbag2.storage_mcap import DECOMPRESSORS

            compression = bytes(buffer[body + 32:inner]).decode()
            records = DECOMPRESSORS[compression](buffer[inner + 8:inner + 8 + size],
                                                 _U64.unpack_from(buffer, body + 16)[0])
            yield from _mcap_records(records, 0, len(records), decompress)
            continue
        if pos > stop:
            raise _McapCut(body - 9)
        if op == _MCAP_DATA_END:
            return
        yield op, buffer, body, pos


def _mcap_string(buffer: Any, at: int) -> tuple[str, int]:
    """The MCAP string (u32 length, UTF-8) at ``at`` and the offset after it."""
    n = _U32.unpack_from(buffer, at)[0]
    return bytes(buffer[at + 4:at + 4 + n]).decode(), at + 4 + n


def _mcap_views(file: Path, wanted: dict[str, Connection]) -> list[BagMessage] | None:
    """The messages of ``wanted`` topics in one MCAP file as views of the mapped file, in file order;
    None where a chunk is compressed (the caller then reads with rosbags).

    Channel records name a channel's topic; Message records hold channel id u16, sequence u32, log time u64,
    publish time u64 and the data (`_mcap_records` walks the file).
    """
    import mmap

    with open(file, "rb") as handle:
        mapped = mmap.mmap(handle.fileno(), 0, access=mmap.ACCESS_READ)
    buffer = memoryview(mapped)
    if buffer[:8] != _MCAP_MAGIC:
        return None
    topics: dict[int, Connection | None] = {}
    out: list[BagMessage] = []
    try:
        for op, data, body, end in _mcap_records(buffer, 8, len(buffer)):
            if op == _MCAP_MESSAGE:
                connection = topics.get(_U16.unpack_from(data, body)[0])
                if connection is not None:
                    out.append(BagMessage(connection.topic, connection.msgtype, _U64.unpack_from(data, body + 6)[0],
                                          data[body + 22:end]))  # a view, not bytes
            elif op == _MCAP_CHANNEL:
                topics[_U16.unpack_from(data, body)[0]] = wanted.get(_mcap_string(data, body + 4)[0])
    except _McapCut as cut:
        raise BagError(f"{file}: cannot read a message, the file is truncated or corrupt (record at byte {cut.at} "
                       f"runs past the end)") from None
    except _McapCompressed:
        return None
    return out


def unfinished(bag_dir: Path | str) -> bool:
    """A bag folder whose recording never closed (killed): one MCAP file and no metadata.yaml."""
    path = Path(bag_dir)
    return path.is_dir() and not (path / "metadata.yaml").exists() and len(list(path.glob("*.mcap"))) == 1


def recover_bag(bag_dir: Path | str, types: BagTypes | None = None) -> dict[str, int]:
    """Make the bag of a killed recording (`unfinished`) a complete one: every message whose record is whole
    in the MCAP file, the file's index and metadata.yaml; returns the messages per topic.

    A killed writer leaves records up to its last write and no summary or footer, which rosbags needs to open
    the file. The complete records are read in file order (stopping at the first one cut short), written into a
    new bag beside it with the channels' types and QoS, and the new bag replaces the folder (renamed: the folder
    is never half recovered). Hand-written: rosbags reads only finished files and the `mcap` library is no
    dependency; `_mcap_records` walks the file, as for `_mcap_views`.

    Raises:
        BagError: not an unfinished bag, or not an MCAP file.
    """
    import shutil

    from rosbags.rosbag2.storage_mcap import get_qos

    path = Path(bag_dir)
    if not unfinished(path):
        raise BagError(f"{path} is not the bag of a killed recording (one .mcap file, no metadata.yaml)")
    import mmap

    with open(next(path.glob("*.mcap")), "rb") as handle:
        data: Any = mmap.mmap(handle.fileno(), 0, access=mmap.ACCESS_READ) if handle.seek(0, 2) else b""
    if data[:8] != _MCAP_MAGIC:
        raise BagError(f"{path}: not an MCAP file, cannot recover it")
    schemas: dict[int, str] = {}
    channels: dict[int, tuple[str, str, list[Qos]]] = {}  # id -> topic, type, offered QoS
    messages: list[tuple[int, int, bytes]] = []  # channel, log time, data
    try:
        for op, buffer, body, end in _mcap_records(data, 8, len(data), decompress=True):
            if op == _MCAP_SCHEMA:  # id, name, encoding, data
                schemas[_U16.unpack_from(buffer, body)[0]] = _mcap_string(buffer, body + 2)[0]
            elif op == _MCAP_CHANNEL:  # id, schema id, topic, message encoding, metadata
                topic, at = _mcap_string(buffer, body + 4)
                _encoding, at = _mcap_string(buffer, at)
                size = _U32.unpack_from(buffer, at)[0]
                channels[_U16.unpack_from(buffer, body)[0]] = (
                    topic, schemas.get(_U16.unpack_from(buffer, body + 2)[0], ""),
                    get_qos(bytes(buffer[at + 4:at + 4 + size])))
            elif op == _MCAP_MESSAGE:
                messages.append((_U16.unpack_from(buffer, body)[0], _U64.unpack_from(buffer, body + 6)[0],
                                 bytes(buffer[body + 22:end])))
    except _McapCut:
        pass  # cut short by the kill: nothing after it was stored
    staging = path.parent / f".{path.name}.recovering"
    shutil.rmtree(staging, ignore_errors=True)
    counts: dict[str, int] = {}
    with BagWriter(staging / path.name, "mcap", types=types) as out:
        for topic, msgtype, qos in channels.values():
            out.add_topic(topic, msgtype, qos)
            counts[topic] = 0
        for channel, stamp, payload in messages:
            if channel in channels:
                out.write(channels[channel][0], stamp, payload)
                counts[channels[channel][0]] += 1
    aside = path.parent / f".{path.name}.unfinished"
    path.rename(aside)
    (staging / path.name).rename(path)
    shutil.rmtree(aside, ignore_errors=True)
    shutil.rmtree(staging, ignore_errors=True)
    return counts


def _select(reader: Reader, path: Path, topics: Iterable[str] | None) -> list[Connection]:
    if topics is None:
        return list(reader.connections)
    wanted = set(topics)
    have = {c.topic for c in reader.connections}
    if missing := sorted(wanted - have):
        raise BagError(f"bag {path} has no topic {', '.join(missing)} (it has: {', '.join(sorted(have)) or 'none'})")
    return [c for c in reader.connections if c.topic in wanted]


def bag_topics(bag_dir: Path | str) -> dict[str, tuple[str, tuple[Qos, ...]]]:
    """Topic -> (type, recorded publisher QoS profiles) of a bag."""
    with open_bag(bag_dir) as reader:
        return {c.topic: (c.msgtype, tuple(c.ext.offered_qos_profiles) if isinstance(c.ext, ConnectionExtRosbag2)
                          else ()) for c in reader.connections}


def stored_definitions(bag_dir: Path | str) -> dict[str, tuple[str, str]]:
    """Topic -> (type, the ``ros2msg`` definition stored in the bag, '' when it holds none or IDL)."""
    from rosbags.interfaces import MessageDefinitionFormat

    with open_bag(bag_dir) as reader:
        return {c.topic: (c.msgtype, c.msgdef.data if c.msgdef.format == MessageDefinitionFormat.MSG else "")
                for c in reader.connections}


Converter = Callable[[bytes], bytes]


def definition_converter(topic: str, msgtype: str, stored: str, types: BagTypes) -> tuple[Converter | None, str]:
    """How to play a topic recorded with definition ``stored`` to subscribers of the installed type.

    Returns ``(None, '')`` when both have the same wire format (or the bag stores no definition),
    ``(converter, note)`` when they differ: the converter (rosbags' message migration) copies the
    fields both have, gives new fields zeros/empty values and drops removed ones; ``note`` says
    which. Raises BagError when the stored definition does not parse (the topic cannot be played
    faithfully).
    """
    if not stored:
        return None, ""
    from rosbags.convert.converter import is_same_wireformat, migrate_bytes

    types.ensure(msgtype, topic)
    recorded = get_typestore(Stores.EMPTY)
    try:
        recorded.register(get_types_from_msg(stored, msgtype))
    except (TypesysError, ValueError, KeyError) as exc:
        raise BagError(f"topic '{topic}': the definition of '{msgtype}' stored in the bag does not parse ({exc}); "
                       f"leave the topic out with --exclude {topic}") from None
    installed = types.typestore
    try:
        if is_same_wireformat(recorded, installed, msgtype, msgtype):
            return None, ""
    except KeyError as exc:  # a nested type only one side defines
        raise BagError(f"topic '{topic}': the bag's '{msgtype}' uses a type the installed one lacks ({exc})") from None
    old = {name for name, _ in recorded.fielddefs[msgtype][1]}
    new = {name for name, _ in installed.fielddefs[msgtype][1]}
    changes = [f"{what} {', '.join(sorted(names))}" for what, names in
               (("adds", new - old), ("drops", old - new)) if names]
    note = (f"topic '{topic}': the bag's {msgtype} differs from the installed one; translated (the installed type "
            f"{'; '.join(changes) or 'changes nested types'}: added fields are zero)")
    cache: dict[str, Any] = {}

    def convert(data: bytes) -> bytes:
        return bytes(migrate_bytes(recorded, installed, msgtype, msgtype, cache, data, src_is2=True, dst_is2=True))

    return convert, note


def bag_info(bag_dir: Path | str) -> BagInfo:
    """Summary of a bag from its metadata and storage index (no message is read)."""
    path = Path(bag_dir)
    with open_bag(path) as reader:
        counts: dict[tuple[str, str], TopicInfo] = {}
        for c in reader.connections:
            ext = c.ext if isinstance(c.ext, ConnectionExtRosbag2) else None
            key = (c.topic, c.msgtype)
            previous = counts.get(key)
            counts[key] = TopicInfo(c.topic, c.msgtype, c.msgcount + (previous.count if previous else 0),
                                    ext.serialization_format if ext else "cdr",
                                    tuple(ext.offered_qos_profiles) if ext else ())
        storage_paths = [p for p in (path.iterdir() if path.is_dir() else [path])
                         if p.is_file() and p.name != "metadata.yaml"]
        storage = _storage_id(path, reader)
        compression = "/".join(x for x in (reader.compression_format or "", reader.compression_mode or "") if x)
        if not compression and storage == "mcap" and path.is_dir():
            compression = _mcap_chunk_compression(storage_paths)
        return BagInfo(path=path, files=tuple(sorted(p.name for p in storage_paths)),
                       size_bytes=sum(p.stat().st_size for p in storage_paths), storage=storage,
                       ros_distro=reader.ros_distro or "",
                       compression=compression or "none",
                       start_ns=reader.start_time if reader.message_count else 0,
                       end_ns=reader.end_time - 1 if reader.message_count else 0,
                       message_count=reader.message_count, topics=tuple(counts.values()))


def _storage_id(path: Path, reader: Reader) -> str:
    if path.is_dir():
        try:
            return str(yaml.safe_load((path / "metadata.yaml").read_text())
                       ["rosbag2_bagfile_information"]["storage_identifier"])
        except Exception:  # the reader opened it, so this only labels; fall back to the suffix
            pass
    return "mcap" if any(p.suffix == ".mcap" for p in ([path] if path.is_file() else path.iterdir())) else "sqlite3"


def _mcap_chunk_compression(paths: Sequence[Path]) -> str:
    """'zstd (mcap chunks)' when an mcap file's chunks are compressed (rosbag2 leaves metadata empty then)."""
    from rosbags.rosbag2.storage_mcap import McapReader

    for p in paths:
        if p.suffix != ".mcap":
            continue
        mcap = McapReader(p)
        try:
            mcap.open()
            kinds = {c.compression for c in mcap.chunks if c.compression}
        except _READ_ERRORS:
            continue
        finally:
            if mcap.bio is not None:
                mcap.close()
        if kinds:
            return "/".join(sorted(kinds)) + " (mcap chunks)"
    return ""


def _stamp(ns: int) -> str:
    sec, nsec = stamps.split_ns(ns)
    when = datetime.fromtimestamp(sec, tz=UTC)
    return f"{when:%b %d %Y %H:%M:%S}.{nsec:09d} UTC ({stamps.to_text(ns)})"


def _size(n: int) -> str:
    value = float(n)
    for unit in ("B", "KiB", "MiB", "GiB"):
        if value < 1024 or unit == "GiB":
            return f"{value:.1f} {unit}" if unit != "B" else f"{n} B"
        value /= 1024
    return f"{n} B"  # pragma: no cover


def format_info(info: BagInfo) -> str:
    """`ros2 bag info`-like text."""
    label = 19
    lines = [
        f"{'Files:':<{label}}{', '.join(info.files)}",
        f"{'Bag size:':<{label}}{_size(info.size_bytes)}",
        f"{'Storage id:':<{label}}{info.storage}",
        f"{'ROS Distro:':<{label}}{info.ros_distro or 'unknown'}",
        f"{'Compression:':<{label}}{info.compression}",
        f"{'Duration:':<{label}}{info.duration_ns / 1e9:.9f}s",
        f"{'Start:':<{label}}{_stamp(info.start_ns) if info.message_count else '-'}",
        f"{'End:':<{label}}{_stamp(info.end_ns) if info.message_count else '-'}",
        f"{'Messages:':<{label}}{info.message_count}",
    ]
    title = "Topic information:"
    if not info.topics:
        lines.append(f"{title:<{label}}none")
    for i, topic in enumerate(sorted(info.topics, key=lambda t: t.name)):
        lines.append(f"{title if i == 0 else '':<{label}}Topic: {topic.name} | Type: {topic.msgtype} | "
                     f"Count: {topic.count} | Serialization Format: {topic.serialization_format}")
    return "\n".join(lines)


# ------------------------------------------------------------------------ deserialise
def deserialize(message: BagMessage, types: BagTypes | None = None) -> Any:
    """A bag message as a rosbags dataclass (no ROS install needed)."""
    types = types or BagTypes()
    types.ensure(message.msgtype, message.topic)
    return types.typestore.deserialize_cdr(message.data, message.msgtype)


def deserialize_ros(message: BagMessage) -> Any:
    """A bag message as the rclpy message class of its type (the installed interface package)."""
    from rclpy.serialization import deserialize_message  # rclpy only when asked for

    from .rosmsg import InterfaceError, get_interface

    try:
        cls = get_interface(message.msgtype, "msg")
    except InterfaceError as exc:
        raise UnknownTypeError(f"topic '{message.topic}': {exc}") from None
    return deserialize_message(message.data, cls)


@dataclass
class PlaybackClock:
    """When to send each message: recorded gaps scaled by ``1/rate`` from a wall-clock origin.

    Pure bookkeeping so the timing is testable without ROS: ``due_s(t_ns)`` is the
    monotonic time at which a message recorded at ``t_ns`` is due.
    """

    rate: float
    first_ns: int | None = None
    origin_s: float = 0.0

    def __post_init__(self) -> None:
        if not self.rate > 0:
            raise BagError(f"--rate must be > 0, got {self.rate:g}")

    def start(self, first_ns: int, now_s: float) -> None:
        """Tie the recording's ``first_ns`` to wall time ``now_s``."""
        self.first_ns = first_ns
        self.origin_s = now_s

    def due_s(self, t_ns: int) -> float:
        """Monotonic time at which the message recorded at ``t_ns`` is to be published."""
        assert self.first_ns is not None, "start() first"
        return self.origin_s + (t_ns - self.first_ns) / 1e9 / self.rate
