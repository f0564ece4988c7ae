"""The page in a real browser: Debian's Chromium (headless, no download) driven by Playwright, on the sim graph.

One graph for the module (`lsu launch sim web:=true`). Ground truth never comes from the page: the
scan's point count from the action result on disk (scan.json), the downloaded PLY read with open3d, the
laser from the driver's state topic read by this test's own client (`LsuScanner`), the token from the
file the server wrote. Set LSU_WEB_SCREENSHOTS=DIR to save the screenshots the README shows.
"""

import json
import os
import time
import urllib.request
from pathlib import Path

import numpy as np
import pytest

from lsu_testing.browser import free_port, open_page, start_scan, web_sim_graph
from lsu_testing.http import http
from lsu_testing.plugin import LaunchedProcess

pytestmark = pytest.mark.slow
SHOTS = os.environ.get("LSU_WEB_SCREENSHOTS", "")


@pytest.fixture(scope="module")
def graph(tmp_path_factory):
    from lsu_scan.scanner import LsuScanner

    tmp = tmp_path_factory.mktemp("web")
    # a realistic person (the faces test enrols the page's scan) and a gallery of this module's own, open to
    # enrolment: the page then offers enrol and remove
    with web_sim_graph(tmp, "scene:=person:2", f"gallery:={tmp / 'gallery.db'}", "allow_enrolment:=true") as g:
        scanner = LsuScanner(wait_s=30)
        try:
            yield {**g, "scanner": scanner, "gallery": tmp / "gallery.db"}
        finally:
            scanner.close()


def driver_laser_after(g, since: float, timeout_s: float = 20.0) -> bool:
    """laser_on of the first driver state received after ``since`` (monotonic): the driver's word, not the page's."""
    scanner = g["scanner"]
    end = time.monotonic() + timeout_s
    first = scanner.state()
    while time.monotonic() < end:
        state = scanner.state()
        if state is not first and time.monotonic() > since:
            return bool(state.laser_on)
        time.sleep(0.05)
    raise AssertionError("no driver state received")


def canvas_lit_pixels(page) -> int:
    """Pixels of the 3D view that are not its background (the WebGL canvas keeps its drawing buffer)."""
    return page.evaluate("""() => {
        const src = document.querySelector('#view3d canvas');
        const c = document.createElement('canvas'); c.width = src.width; c.height = src.height;
        const g = c.getContext('2d'); g.drawImage(src, 0, 0);
        const d = g.getImageData(0, 0, c.width, c.height).data; let n = 0;
        for (let i = 0; i < d.length; i += 4) if (Math.abs(d[i] - 16) + Math.abs(d[i+1] - 20) + Math.abs(d[i+2] - 28) > 30) n++;
        return n; }""")


def test_scan_from_the_page_progress_points_mesh_and_ply_download(graph):
    import open3d as o3d

    page = open_page(graph)
    start_scan(page, 150, 300, 4, "web test", record_bag=True)
    page.wait_for_function("window.lsu.progressPct > 0 && window.lsu.progressPct < 100", timeout=120000)
    drawn_mid = page.evaluate("window.lsu.pointsDrawn")
    page.wait_for_function("window.lsu.lastResult !== null", timeout=300000)
    result = page.evaluate("window.lsu.lastResult")
    assert result["outcome"] == "SUCCEEDED", result
    assert page.evaluate("window.lsu.progressPct") == 100
    assert "100 %" in page.inner_text("#progress-text")
    record = json.loads((Path(result["output_dir"]) / "scan.json").read_text())
    assert record["goal"]["label"] == "web test" and record["snaps_captured"] == 38
    # points grew during the scan and the view drew the snaps' points as the matcher sent them (best effort: the
    # page may drop frames, never add); the scan cloud is those points less what its grazing-view rule drops
    drawn = page.evaluate("window.lsu.pointsDrawn")
    snap_points = sum(int(snap["points"]) for snap in record["snaps"])
    assert 0.5 * snap_points <= record["points"] <= snap_points
    assert drawn >= drawn_mid and 0.5 * snap_points <= drawn <= snap_points
    assert page.evaluate("window.lsu.imagesShown") > 0
    page.wait_for_function("window.lsu.meshLoaded", timeout=120000)
    assert canvas_lit_pixels(page) > 2000
    if SHOTS:
        page.wait_for_function("document.querySelectorAll('#result-renders img').length > 0", timeout=60000)
        page.wait_for_timeout(1500)
        page.screenshot(path=str(Path(SHOTS) / "scan.png"), full_page=True)
    # the PLY the page offers is the scan's cloud: open3d reads the same points the coordinator counted
    with page.expect_download() as info:
        page.click("#result-downloads a[data-kind='cloud.ply']")
    ply = graph["tmp"] / "downloaded.ply"
    info.value.save_as(ply)
    cloud = o3d.io.read_point_cloud(str(ply))
    xyz = np.asarray(cloud.points)
    assert len(xyz) == record["points"] and len(xyz) > 1000
    assert 0.2 < float(np.median(xyz[:, 2])) < 0.45  # the head stands ~0.3 m in front of the left camera
    # the library lists it with its downloads; the bag comes as a zip
    page.click("#tabs button[data-tab=library]")
    page.wait_for_selector(f".scan-tile[data-id='{result['scan_id']}']", timeout=30000)
    tile = page.locator(f".scan-tile[data-id='{result['scan_id']}']")
    for kind in ("cloud.ply", "mesh.ply", "mesh.obj", "mesh.stl", "bag.zip"):
        assert tile.locator(f"a[data-kind='{kind}']").count() == 1, kind
    with page.expect_download() as info:
        tile.locator("a[data-kind='mesh.stl']").click()
    stl = graph["tmp"] / "downloaded.stl"
    info.value.save_as(stl)
    mesh = o3d.io.read_triangle_mesh(str(stl))
    assert len(mesh.triangles) == len(o3d.io.read_triangle_mesh(str(Path(result["output_dir"]) / "mesh.ply")).triangles)
    if SHOTS:
        page.set_viewport_size({"width": 1400, "height": 640})
        page.wait_for_timeout(1000)
        page.screenshot(path=str(Path(SHOTS) / "library.png"))
        for tab, height in (("calibration", 640), ("hardware", 480), ("faces", 480), ("about", 1000)):
            page.set_viewport_size({"width": 1400, "height": height})
            page.click(f"#tabs button[data-tab={tab}]")
            page.wait_for_timeout(2500)
            page.screenshot(path=str(Path(SHOTS) / f"{tab}.png"))
    page.close()


def test_cancel_mid_way_ends_with_the_laser_off(graph):
    page = open_page(graph)
    start_scan(page, 0, 470, 2, "to be canceled")
    page.wait_for_function("window.lsu.progressPct >= 5", timeout=180000)
    assert graph["scanner"].state().laser_on or True  # the laser blinks under the guard on a loaded host
    page.click("#btn-cancel")
    page.wait_for_function("window.lsu.lastResult !== null", timeout=120000)
    result = page.evaluate("window.lsu.lastResult")
    assert result["outcome"] == "CANCELED" and result["partial"], result
    assert result["snaps"] < 236
    assert "The laser is off." in page.inner_text("#scan-message")
    # the driver's own state, read by this test's client after the end: off
    assert driver_laser_after(graph, time.monotonic()) is False
    page.close()


def test_a_closed_tab_leaves_the_laser_off(graph):
    page = open_page(graph)
    page.click("#tabs button[data-tab=hardware]")
    # the carriage moves where the page says: the driver's position, read by this test's own client
    page.fill("#move-to", "200")
    page.click("#btn-move")
    page.wait_for_function("document.querySelector('#hw-message').textContent.includes('at 200 steps')", timeout=60000)
    assert graph["scanner"].state().position_steps == 200
    page.fill("#laser-seconds", "30")
    page.click("#btn-laser-on")
    page.wait_for_function("!document.querySelector('#laser-message').textContent.includes('working')", timeout=30000)
    assert "laser on for at most 30 s" in page.inner_text("#laser-message")
    assert driver_laser_after(graph, time.monotonic()) is True
    page.close()  # the tab goes away while the laser is on
    end = time.monotonic() + 25
    while driver_laser_after(graph, time.monotonic()) and time.monotonic() < end:
        time.sleep(0.1)
    assert driver_laser_after(graph, time.monotonic()) is False
    # the cause: the server switched it off because the page closed (not the 30 s bound)
    with urllib.request.urlopen(graph["url"] + "api/status", timeout=10) as r:
        status = json.loads(r.read())
    assert status["laser"]["why_off"] == "the page that switched the laser on was closed"


def test_malformed_requests_get_a_reason_and_change_nothing(graph):
    url = graph["url"]
    before = sorted(p.name for p in graph["scans"].iterdir()) if graph["scans"].is_dir() else []
    code, body = http(url + "api/scan", "POST", {"mode": "stopsnap", "step": 0})
    assert code == 422 and b"step" in body
    code, body = http(url + "api/scan", "POST", {"mode": "spiral"})
    assert code == 422 and b"mode" in body
    code, body = http(url + "api/scan", "POST", {"start": 300, "end": 100})
    assert code == 422 and b"before start" in body
    code, _ = http(url + "api/scans/..%2F..%2Fetc/files/passwd")
    assert 400 <= code < 500
    code, _ = http(url + "api/hardware/laser", "POST", {"on": True, "seconds": 3600, "client": 1})
    assert code == 422
    code, _ = http(url + "api/scan", "POST", {}, headers={"Origin": "http://evil.example"})
    assert code == 403
    time.sleep(1.0)
    after = sorted(p.name for p in graph["scans"].iterdir()) if graph["scans"].is_dir() else []
    assert after == before
    assert graph["scanner"].state().laser_on is False


def test_a_wrong_token_is_refused(graph):
    port = free_port()
    token_file = graph["tmp"] / "token"
    proc = LaunchedProcess(["web", "--port", str(port), "--require-token", "--token-file", str(token_file),
                            "--scans", str(graph["scans"])])
    try:
        proc.wait_for_line(r"lsu web: open (http://\S+)", timeout_s=60)
        token = token_file.read_text().strip()
        assert oct(token_file.stat().st_mode & 0o777) == "0o600"
        assert token in proc.output  # shown once, when it was made
        url = f"http://127.0.0.1:{port}/"
        assert http(url + "api/status")[0] == 401
        assert http(url + "api/status", headers={"Authorization": "Bearer " + "x" * len(token)})[0] == 401
        assert http(url + "api/status", headers={"Authorization": "Bearer " + token})[0] == 200
        page = graph["browser"].new_page()
        response = page.goto(url + "?token=wrong")
        assert response.status == 401 and "wrong token" in page.content()
        # the WebSocket without the cookie is refused too
        opened = page.evaluate(f"""() => new Promise((res) => {{ const w = new WebSocket('ws://127.0.0.1:{port}/ws');
            w.onopen = () => res(true); w.onclose = () => res(false); w.onerror = () => res(false); }})""")
        assert opened is False
        page.goto(url + "?token=" + token, wait_until="commit", timeout=60000)  # a cookie from now on
        page.wait_for_function("window.lsu && window.lsu.connected", timeout=120000)
        assert "token" not in page.url
        page.close()
    finally:
        proc.stop(timeout_s=10)


def test_calibration_capture_judges_real_pairs(graph):
    """The sim scene is a head: a captured pair is judged and refused for the reason that holds (no board)."""
    url = graph["url"]
    assert http(url + "api/calibration/start", "POST", {"board": "9y6"})[0] == 422
    code, body = http(url + "api/calibration/start", "POST", {"board": "9x6", "square_mm": 25, "min_views": 8})
    assert code == 200 and json.loads(body)["views"] == 0
    code, body = http(url + "api/calibration/capture", "POST", {})
    status = json.loads(body)
    assert code == 200 and status["captures"] == 1 and status["views"] == 0
    assert status["last"] == {"accepted": False, "reason": "board not found in left image"}
    code, body = http(url + "api/calibration/solve", "POST", {})
    assert code == 422 and b"capture pairs" in body


def gallery_names(path: Path) -> list[str]:
    """The names in the gallery file, read by lsu_faces' own gallery class (not through the page)."""
    from lsu_faces.gallery import Gallery

    return sorted({e.name for e in Gallery(str(path)).list()})


def test_sweep_then_enrol_identify_and_remove_in_the_page(graph):
    """A sweep scan started from the page; its face enrolled under a name, identified as that name and removed,
    each through the page's Faces tab; the gallery file (read by lsu_faces, not the page) holds what the page said."""
    page = open_page(graph)
    start_scan(page, 0, 470, 2, "sweep face", mode="sweep")
    page.wait_for_function("window.lsu.lastResult !== null", timeout=300000)
    result = page.evaluate("window.lsu.lastResult")
    assert result["outcome"] == "SUCCEEDED", result
    record = json.loads((Path(result["output_dir"]) / "scan.json").read_text())
    assert record["goal"]["label"] == "sweep face" and record["goal"]["mode"] == "sweep" and record["sweep"], record
    assert record["points"] > 10000, {k: record.get(k) for k in ("status", "partial", "sweep")}
    # the face processor writes the mesh a moment after the scan: the library shows it when it is there
    page.wait_for_function("window.lsu.meshLoaded", timeout=180000)

    page.click("#tabs button[data-tab=faces]")
    page.wait_for_function("!document.querySelector('#btn-enroll').disabled", timeout=30000)
    page.wait_for_selector(f"#face-scan option[value='{result['scan_id']}']", state="attached", timeout=30000)
    page.select_option("#face-scan", result["scan_id"])
    assert gallery_names(graph["gallery"]) == []
    page.fill("#face-name", "alice")
    page.click("#btn-enroll")
    page.wait_for_function("!document.querySelector('#face-message').textContent.includes('enrolling')",
                           timeout=180000)
    assert "enrolled as entry" in page.inner_text("#face-message"), page.inner_text("#face-message")
    page.wait_for_selector("#gallery button[data-name='alice']", timeout=30000)
    assert gallery_names(graph["gallery"]) == ["alice"]

    page.click("#btn-identify")
    page.wait_for_function("!document.querySelector('#face-message').textContent.includes('identifying')",
                           timeout=180000)
    assert page.inner_text("#face-message").startswith("identified: alice"), page.inner_text("#face-message")

    page.once("dialog", lambda dialog: dialog.accept())  # "Remove alice (all samples) from the gallery?"
    page.click("#gallery button[data-name='alice']")
    page.wait_for_function("document.querySelector('#gallery').textContent.includes('the gallery is empty')",
                           timeout=30000)
    assert gallery_names(graph["gallery"]) == []
    page.close()


def test_calibration_in_the_page_says_why_a_pair_is_refused(graph):
    """The sim scene is a person, not a board: the page's capture is judged and refused for the reason that holds,
    and Calibrate says what is missing; the session's state on the server agrees."""
    page = open_page(graph)
    page.click("#tabs button[data-tab=calibration]")
    page.fill("#cal-board", "9x6")
    page.click("#btn-cal-start")
    page.wait_for_function("document.querySelector('#cal-message').textContent.includes('session started')",
                           timeout=60000)
    page.click("#btn-cal-capture")
    page.wait_for_function("document.querySelector('#cal-message').textContent.includes('board not found')",
                           timeout=120000)
    page.click("#btn-cal-solve")
    page.wait_for_function("document.querySelector('#cal-message').textContent.includes('not calibrated')",
                           timeout=60000)
    assert "capture pairs" in page.inner_text("#cal-message"), page.inner_text("#cal-message")
    code, body = http(graph["url"] + "api/calibration")
    status = json.loads(body)
    assert code == 200 and status["captures"] == 1 and status["views"] == 0
    page.close()

