"""Driver benchmark: GP32 command round trip over the pty, and a service round trip through the node.

    make bench-driver   ->  bench/results/driver.json
"""

from __future__ import annotations

import sys
import tempfile
import threading
import time
from pathlib import Path

from common import median, percentile, time_calls, write_result

from lsu_bringup import rosenv


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
    claim.release()
    write_result(
        "driver",
        {"roundtrip_ms_median": median(status_ms), "roundtrip_ms_p99": percentile(status_ms, 99),
         "laser_cmd_ms_median": median(laser_ms), "service_roundtrip_ms_median": median(service_ms),
         "service_roundtrip_ms_p99": percentile(service_ms, 99),
         "service_over_serial_ratio": median(service_ms) / median(laser_ms)},
        {"roundtrip_ms_median": "ms", "roundtrip_ms_p99": "ms", "laser_cmd_ms_median": "ms",
         "service_roundtrip_ms_median": "ms", "service_roundtrip_ms_p99": "ms", "service_over_serial_ratio": "x"},
        notes="roundtrip: `P` status command -> parsed reply over the emulator's pty (500 calls, 115200 baud "
              "setting; a pty has no baud delay). service: /lsu/laser/set (std_srvs/SetBool) from a client node to "
              "gp32_driver in the same process (MultiThreadedExecutor), which sends L0 and waits for OK L0 "
              "(200 calls); the ratio is against the bare serial L0 measured in the same run.")
    return 0


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
