"""The living subject of the graph tests (test/test_motion_graph.py, lsu_web's test_browser_motion.py): `lsu launch
sim` on person:2 turning its head during a sweep of its face, so that the sweep is flagged and scanned again.

The simulator's ``turn`` (lsu_sim.motion) turns the head 15 deg at ``TURN_AT_S`` after the first frame rendered; the
pose is updated every 1 / ``MOTION_HZ`` s, so the sweep's frames exposed in its first 2 s see the head unturned and
those of its last 1.5 s turned, the reference frame (the middle measured one) among the first; the head stays turned
for the second sweep. Each update re-casts the simulated views (~0.5 s of CPU, seconds on a busy host), cast ahead
by the simulator's own thread; a camera whose frames reach the update before that cast is done waits for it, so a
short sweep left a busy host's camera too few frames after the update to see the turn, and the camera's stall limit
(``capture_timeout_s``, a real camera's deadline) is raised past such a wait: these tests are about the motion, not
the camera's deadline.
"""

from __future__ import annotations

__all__ = ["SWEEP_START", "SWEEP_END", "SWEEP_RATE", "TURN_AT_S", "MOTION_HZ", "CAPTURE_TIMEOUT_S", "launch_args"]

# the face of person:2 (its landmarks lie within steps 133..295): 200 steps at the face rate, 3.5 s
SWEEP_START, SWEEP_END, SWEEP_RATE = 140, 340, 57
TURN_AT_S, MOTION_HZ = 1.5, 0.5
CAPTURE_TIMEOUT_S = 15.0


def launch_args() -> list[str]:
    """The `lsu launch sim` arguments of the turning subject (the scene, its motion, the camera's stall limit)."""
    return ["scene:=person:2", "motion:=turn", "motion_seed:=2", f"motion_turn_at_s:={TURN_AT_S}",
            f"motion_hz:={MOTION_HZ}", f"capture_timeout_s:={CAPTURE_TIMEOUT_S}"]
