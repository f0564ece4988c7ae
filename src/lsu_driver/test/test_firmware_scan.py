"""A short scan of the sim graph on the unit's own firmware (`lsu launch sim unit:=firmware`):
the driver, coordinator and cameras run unchanged against shc08 + the simulated board."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from lsu_driver.emulator import send_control
from lsu_scan.scanner import LsuScanner
from lsu_testing.plugin import LaunchedProcess

pytestmark = pytest.mark.slow


def test_scan_of_six_snaps_on_the_firmware(firmware_build, tmp_path):
    port = str(tmp_path / "gp32")
    proc = LaunchedProcess(["launch", "sim", "unit:=firmware", f"port:={port}", "scene:=plane",
                            f"output_dir:={tmp_path / 'scans'}"])
    scanner = None
    try:
        proc.wait_for_line(r"\[gp32_emulator\].*GP32 firmware on", timeout_s=90)
        proc.wait_for_line(r"\[gp32_driver\].*homed: track 470", timeout_s=90)
        proc.wait_for_line(r"\[stereo_camera\].*source 'sim' open", timeout_s=60)
        scanner = LsuScanner(wait_s=30)
        result = scanner.scan(start=200, end=210, step=2, settle_s=0.05, output_dir=str(tmp_path / "scans"))
        assert result.success and not result.partial, (result.status, proc.output[-3000:])
        record = json.loads((Path(result.output_dir) / "scan.json").read_text())
        assert [s["position_steps"] for s in record["snaps"]] == [200, 202, 204, 206, 208, 210]
        assert record["snaps_acknowledged"] == 6 and result.points > 6 * 300  # a plane fills most rows
        truth = send_control(port + ".ctl", {"get": "truth"})["truth"]  # the simulated board's pins
        assert not truth["laser_on"] and truth["homed"] and truth["boot_count"] == 1
        assert abs(truth["position_steps"] - 210) < 0.5
    finally:
        if scanner is not None:
            scanner.close()
        proc.stop(timeout_s=15)
