"""lsu_web: the web page for the person at the scanner (`lsu web`).

Framework: FastAPI on uvicorn (both pinned in requirements.lock). FastAPI gives typed request models
(pydantic: a malformed request is answered 422 with the field and the reason before any route runs),
WebSockets and static files from Starlette, and runs on asyncio, which the graph thread reaches with
``loop.call_soon_threadsafe``. aiohttp would serve as well but has no request models; Tornado (FabScan
Pi's) neither. The server is one more client of the graph (`graph.WebGraph`); the page is plain
HTML/JS/CSS in ``static/`` with three.js vendored (``static/vendor/three``), no build step, no CDN.
The only things the server keeps are the page's own: the goal handle of a scan it started (an action
client must hold it), a hardware-panel laser hold (so that it can end it) and the calibration
session's kept board views (`calib`).
"""
