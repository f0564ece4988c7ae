"""The coordinator's end-of-scan laser-off call when a shutdown begins while it waits.

Ctrl-C reaches every node of `lsu launch`: the driver may stop first (ending the scan's move), so
the coordinator asks for the laser off with its normal timeout and only then gets the signal
itself. The launcher SIGKILLs 4 s after its SIGINT, so this wait must end soon after the
shutdown begins, or scan.json and the bag are lost (it waited 3 s, CI lost a scan that way).
"""

import threading
import time

import pytest
import rclpy
from std_srvs.srv import SetBool

from lsu_scan.coordinator import ScanCoordinatorNode

SIGNAL_AT_S = 0.5


@pytest.mark.parametrize("how", ["context shut down", "node destroyed"])
def test_laser_off_gives_up_soon_after_a_shutdown_begins_mid_call(ros_context, tmp_path, how):
    ns = "/lsu_mute_test"
    coordinator = ScanCoordinatorNode(context=ros_context, namespace=ns,
                                      parameter_overrides=[rclpy.parameter.Parameter("output_dir", value=str(tmp_path))])
    # a driver that is going away: its service is on the graph but nobody spins it, so no answer comes
    mute = rclpy.create_node("mute_driver", namespace=ns, context=ros_context)
    mute.create_service(SetBool, "laser/set", lambda _request, response: response)
    # "context shut down": rclpy's SIGINT/SIGTERM handler; "node destroyed": main() after its spin
    # ended, while the scan thread (which holds the busy lock, as here) still runs
    stop = ((lambda: rclpy.try_shutdown(context=ros_context)) if how == "context shut down"
            else coordinator.destroy_node)
    timer = threading.Timer(SIGNAL_AT_S, stop)
    try:
        with coordinator._busy:  # what the scan thread holds for the whole scan
            assert not coordinator.shutting_down
            t0 = time.monotonic()
            timer.start()
            error = coordinator._laser_off_safely()  # starts with the normal 3 s timeout
            elapsed = time.monotonic() - t0
            assert coordinator.shutting_down
    finally:
        timer.cancel()
        timer.join()
        mute.destroy_node()
        if how == "context shut down":
            coordinator.destroy_node()
    assert error, "the mute driver cannot have switched the laser off"
    # the shutdown cut the wait: it ended before the call's own 3 s timeout (typically 0.5 s
    # after the signal); no tighter bound, a busy host may be late on it
    assert elapsed < 3.0, f"waited {elapsed:.2f} s: the shutdown did not cut the 3 s wait"
    assert elapsed >= SIGNAL_AT_S - 0.05, "the call should wait while there is no shutdown"
