"""Storage faults while a scan is written: the disk fills up, the folder is deleted under the open bag.

A full disk is a real one: a small tmpfs mounted for the test (root only; skipped with the reason
elsewhere), so the failure is the kernel's ENOSPC, not an imitation of it. What must hold: nothing
half-written is left looking complete (no PLY or scan.json cut short, no temporary file), the writer
says what happened, and every message stored before is still there for a plain rosbags reader.
"""

from __future__ import annotations

import json
import os
import struct
import subprocess
import time
from pathlib import Path

import numpy as np
import pytest
from rosbags.rosbag2 import Reader

from lsu_bags import bags
from lsu_bags.ply import read_ply, write_ply

TOPIC = "/lsu/stereo/left/image_raw"


def _string_cdr(size: int, seed: int) -> bytes:
    """A std_msgs/String of ``size`` bytes (an image's worth of data), CDR little-endian."""
    text = bytes(np.random.default_rng(seed).integers(97, 123, size, dtype=np.uint8))
    return b"\x00\x01\x00\x00" + struct.pack("<I", size + 1) + text + b"\x00"


@pytest.fixture
def small_disk(tmp_path):
    """A 24 MiB filesystem of its own (tmpfs), unmounted afterwards."""
    mnt = tmp_path / "disk"
    mnt.mkdir()
    if os.geteuid() != 0:
        pytest.skip("a full disk needs a small tmpfs, and mounting one needs root")
    done = subprocess.run(["mount", "-t", "tmpfs", "-o", "size=24m", "tmpfs", str(mnt)], capture_output=True, text=True)
    if done.returncode != 0:
        pytest.skip(f"cannot mount a small tmpfs here: {done.stderr.strip()}")
    try:
        yield mnt
    finally:
        subprocess.run(["umount", "-l", str(mnt)], check=False)


def _stored(path: Path) -> list[tuple[int, bytes]]:
    """The messages of a bag as rosbags' own reader sees them (no LSU code)."""
    with Reader(path) as reader:
        return [(t, bytes(raw)) for _conn, t, raw in reader.messages()]


@pytest.mark.fault("storage: disk full while writing a scan's bag")
def test_a_full_disk_stops_the_bag_which_keeps_every_message_before(small_disk, fault_report):
    path = small_disk / "scan" / "bag"
    written = []
    bag = bags.BagWriter(path, "mcap")
    bag.add_topic(TOPIC, "std_msgs/msg/String", [bags.make_qos("reliable", "volatile")])
    for i in range(60):  # 60 MB offered to a 24 MiB disk
        data = _string_cdr(1_000_000, i)
        bag.write(TOPIC, 1_795_000_000_000_000_000 + i * 10_000_000, data)
        written.append((1_795_000_000_000_000_000 + i * 10_000_000, data))
        bag._io.submit(lambda: None).result()  # the writer thread has taken it (a capture's pace)
        if bag.error is not None:
            break
    assert bag.error is not None and "full" in bag.error, bag.error
    with pytest.raises(bags.BagError, match="full"):
        bag.close()
    stored = _stored(path)  # metadata.yaml and the MCAP index fit in the space kept for them
    assert len(stored) >= 5 and stored == written[:len(stored)]
    assert not [p for p in path.rglob("*") if p.name.endswith(".tmp")]
    fault_report.note(error_shown=bag.error, snaps_captured=len(written), snaps_lost=0,
                      data_kept=f"a closed bag with the {len(stored)} messages before the disk filled")


@pytest.mark.fault("storage: disk full while writing cloud.ply and scan.json")
def test_a_full_disk_leaves_no_cloud_or_record_cut_short(small_disk, fault_report):
    from lsu_scan.scan_plan import ScanRecord

    folder = small_disk / "scan"
    record = ScanRecord(scan_id="s1", started="2026-01-01T00:00:00", goal={}, parameters={}, calibration="")
    first = record.write(folder)  # the scan's record before the disk filled
    before = first.read_text()
    small = {k: np.arange(10, dtype="<f4") for k in "xyz"}
    write_ply(folder / "small.ply", small)
    (small_disk / "filler").write_bytes(b"\0" * (24 * 1024 * 1024 - 2 * 1024 * 1024))  # 2 MiB left
    big = {"x": np.zeros(2_000_000, "<f4"), "y": np.zeros(2_000_000, "<f4")}  # 16 MB: cannot fit
    with pytest.raises(OSError) as caught:
        write_ply(folder / "cloud.ply", big)
    assert not (folder / "cloud.ply").exists()  # nothing that looks like a cloud
    record.status = "x" * 3_000_000  # a record larger than what is left
    with pytest.raises(OSError):
        record.write(folder)
    assert first.read_text() == before  # the record stored before is untouched
    assert sorted(p.name for p in folder.iterdir()) == ["scan.json", "small.ply"]  # no temporary file left
    assert len(read_ply(folder / "small.ply")[0]["x"]) == 10
    fault_report.note(error_shown=str(caught.value), snaps_lost=0, data_kept="scan.json and the PLY written before")


@pytest.mark.fault("storage: scan folder deleted while its bag is written")
def test_a_bag_whose_folder_is_deleted_is_written_again_with_every_message(tmp_path, fault_report):
    import shutil

    folder = tmp_path / "scan"
    path = folder / "bag"
    written = []
    bag = bags.BagWriter(path, "mcap")
    bag.add_topic(TOPIC, "std_msgs/msg/String", [bags.make_qos("reliable", "volatile")])
    for i in range(12):
        if i == 6:
            bag._io.submit(lambda: None).result()
            shutil.rmtree(folder)  # the user deletes the scan folder mid-scan
        t = 1_795_000_000_000_000_000 + i * 10_000_000
        data = _string_cdr(300_000, i)
        bag.write(TOPIC, t, data)
        written.append((t, data))
    assert bag.error is None
    bag.close()
    assert _stored(path) == written  # before and after the deletion, for a plain rosbags reader
    assert not [p for p in path.rglob("*") if p.name.endswith(".tmp")]
    fault_report.note(error_shown="(the scan coordinator stops the scan and names the folder)", snaps_lost=0,
                      data_kept="the bag written again from its open file, every message")


def test_the_scan_stops_naming_the_storage_problem(tmp_path):
    from types import SimpleNamespace

    from lsu_scan.scan_bag import storage_problem

    folder = tmp_path / "scan"
    folder.mkdir()
    healthy = SimpleNamespace(recorder=SimpleNamespace(writer=SimpleNamespace(error=None, free_bytes=10**9)))
    full = SimpleNamespace(recorder=SimpleNamespace(writer=SimpleNamespace(error="the disk of /x is full",
                                                                           free_bytes=0)))
    nearly = SimpleNamespace(recorder=SimpleNamespace(writer=SimpleNamespace(error=None, free_bytes=12 << 20)))
    assert storage_problem(healthy, folder) is None and storage_problem(None, folder) is None
    assert "nearly full" in storage_problem(nearly, folder)
    assert "disk of /x is full" in storage_problem(full, folder) and "free space" in storage_problem(full, folder)
    folder.rmdir()
    assert f"scan folder {folder} was deleted" in storage_problem(healthy, folder)


WRITER = """
import os, signal, struct, sys
import numpy as np
from lsu_bags import bags
bag = bags.BagWriter(sys.argv[1], "mcap")
bag.add_topic("/lsu/stereo/left/image_raw", "std_msgs/msg/String", [bags.make_qos("reliable", "volatile")])
for i in range(40):
    text = bytes(np.random.default_rng(i).integers(97, 123, 300_000, dtype=np.uint8))
    bag.write("/lsu/stereo/left/image_raw", 1_795_000_000_000_000_000 + i * 10_000_000,
              b"\\x00\\x01\\x00\\x00" + struct.pack("<I", len(text) + 1) + text + b"\\x00")
bag._io.submit(lambda: None).result()  # all 40 handed to the storage (about 12 MB: chunks on disk, one open)
os.kill(os.getpid(), signal.SIGKILL)  # the bag writer killed mid-scan
"""


@pytest.mark.fault("storage: bag writer SIGKILLed mid-scan")
def test_a_killed_bag_writer_leaves_a_bag_that_opens_with_every_stored_message(tmp_path, fault_report):
    import sys

    from lsu_scan.scan_bag import recover_killed_scans

    folder = tmp_path / "scans" / "20260101-000000-1"
    done = subprocess.run([sys.executable, "-c", WRITER, str(folder / "bag")], capture_output=True, text=True,
                          timeout=120)
    assert done.returncode == -9, done.stderr
    file = folder / "bag" / "bag.mcap"
    size = file.stat().st_size
    # what the kill left on disk, read independently: every complete Message record before the cut
    raw = file.read_bytes()
    on_disk = raw.count(b"\x00\x01\x00\x00" + struct.pack("<I", 300_001))
    with pytest.raises(Exception):  # noqa: B017 - rosbags cannot open it as it is (no footer, no metadata.yaml)
        _stored(folder / "bag")

    class Log:
        lines: list[str] = []

        def warning(self, text):
            self.lines.append(text)

        error = warning

    os.utime(file, (time.time() - 10, time.time() - 10))
    assert recover_killed_scans(tmp_path / "scans", Log()) == [folder], Log.lines
    stored = _stored(folder / "bag")  # plain rosbags
    assert len(stored) >= on_disk - 1 and len(stored) >= 20, (len(stored), on_disk, size)
    for i, (t, data) in enumerate(stored):  # the first messages, whole and in order
        assert t == 1_795_000_000_000_000_000 + i * 10_000_000 and data == _string_cdr(300_000, i)
    record = json.loads((folder / "scan.json").read_text())
    assert record["partial"] and "killed" in record["status"]
    fault_report.note(error_shown=Log.lines[-1], snaps_captured=40, snaps_lost=0,
                      data_kept=f"the bag recovered with {len(stored)} of the 40 messages "
                                f"({on_disk} whole on disk at the kill), scan.json marked partial")
