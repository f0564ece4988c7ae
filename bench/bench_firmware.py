"""Firmware benchmark: image size on the GP32, command round trip through the HC08 simulator, and
the step timing the simulated board sees.

    make bench-firmware   ->  bench/results/firmware.json
"""

from __future__ import annotations

import os
import sys
import tempfile
from pathlib import Path

from common import median, percentile, time_calls, write_result


def main() -> int:
    from lsu_driver.client import Gp32Client
    from lsu_driver.emulator import EmulatorConfig, Gp32Emulator
    from lsu_driver.firmware import FirmwareUnavailable, Gp32Firmware, build, toolchain_missing

    reason = toolchain_missing()
    if reason:
        print(f"bench_firmware: skipped: {reason}", file=sys.stderr)
        return 0
    try:
        made = build()
    except FirmwareUnavailable as exc:
        print(f"bench_firmware: {exc}", file=sys.stderr)
        return 1
    with tempfile.TemporaryDirectory(prefix="lsu-bench-firmware-") as tmp:
        with Gp32Emulator(link=str(Path(tmp) / "emu")) as emu:
            with Gp32Client(str(emu.link)) as client:
                client.set_watchdog(0)
                emulator_ms = time_calls(client.status, repeat=300, warmup=20)
        config = EmulatorConfig(start_position_steps=20.0)
        with Gp32Firmware(config, link=str(Path(tmp) / "fw"), image=made.sim_image) as unit:
            unit.wait_booted()
            with Gp32Client(str(unit.link), command_timeout_s=2.0) as client:
                client.set_watchdog(0)
                firmware_ms = time_calls(client.status, repeat=300, warmup=20)
                jitter, own = {}, {}
                for rate in (200, 400):
                    client.set_rate(rate)
                    client.home()
                    unit.steps.clear()
                    client.move_to(400)
                    jitter[rate] = unit.step_jitter_ms(rate)
                    own[rate] = unit.step_jitter_ms(rate, firmware_time=True)
    worst_ms, pulses = max(jitter.values())
    write_result(
        "firmware",
        {"flash_bytes": made.size.flash_bytes, "ram_bytes": made.size.ram_bytes,
         "stack_bytes_free": made.size.stack_bytes,
         "roundtrip_ms_median": median(firmware_ms), "roundtrip_ms_p99": percentile(firmware_ms, 99),
         "roundtrip_over_emulator_ratio": median(firmware_ms) / median(emulator_ms),
         "step_jitter_ms_max": worst_ms, "step_jitter_ms_max_200": jitter[200][0],
         "step_jitter_ms_max_400": jitter[400][0],
         "step_jitter_ms_max_firmware_clock": max(own[200][0], own[400][0])},
        {"flash_bytes": "B", "ram_bytes": "B", "stack_bytes_free": "B", "roundtrip_ms_median": "ms",
         "roundtrip_ms_p99": "ms", "roundtrip_over_emulator_ratio": "x", "step_jitter_ms_max": "ms",
         "step_jitter_ms_max_200": "ms", "step_jitter_ms_max_400": "ms", "step_jitter_ms_max_firmware_clock": "ms"},
        notes="flash/RAM: the real image (hal_gp32.c, 9600 baud) from the linker map; GP32: 32768 B flash, 512 B "
              "RAM (the stack takes what the variables leave). roundtrip: `P` -> parsed reply through the pty, the "
              "board and shc08 running the simulator image (300 calls), ratio against the Python emulator in the "
              "same run. step jitter: largest deviation of a step-pulse interval from 1/rate as the board "
              f"received them (wall clock), over a 400-step move at 200 and at 400 steps/s ({pulses} intervals); "
              "firmware_clock: the same intervals in the firmware's own milliseconds (what a real board's pins "
              "would show, bounded by the 1 ms tick); the wall-clock figure adds the simulated host's scheduling "
              f"(load average {os.getloadavg()[0]:.1f} on {os.cpu_count()} cores during this run).")
    return 0


if __name__ == "__main__":
    sys.exit(main())
