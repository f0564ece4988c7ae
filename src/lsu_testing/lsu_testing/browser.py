"""The web page's browser tests: `lsu launch sim web:=true` with Debian's Chromium driven by Playwright (headless,
no browser download), a page opened and connected, a scan started from its form."""

from __future__ import annotations

import contextlib
import socket
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

from .plugin import LaunchedProcess

__all__ = ["CHROMIUM", "free_port", "web_sim_graph", "open_page", "start_scan"]

CHROMIUM = Path("/usr/bin/chromium")


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


@contextlib.contextmanager
def web_sim_graph(tmp: Path, *args: str) -> Iterator[dict[str, Any]]:
    """`lsu launch sim web:=true` (``args`` added) with scans under ``tmp``/scans and a headless Chromium, once the
    carriage is homed, the page served and the cameras open: {"proc", "url", "scans", "tmp", "browser"}. Skips the
    test where Chromium or Playwright is missing."""
    if not CHROMIUM.is_file():
        pytest.skip("no /usr/bin/chromium (make setup installs Debian's chromium)")
    playwright_api = pytest.importorskip("playwright.sync_api")
    port = free_port()
    # capture and ack timeouts sized for a loaded 2-core host: these tests test the page, not the deadlines
    proc = LaunchedProcess(["launch", "sim", f"port:={tmp / 'gp32'}", f"output_dir:={tmp / 'scans'}", "web:=true",
                            f"web_port:={port}", "capture_timeout_s:=10.0", "ack_timeout_s:=60.0", *args])
    try:
        proc.wait_for_line(r"\[gp32_driver\].*homed: track 470", timeout_s=90)
        proc.wait_for_line(r"\[web_server\] lsu web: open (http://\S+)", timeout_s=90)
        proc.wait_for_line(r"\[stereo_camera\].*source 'sim' open", timeout_s=90)
        with playwright_api.sync_playwright() as pw:
            browser = pw.chromium.launch(executable_path=str(CHROMIUM), args=["--no-sandbox"])
            yield {"proc": proc, "url": f"http://127.0.0.1:{port}/", "scans": tmp / "scans", "tmp": tmp,
                   "browser": browser}
            browser.close()
    finally:
        proc.stop(timeout_s=15)


def open_page(g: dict[str, Any], url: str | None = None) -> Any:
    """A new page of ``g``'s browser on the server's URL, once its WebSocket is connected and greeted."""
    page = g["browser"].new_page(viewport={"width": 1400, "height": 1000}, accept_downloads=True)
    # "load" waits for the WebGL set-up too, which a loaded host's software GL may take tens of seconds for
    page.goto(url or g["url"], wait_until="commit", timeout=60000)
    try:
        page.wait_for_function("window.lsu && window.lsu.connected && window.lsu.clientId > 0", timeout=120000)
    except Exception:
        web_lines = [line for line in g["proc"].output.splitlines() if "[web_server]" in line][-30:]
        raise AssertionError(f"the page did not connect: window.lsu = {page.evaluate('JSON.stringify(window.lsu || null)')}"
                             f"\nweb_server said:\n" + "\n".join(web_lines)) from None
    return page


def start_scan(page: Any, start: int, end: int, step: int, name: str, record_bag: bool = False,
               mode: str = "stopsnap") -> None:
    """Fill the page's scan form and press Start (a sweep's own fields, rate and frames, as they are)."""
    page.select_option("select[name=mode]", mode)
    page.fill("input[name=name]", name)
    page.fill("input[name=start]", str(start))
    page.fill("input[name=end]", str(end))
    if mode == "stopsnap":
        page.fill("input[name=step]", str(step))
    if record_bag:
        page.check("input[name=record_bag]")
    page.click("#btn-start")
