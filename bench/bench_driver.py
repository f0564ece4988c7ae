"""Driver benchmark: GP32 command round trip over the pty, a service round trip through the node, and how
well the device's own stamps (protocol v2) place stops and positions in host time.

    make bench-driver   ->  bench/results/driver.json
"""

from __future__ import annotations

import sys
import tempfile
import threading
import time
from pathlib import Path

from common import median, percentile, time_calls, write_result

from lsu_scan import rosenv


def main() -> int:
    claim = rosenv.isolate()  # our own DDS domain, localhost only
    from lsu_driver.client import Gp32Client
    from lsu_driver.emulator import Gp32Emulator

    with tempfile.TemporaryDirectory(prefix="lsu-bench-driver-") as tmp:
        link = str(Path(tmp) / "gp32")
        with Gp32Emulator(link=link) as emu:
            with Gp32Client(link) as client:
                client.set_watchdog(0)
                status_ms = time_calls(client.status, repeat=500, warmup=20)
                laser_ms = time_calls(lambda: client.laser(False), repeat=200, warmup=10)
            service_ms = _service_round_trip(link)
        del emu
        stamps = _stamp_errors(str(Path(tmp) / "gp32-clock"))
    claim.release()
    write_result(
        "driver",
        {"roundtrip_ms_median": median(status_ms), "roundtrip_ms_p99": percentile(status_ms, 99),
         "laser_cmd_ms_median": median(laser_ms), "service_roundtrip_ms_median": median(service_ms),
         "service_roundtrip_ms_p99": percentile(service_ms, 99),
         "service_over_serial_ratio": median(service_ms) / median(laser_ms), **stamps},
        {"roundtrip_ms_median": "ms", "roundtrip_ms_p99": "ms", "laser_cmd_ms_median": "ms",
         "service_roundtrip_ms_median": "ms", "service_roundtrip_ms_p99": "ms", "service_over_serial_ratio": "x",
         "device_stamp_error_ms_p95": "ms", "device_stamp_uncertainty_ms_median": "ms",
         "device_stamps_within_uncertainty_pct": "%", "stop_arrival_error_ms_p95": "ms",
         "stop_stamp_error_over_arrival": "x", "device_clock_drift_error_ppm": "ppm"},
        notes="roundtrip: `P` status command -> parsed reply over the emulator's pty (500 calls, 115200 baud "
              "setting; a pty has no baud delay). service: /lsu/laser/set (std_srvs/SetBool) from a client node to "
              "gp32_driver in the same process (MultiThreadedExecutor), which sends L0 and waits for OK L0 "
              "(200 calls); the ratio is against the bare serial L0 measured in the same run. device stamps: the "
              "emulator's clock at +150 ppm from a random start, status polls at 10 Hz (the driver's round trips), "
              "20 moves of 10 steps with !POS at 20 Hz; error = |mapped stamp - the emulator's true host time of the "
              "event|; arrival = the v1 way, a stop stamped when its !DONE arrived (same stops); over a pty lines "
              "arrive at once, so arrival is a lower bound that a USB adapter's latency timer (1-16 ms) would add to.")
    return 0


def _stamp_errors(link: str) -> dict:
    from lsu_driver import protocol as p
    from lsu_driver.client import Gp32Client
    from lsu_driver.emulator import EmulatorConfig, Gp32Emulator

    drift_ppm = 150.0
    with Gp32Emulator(EmulatorConfig(clock_drift_ppm=drift_ppm), link=link) as emu:
        client = Gp32Client(link)
        client.position_rate_hz = 20
        client.connect()
        seen: list = []  # (event, mapped stamp, uncertainty, arrival)

        def listener(event: object) -> None:
            device_ms = getattr(event, "device_ms", None)
            mapped = client.map_device_ms(device_ms) if device_ms is not None else None
            if mapped is not None:
                seen.append((event, mapped[0], mapped[1], time.time()))

        client.add_listener(listener)
        stop = threading.Event()

        def poll() -> None:
            while not stop.is_set():
                client.status()
                stop.wait(0.1)

        poller = threading.Thread(target=poll, daemon=True)
        poller.start()
        try:
            time.sleep(2.0)
            for i in range(20):
                client.step(10 if i % 2 == 0 else -10)
                time.sleep(0.05)
        finally:
            stop.set()
            poller.join()
        drift = client.clock_drift_ppm()
        client.close()
        truth = {e["line"]: e["wall_s"] for e in emu.handle_control({"get": "events"})["events"]}
    errors, within, uncertainties, stop_errors, arrival_errors = [], 0, [], [], []
    for event, stamp, uncertainty, arrival in seen:
        happened = truth.get(p.encode_line(event).decode().strip())
        if happened is None:
            continue
        error = abs(stamp - happened) * 1e3
        errors.append(error)
        uncertainties.append(uncertainty * 1e3)
        within += error <= uncertainty * 1e3
        if isinstance(event, p.Done):
            stop_errors.append(error)
            arrival_errors.append((arrival - happened) * 1e3)
    return {"device_stamp_error_ms_p95": percentile(errors, 95),
            "device_stamp_uncertainty_ms_median": median(uncertainties),
            "device_stamps_within_uncertainty_pct": 100.0 * within / len(errors),
            "stop_arrival_error_ms_p95": percentile(arrival_errors, 95),
            "stop_stamp_error_over_arrival": percentile(stop_errors, 95) / percentile(arrival_errors, 95),
            "device_clock_drift_error_ppm": abs((drift or 0.0) - drift_ppm)}


def _service_round_trip(link: str) -> list:
    import rclpy
    from rclpy.executors import MultiThreadedExecutor
    from std_srvs.srv import SetBool

    from lsu_driver.node import Gp32DriverNode

    rclpy.init()
    driver = Gp32DriverNode(cli_args=["--ros-args", "-p", f"port:={link}", "-p", "watchdog_ms:=0"])
    user = rclpy.create_node("bench_user")
    executor = MultiThreadedExecutor()
    executor.add_node(driver)
    executor.add_node(user)
    spinner = threading.Thread(target=executor.spin, daemon=True)
    spinner.start()
    client = user.create_client(SetBool, "/lsu/laser/set")
    if not client.wait_for_service(timeout_sec=10.0):
        raise RuntimeError("gp32_driver's laser/set did not come up")

    def call() -> None:
        future = client.call_async(SetBool.Request(data=False))
        end = time.monotonic() + 5.0
        while not future.done():
            if time.monotonic() > end:
                raise RuntimeError("laser/set did not answer within 5 s")
            time.sleep(0.0002)
        if not future.result().success:
            raise RuntimeError(future.result().message)

    try:
        return time_calls(call, repeat=200, warmup=10)
    finally:
        executor.shutdown()
        driver.destroy_node()
        user.destroy_node()
        rclpy.try_shutdown()


if __name__ == "__main__":
    sys.exit(main())
