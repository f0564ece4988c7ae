"""The page in a real browser (Debian's Chromium, Playwright) says "hold still, scanning again" when the subject
moved beyond correction and the coordinator scans again: `lsu launch sim web:=true motion:=turn`, a sweep
started from the page.

Ground truth never comes from the page: the scans' records on disk (scan.json: the first flagged with the
coordinator's message, the second a rescan of it) and the simulator's motion (lsu_sim.motion ``turn``, the head
turning during the first sweep and turned for the second: lsu_testing.motion, the sweep and settings of
test/test_motion_graph.py too). The words shown are the ones the record holds (lsu_reconstruct.motion.HOLD_STILL,
their one owner), not a copy in the test.
"""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from lsu_reconstruct.motion import HOLD_STILL
from lsu_testing.browser import open_page, start_scan, web_sim_graph
from lsu_testing.motion import SWEEP_END, SWEEP_RATE, SWEEP_START, launch_args

pytestmark = [pytest.mark.slow, pytest.mark.timeout(600)]


@pytest.fixture(scope="module")
def graph(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("webmotion")
    with web_sim_graph(tmp, *launch_args()) as g:
        yield g


def test_the_page_says_hold_still_when_a_sweep_is_scanned_again(graph):
    page = open_page(graph)
    page.select_option("select[name=mode]", "sweep")  # shows the sweep's own fields
    page.fill("input[name=sweep_rate]", str(SWEEP_RATE))
    page.uncheck("input[name=texture]")  # as test_motion_graph's `lsu scan --no-texture`
    start_scan(page, SWEEP_START, SWEEP_END, 1, "moving", mode="sweep")
    # the notice is shown while the second sweep runs, before the goal's result
    page.wait_for_function("window.lsu.notices.length > 0", timeout=300000)
    assert page.evaluate("window.lsu.lastResult") is None
    assert page.is_visible("#scan-notice")
    shown = page.inner_text("#scan-notice")
    page.wait_for_function("window.lsu.lastResult !== null", timeout=300000)
    result = page.evaluate("window.lsu.lastResult")
    notices = page.evaluate("window.lsu.notices")
    # the disk's word: two scans, the first flagged with the coordinator's message, the second its rescan
    records = [json.loads(p.read_text()) for p in sorted(Path(graph["scans"]).glob("*/scan.json"))]
    assert len(records) == 2, records
    first = next(r for r in records if not r["rescan_of"])
    second = next(r for r in records if r["rescan_of"])
    assert first["motion"]["flagged"] and first["motion"]["message"] == HOLD_STILL, first["motion"]
    assert second["rescan_of"] == first["scan_id"] and not second["motion"]["flagged"], json.dumps(second["motion"])
    # the page said it once, in the words of the record, and it stays on the page after the result
    assert notices == [HOLD_STILL] and shown == HOLD_STILL, (notices, shown)
    assert result["outcome"] == "SUCCEEDED" and result["scan_id"] == second["scan_id"], result
    assert page.is_visible("#scan-notice") and page.inner_text("#scan-notice") == HOLD_STILL
    assert HOLD_STILL in page.inner_text("#scan-message")  # the result's status names the rescan too
    page.close()
