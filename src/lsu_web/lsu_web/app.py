"""The HTTP + WebSocket server (FastAPI on uvicorn): pages, the JSON API and the live WebSocket.

Every route only asks the graph (`WebGraph`) or reads the scan folders (`Library`); blocking graph
calls run in worker threads (``asyncio.to_thread``), so the event loop keeps serving while a homing
runs. Requests are checked by `security.Access` before any route sees them. Bodies are pydantic
models with ranges: a malformed request gets 422 with the field and the reason, and nothing is sent
to the graph.
"""

from __future__ import annotations

import asyncio
import html
import importlib.metadata
import json
import os
import platform
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal

from fastapi import FastAPI, HTTPException, Request, WebSocket, WebSocketDisconnect
from fastapi.responses import FileResponse, HTMLResponse, JSONResponse, RedirectResponse, Response
from fastapi.staticfiles import StaticFiles
from pydantic import BaseModel, Field

from .library import DOWNLOADS, Library, LibraryError
from .outbox import ClientBox, Outbox
from .security import COOKIE, Access, bearer

STATIC = Path(__file__).parent / "static"
THREE_VERSION = "0.187.0"  # static/vendor/three/README.md


class ScanRequest(BaseModel):
    """A scan goal from the page; the ranges are the action's (Scan.action), checked before it is sent."""

    model_config = {"extra": "forbid"}
    mode: Literal["stopsnap", "sweep"] = "stopsnap"
    start: int = Field(0, ge=0, le=10000)
    end: int = Field(470, ge=0, le=10000)
    step: int = Field(2, ge=1, le=500)
    settle_s: float = Field(0.1, ge=0.0, le=5.0)
    sweep_rate: float = Field(60.0, ge=20.0, le=180.0)
    fps: float = Field(30.0, ge=1.0, le=60.0)
    texture: bool = True
    record_bag: bool = False
    name: str = Field("", max_length=200)


class MoveRequest(BaseModel):
    model_config = {"extra": "forbid"}
    position: int = Field(..., ge=0, le=10000)


class LaserRequest(BaseModel):
    model_config = {"extra": "forbid"}
    on: bool
    seconds: float = Field(10.0, gt=0.0, le=30.0)
    client: int = Field(0, ge=0)


class CalibrationStart(BaseModel):
    model_config = {"extra": "forbid"}
    board: str = Field("9x6", pattern=r"^[0-9]{1,2}x[0-9]{1,2}$")
    square_mm: float = Field(25.0, gt=1.0, le=200.0)
    min_views: int = Field(8, ge=3, le=100)


class LaserCalibration(BaseModel):
    model_config = {"extra": "forbid"}
    scan_ids: list[str] = Field(..., min_length=1, max_length=20)


class FaceRequest(BaseModel):
    model_config = {"extra": "forbid"}
    scan_id: str = Field(..., min_length=1, max_length=128)
    name: str = Field("", max_length=100)


@dataclass
class WebConfig:
    host: str
    port: int
    access: Access
    scans_dir: Path | None = None  # None: the coordinator's output_dir parameter
    extra: dict[str, Any] = field(default_factory=dict)


class AccessMiddleware:
    """Host, Origin and token checks on every HTTP request (WebSockets are checked in their route).

    Plain ASGI (not Starlette's BaseHTTPMiddleware, which wraps every response in its own stream): a
    refusal is answered here, anything else goes to the app untouched.
    """

    def __init__(self, app: Any, access: Access) -> None:
        self.app = app
        self.access = access

    async def __call__(self, scope: Any, receive: Any, send: Any) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        refusal = self.refusal(Request(scope))
        if refusal is not None:
            await refusal(scope, receive, send)
            return
        await self.app(scope, receive, send)

    def refusal(self, request: Request) -> Response | None:
        a = self.access
        host = request.headers.get("host")
        if not a.host_ok(host):
            return JSONResponse({"detail": f"unknown Host '{host}': open the page as the server printed it"}, 421)
        if not a.origin_ok(request.headers.get("origin"), host):
            return JSONResponse({"detail": "cross-origin request refused (no CORS: only this page may use the API)"},
                                403)
        if a.token is None or request.url.path in ("/login", "/login.css", "/favicon.ico"):
            return None
        query_token = request.query_params.get("token")
        if query_token is not None and request.method == "GET":
            if not a.token_ok(query_token):
                return login_page("wrong token", status=401)
            # the token leaves the address bar (and the history) at once: a cookie carries it from now on
            response = RedirectResponse(request.url.path, status_code=303)
            set_token_cookie(response, query_token, request)
            return response
        offered = request.cookies.get(COOKIE) or bearer(request.headers.get("authorization"))
        if not a.token_ok(offered):
            if request.method == "GET" and not request.url.path.startswith("/api/"):
                return login_page("" if offered is None else "wrong token", status=401)
            return JSONResponse({"detail": "token required: open /login (or send 'Authorization: Bearer TOKEN')"},
                                401)
        return None


def set_token_cookie(response: Response, token: str, request: Request) -> None:
    response.set_cookie(COOKIE, token, httponly=True, samesite="strict", secure=request.url.scheme == "https",
                        path="/")


def login_page(message: str = "", status: int = 200) -> HTMLResponse:
    note = f'<p class="err">{html.escape(message)}</p>' if message else ""
    return HTMLResponse(f"""<!doctype html><html><head><meta charset="utf-8"><title>LSU: token</title>
<link rel="stylesheet" href="/login.css"></head><body class="login"><form method="post" action="/login">
<h1>LSU scanner</h1><p>This page is served to other machines: enter the token <code>lsu web</code> printed when it made
it (or read it on the scanner PC: <code>lsu web --show-token</code>).</p>{note}
<input name="token" type="password" autocomplete="off" autofocus placeholder="token">
<button type="submit">Open</button></form></body></html>""", status_code=status)


LOGIN_CSS = """body.login{font-family:system-ui,sans-serif;background:#1d2330;color:#e8ecf3;display:flex;
justify-content:center;align-items:center;height:100vh;margin:0}form{background:#283042;padding:2em;border-radius:8px;
max-width:26em}input{width:100%;padding:.5em;margin:.5em 0;box-sizing:border-box}button{padding:.5em 1.5em}
.err{color:#ff8a80}code{background:#1d2330;padding:0 .3em}"""


def create_app(graph: Any, config: WebConfig, outbox: Outbox) -> FastAPI:
    """The app for one `WebGraph`; ``graph`` may be any object with the same methods (tests)."""
    app = FastAPI(title="LSU scanner", docs_url=None, redoc_url=None, openapi_url=None)
    app.add_middleware(AccessMiddleware, access=config.access)
    app.mount("/static", StaticFiles(directory=STATIC), name="static")
    scans: dict[str, Path] = {}

    async def library() -> Library:
        if config.scans_dir is not None:
            return Library(config.scans_dir)
        if "root" not in scans:
            try:
                params = await asyncio.to_thread(graph.parameters, "/lsu/scan_coordinator", 5.0)
                value = str(params.get("output_dir") or "")
            except TimeoutError:
                return Library(Path.cwd() / "scans")  # not cached: ask again once the coordinator is up
            scans["root"] = Path(value).expanduser() if value else Path.cwd() / "scans"
        return Library(scans["root"])

    def refuse(exc: Exception, status: int = 409) -> HTTPException:
        return HTTPException(status, str(exc))

    # ------------------------------------------------------------------ pages
    @app.get("/", include_in_schema=False)
    async def index() -> FileResponse:
        return FileResponse(STATIC / "index.html", headers={"Cache-Control": "no-cache"})

    @app.get("/favicon.ico", include_in_schema=False)
    async def favicon() -> Response:
        return Response(status_code=204)

    @app.get("/login", include_in_schema=False)
    async def login_form() -> HTMLResponse:
        return login_page()

    @app.get("/login.css", include_in_schema=False)
    async def login_css() -> Response:
        return Response(LOGIN_CSS, media_type="text/css")

    @app.post("/login", include_in_schema=False)
    async def login(request: Request) -> Response:
        form = (await request.body()).decode(errors="replace")
        from urllib.parse import parse_qs

        offered = (parse_qs(form).get("token") or [""])[0].strip()
        if not config.access.token_ok(offered):
            return login_page("wrong token", status=401)
        response = RedirectResponse("/", status_code=303)
        if config.access.token is not None:
            set_token_cookie(response, offered, request)
        return response

    # ------------------------------------------------------------------ status and scans
    @app.get("/api/status")
    async def status() -> dict[str, Any]:
        return {"state": outbox.latest("state"), "progress": outbox.latest("progress"), "laser": outbox.latest("laser"),
                "scanning": graph.scanning(), "clients": outbox.count}

    @app.post("/api/scan")
    async def start_scan(req: ScanRequest) -> dict[str, Any]:
        from lsu_scan.scanner import ScannerError

        if req.end < req.start and req.mode == "stopsnap":
            raise HTTPException(422, f"end ({req.end}) is before start ({req.start})")
        if req.mode == "sweep" and req.end == req.start:
            raise HTTPException(422, "a sweep needs start and end apart")
        if graph.laser_hold is not None:
            raise HTTPException(409, "the hardware panel holds the laser on: switch it off first")
        goal = {"mode": req.mode, "start": req.start, "end": req.end, "step": req.step, "settle_s": req.settle_s,
                "sweep_rate_steps_s": req.sweep_rate, "frame_rate_hz": req.fps, "texture": req.texture,
                "record_bag": req.record_bag, "label": req.name}
        try:
            await asyncio.to_thread(graph.start_scan, goal)
        except (ScannerError, TimeoutError) as exc:
            raise refuse(exc) from None
        return {"started": True, "goal": goal}

    @app.post("/api/scan/cancel")
    async def cancel_scan() -> dict[str, Any]:
        try:
            return {"message": await asyncio.to_thread(graph.cancel_scan)}
        except TimeoutError as exc:
            raise refuse(exc, 503) from None

    # ------------------------------------------------------------------ library
    @app.get("/api/scans")
    async def scans_list() -> dict[str, Any]:
        lib = await library()
        return {"root": str(lib.root), "scans": await asyncio.to_thread(lib.list),
                "downloads": {k: v[2] for k, v in DOWNLOADS.items()}}

    @app.get("/api/scans/{scan_id}")
    async def scan_detail(scan_id: str) -> dict[str, Any]:
        lib = await library()
        try:
            folder = lib.folder(scan_id)
        except LibraryError as exc:
            raise refuse(exc, exc.status) from None
        return {**lib.summary(folder), "record": lib.record(folder)}

    @app.delete("/api/scans/{scan_id}")
    async def scan_delete(scan_id: str) -> dict[str, Any]:
        lib = await library()
        running = outbox.latest("progress") or {}
        if graph.scanning() and running.get("scan_id") == scan_id:
            raise HTTPException(409, "this scan is still running: cancel it first")
        try:
            folder = await asyncio.to_thread(lib.delete, scan_id)
        except LibraryError as exc:
            raise refuse(exc, exc.status) from None
        return {"deleted": folder.name}

    @app.get("/api/scans/{scan_id}/files/{name:path}")
    async def scan_file(scan_id: str, name: str) -> FileResponse:
        lib = await library()
        try:
            return FileResponse(lib.file(scan_id, name))
        except LibraryError as exc:
            raise refuse(exc, exc.status) from None

    @app.get("/api/scans/{scan_id}/download/{kind}")
    async def scan_download(scan_id: str, kind: str) -> Response:
        lib = await library()
        try:
            body, media, filename = await asyncio.to_thread(lib.download, scan_id, kind)
        except LibraryError as exc:
            raise refuse(exc, exc.status) from None
        if isinstance(body, Path):
            return FileResponse(body, media_type=media, filename=filename)
        return Response(body, media_type=media, headers={"Content-Disposition": f'attachment; filename="{filename}"'})

    # ------------------------------------------------------------------ hardware test panel
    def idle_or_409() -> None:
        if graph.scanning():
            raise HTTPException(409, "a scan is running: the hardware panel waits until it ends (or cancel it)")

    @app.post("/api/hardware/home")
    async def home() -> dict[str, Any]:
        from lsu_scan.scanner import ScannerError

        idle_or_409()
        try:
            return {"message": await asyncio.to_thread(graph.scanner.home, 60.0)}
        except (ScannerError, TimeoutError) as exc:
            raise refuse(exc) from None

    @app.post("/api/hardware/move")
    async def move(req: MoveRequest) -> dict[str, Any]:
        from lsu_scan.scanner import ScannerError

        idle_or_409()
        state = outbox.latest("state") or {}
        if state.get("track") and req.position > int(state["track"]):
            raise HTTPException(422, f"position {req.position} is beyond the track ({state['track']} steps)")
        try:
            return {"position": await asyncio.to_thread(graph.scanner.move_to, req.position, 30.0)}
        except (ScannerError, TimeoutError) as exc:
            raise refuse(exc) from None

    @app.post("/api/hardware/laser")
    async def laser(req: LaserRequest) -> dict[str, Any]:
        from lsu_scan.scanner import ScannerError

        try:
            if not req.on:
                await asyncio.to_thread(graph.laser_off, "switched off on the page")
                return {"laser": "off", "message": "laser off"}
            idle_or_409()
            if req.client not in ws_clients:
                raise HTTPException(422, "laser on needs the page's live connection (client id from the WebSocket "
                                         "hello): a closed page must be able to switch it off")
            seconds = await asyncio.to_thread(graph.laser_on_for, req.client, req.seconds)
            return {"laser": "on", "seconds": seconds, "message": f"laser on for at most {seconds:g} s"}
        except (ScannerError, TimeoutError) as exc:
            raise refuse(exc) from None

    # ------------------------------------------------------------------ faces
    async def face_params() -> dict[str, Any]:
        try:
            return await asyncio.to_thread(graph.parameters, "/lsu/face_processor", 5.0)
        except TimeoutError as exc:
            raise refuse(exc, 503) from None

    @app.get("/api/faces")
    async def faces() -> dict[str, Any]:
        params = await face_params()
        allowed = bool(params.get("allow_enrolment"))
        names: list[dict[str, Any]] = []
        if allowed:
            from lsu_faces.gallery import Gallery, GalleryError

            try:
                entries = await asyncio.to_thread(Gallery(str(params.get("gallery_file"))).list)
            except GalleryError as exc:
                raise refuse(exc) from None
            counts: dict[str, int] = {}
            for e in entries:
                counts[e.name] = counts.get(e.name, 0) + 1
            names = [{"name": n, "samples": c} for n, c in sorted(counts.items())]
        return {"enrolment": allowed, "names": names}

    async def face_cloud(scan_id: str) -> str:
        lib = await library()
        try:
            return str(lib.file(scan_id, "cloud.ply"))
        except LibraryError as exc:
            raise refuse(exc, exc.status) from None

    @app.post("/api/faces/enroll")
    async def enroll(req: FaceRequest) -> dict[str, Any]:
        from lsu_interfaces.srv import Enroll

        if not req.name.strip():
            raise HTTPException(422, "name is empty: give the person's name")
        if not bool((await face_params()).get("allow_enrolment")):
            raise HTTPException(403, "this gallery does not allow enrolment through the graph (face_processor "
                                     "allow_enrolment is false)")
        cloud = await face_cloud(req.scan_id)
        try:
            r = await asyncio.to_thread(graph.call, graph.enroll_client,
                                        Enroll.Request(name=req.name.strip(), cloud_file=cloud), 120.0, "enrol")
        except TimeoutError as exc:
            raise refuse(exc, 503) from None
        if not r.success:
            raise HTTPException(422, r.message)
        return {"entry_id": int(r.entry_id), "points_used": int(r.points_used)}

    @app.post("/api/faces/identify")
    async def identify(req: FaceRequest) -> dict[str, Any]:
        from lsu_interfaces.srv import Identify

        cloud = await face_cloud(req.scan_id)
        try:
            r = await asyncio.to_thread(graph.call, graph.identify_client,
                                        Identify.Request(cloud_file=cloud, max_results=5), 120.0, "identify")
        except TimeoutError as exc:
            raise refuse(exc, 503) from None
        if not r.success:
            raise HTTPException(422, r.message)
        return {"accepted": bool(r.accepted), "best_name": r.best_name, "message": r.message,
                "matches": [{"name": n, "score": round(float(s), 3)} for n, s in zip(r.names, r.scores)]}

    @app.delete("/api/faces/{name}")
    async def face_remove(name: str) -> dict[str, Any]:
        params = await face_params()
        if not bool(params.get("allow_enrolment")):
            raise HTTPException(403, "this gallery does not allow changes through the graph")
        from lsu_faces.gallery import Gallery, GalleryError

        try:
            removed = await asyncio.to_thread(Gallery(str(params.get("gallery_file"))).remove, name)
        except GalleryError as exc:
            raise refuse(exc) from None
        if not removed:
            raise HTTPException(404, f"no '{name}' in the gallery")
        return {"removed": removed}

    # ------------------------------------------------------------------ calibration
    from .calib import CalibrationSession, laser_calibration

    session = CalibrationSession()

    async def calibration_dir() -> str:
        try:
            params = await asyncio.to_thread(graph.parameters, "/lsu/scan_coordinator", 5.0)
        except TimeoutError:
            return ""
        return str(params.get("calibration_dir") or "")

    @app.get("/api/calibration")
    async def calibration_status() -> dict[str, Any]:
        calib = await calibration_dir()
        shown = os.path.normpath(calib) if calib else ""
        if shown and Path(shown).is_relative_to(Path.cwd()):
            shown = str(Path(shown).relative_to(Path.cwd()))  # shorter, and what a user in the checkout types
        return {**session.status(), "calibration_dir": calib, "calibration_dir_shown": shown}

    @app.post("/api/calibration/start")
    async def calibration_start(req: CalibrationStart) -> dict[str, Any]:
        from lsu_cameras.calibration import CalibrationError

        try:
            session.reset(req.board, req.square_mm, req.min_views)
        except CalibrationError as exc:
            raise HTTPException(422, str(exc)) from None
        return session.status()

    @app.post("/api/calibration/capture")
    async def calibration_capture() -> dict[str, Any]:
        if session.tracker is None:
            raise HTTPException(409, "start a calibration session first (board size and square)")
        try:
            left, right = await asyncio.to_thread(graph.capture_pair)
        except (RuntimeError, TimeoutError) as exc:
            raise refuse(exc) from None
        return await asyncio.to_thread(session.consider, left, right)

    @app.post("/api/calibration/solve")
    async def calibration_solve() -> dict[str, Any]:
        from lsu_cameras.calibration import CalibrationError

        lib = await library()
        try:
            return await asyncio.to_thread(session.solve, lib.root)
        except (ValueError, CalibrationError) as exc:
            raise HTTPException(422, str(exc)) from None

    @app.post("/api/calibration/laser")
    async def calibration_laser(req: LaserCalibration) -> dict[str, Any]:
        from lsu_reconstruct.laser_sheet import LaserSheetError

        lib = await library()
        try:
            folders = [lib.folder(s) for s in req.scan_ids]
        except LibraryError as exc:
            raise refuse(exc, exc.status) from None
        calib = await calibration_dir()
        if not calib:
            raise HTTPException(503, "scan_coordinator does not say its calibration_dir: is it running?")
        try:
            return await asyncio.to_thread(laser_calibration, folders, Path(calib), lib.root)
        except LaserSheetError as exc:
            raise HTTPException(422, str(exc)) from None

    # ------------------------------------------------------------------ about
    @app.get("/api/about")
    async def about() -> dict[str, Any]:
        versions = {}
        for dist in sorted(importlib.metadata.distributions(), key=lambda d: d.metadata["Name"] or ""):
            name = dist.metadata["Name"] or ""
            if name.startswith("lsu") or name in ("fastapi", "uvicorn", "starlette", "numpy", "opencv-python",
                                                  "opencv-python-headless", "open3d", "rclpy", "rosbags"):
                versions[name] = dist.version
        versions["three.js"] = THREE_VERSION
        versions["python"] = platform.python_version()
        nodes = await asyncio.to_thread(graph.node_names)
        coordinator: dict[str, Any] = {}
        try:
            coordinator = await asyncio.to_thread(graph.parameters, "/lsu/scan_coordinator", 3.0)
        except TimeoutError:
            pass
        lib = await library()
        return {"versions": versions, "ros_distro": os.environ.get("ROS_DISTRO", "jazzy"),
                "ros_domain_id": os.environ.get("ROS_DOMAIN_ID", ""), "nodes": nodes,
                "server": {"host": config.host, "port": config.port, "token_required": config.access.token is not None,
                           "scans_dir": str(lib.root), "image_max_hz": graph.image_max_hz, **config.extra},
                "scan_coordinator": coordinator}

    # ------------------------------------------------------------------ live WebSocket
    ws_clients: set[int] = set()

    @app.websocket("/ws")
    async def live(ws: WebSocket) -> None:
        a = config.access
        host = ws.headers.get("host")
        offered = ws.cookies.get(COOKIE) or bearer(ws.headers.get("authorization")) or ws.query_params.get("token")
        if not a.host_ok(host) or not a.origin_ok(ws.headers.get("origin"), host) or not a.token_ok(offered):
            await ws.close(code=1008, reason="token, host or origin refused")
            return
        await ws.accept()
        box = ClientBox(asyncio.get_running_loop())
        cid = outbox.add(box)
        ws_clients.add(cid)
        await ws.send_text(json.dumps({"type": "hello", "client": cid, "t": time.time()}))

        async def reader() -> None:
            while True:
                await ws.receive_text()  # the page sends nothing that matters; this notices a close

        read_task = asyncio.create_task(reader())
        try:
            while not read_task.done():
                take = asyncio.create_task(box.take())
                done, _ = await asyncio.wait({take, read_task}, return_when=asyncio.FIRST_COMPLETED)
                if take not in done:
                    take.cancel()
                    break
                for item in take.result():
                    if isinstance(item, bytes):
                        await ws.send_bytes(item)
                    else:
                        await ws.send_text(json.dumps(item, default=str))
        except (WebSocketDisconnect, RuntimeError, OSError):
            pass
        finally:
            read_task.cancel()
            outbox.remove(cid)
            ws_clients.discard(cid)
            await asyncio.to_thread(graph.client_gone, cid)

    return app
