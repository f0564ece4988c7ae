"""lsu_web without ROS or a browser: the token file, the request checks, the library's path rules, the outbox."""

import asyncio
import json
import stat

import pytest

from lsu_web.library import Library, LibraryError, mesh_to_stl
from lsu_web.outbox import BULK, CONTROL, ClientBox, Outbox
from lsu_web.security import access_for, bearer, load_or_make_token


def test_token_is_made_once_private_and_kept(tmp_path):
    path = tmp_path / "cfg" / "web_token"
    token, made = load_or_make_token(path)
    assert made and len(token) >= 40
    assert stat.S_IMODE(path.stat().st_mode) == 0o600
    again, made_again = load_or_make_token(path)
    assert (again, made_again) == (token, False)
    renewed, made3 = load_or_make_token(path, renew=True)
    assert made3 and renewed != token
    path.chmod(0o644)
    with pytest.raises(PermissionError, match="chmod 600"):
        load_or_make_token(path)


def test_access_checks_token_host_and_origin():
    open_local = access_for("127.0.0.1", None)
    assert open_local.token_ok(None)
    assert open_local.host_ok("127.0.0.1:8080") and open_local.host_ok("localhost:8080")
    assert open_local.host_ok("127.0.0.1:9000") and open_local.host_ok("[::1]:8080")  # an SSH tunnel's other port
    assert not open_local.host_ok("evil.example:8080") and not open_local.host_ok(None)  # a DNS-rebinding page
    assert open_local.origin_ok(None, "127.0.0.1:8080")
    assert open_local.origin_ok("http://127.0.0.1:8080", "127.0.0.1:8080")
    assert not open_local.origin_ok("http://evil.example", "127.0.0.1:8080")
    guarded = access_for("0.0.0.0", "s3cret-token-" + "x" * 30)
    assert not guarded.token_ok(None) and not guarded.token_ok("wrong")
    assert guarded.token_ok("s3cret-token-" + "x" * 30)
    assert bearer("Bearer abc") == "abc" and bearer("Basic abc") is None


@pytest.fixture
def library(tmp_path):
    root = tmp_path / "scans"
    scan = root / "20261206-070406-0001"
    (scan / "renders").mkdir(parents=True)
    (scan / "scan.json").write_text(json.dumps({"status": "finished", "points": 3, "snaps_captured": 2,
                                                "snaps_expected": 2, "goal": {"label": "alice", "mode": "sweep"},
                                                "timings_s": {"scan": 4.5}}))
    (scan / "render_front.png").write_bytes(b"\x89PNG")
    (tmp_path / "secret.txt").write_text("not yours")
    (scan / "link_out").symlink_to(tmp_path / "secret.txt")
    return Library(root)


def test_library_lists_what_scan_json_says(library):
    rows = library.list()
    assert [r["id"] for r in rows] == ["20261206-070406-0001"]
    r = rows[0]
    assert (r["label"], r["mode"], r["snaps"], r["points"], r["seconds"]) == ("alice", "sweep", 2, 3, 4.5)
    assert r["thumbnail"] == "render_front.png" and r["downloads"] == ["scan.json"]


@pytest.mark.parametrize("scan_id, name, status", [
    ("..", "scan.json", 400), ("../scans/20261206-070406-0001", "scan.json", 400), ("nope", "scan.json", 404),
    ("20261206-070406-0001", "../../secret.txt", 403), ("20261206-070406-0001", "/etc/passwd", 400),
    ("20261206-070406-0001", "link_out", 403), ("20261206-070406-0001", "cloud.ply", 404),
])
def test_library_refuses_names_outside_the_scan_folder(library, scan_id, name, status):
    with pytest.raises(LibraryError) as info:
        library.file(scan_id, name)
    assert info.value.status == status


def test_unknown_download_kind_is_refused_and_delete_removes_only_the_scan(library):
    with pytest.raises(LibraryError, match="unknown download"):
        library.download("20261206-070406-0001", "passwd")
    with pytest.raises(LibraryError):
        library.delete("..")
    assert library.root.is_dir()
    library.delete("20261206-070406-0001")
    assert library.list() == [] and (library.root.parent / "secret.txt").is_file()


def test_stl_has_the_mesh_triangles(tmp_path):
    import numpy as np
    import open3d as o3d

    mesh = o3d.geometry.TriangleMesh.create_box(0.01, 0.02, 0.03)
    o3d.io.write_triangle_mesh(str(tmp_path / "mesh.ply"), mesh)
    data = mesh_to_stl(tmp_path / "mesh.ply")
    # binary STL: 80-byte header, uint32 triangle count, 50 bytes a triangle
    count = int(np.frombuffer(data[80:84], "<u4")[0])
    assert count == len(mesh.triangles) == 12 and len(data) == 84 + 50 * count


def test_outbox_drops_the_oldest_and_never_grows():
    async def run():
        outbox = Outbox()
        box = ClientBox(asyncio.get_running_loop(), control_max=4, bulk_max=2)
        outbox.add(box)
        for i in range(100):
            outbox.publish(BULK, i)
        for i in range(10):
            outbox.publish(CONTROL, {"i": i}, latest_key="state")
        items = await box.take()
        late = ClientBox(asyncio.get_running_loop())
        outbox.add(late)
        return items, box.dropped, await late.take()

    items, dropped, late_items = asyncio.run(run())
    assert items == [{"i": 6}, {"i": 7}, {"i": 8}, {"i": 9}, 98, 99]  # control first, newest kept
    assert dropped == 98 + 6
    assert late_items == [{"i": 9}]  # a newcomer gets the latest state


class _GalleryClosedGraph:
    """Only what the faces routes ask of the graph: the face processor's parameters, enrolment off."""

    def __init__(self, gallery):
        self.gallery = gallery
        self.asked: list[str] = []

    def parameters(self, node_name, timeout_s=5.0):
        self.asked.append(node_name)
        return {"allow_enrolment": False, "gallery_file": str(self.gallery)}


def test_a_gallery_closed_to_enrolment_refuses_enrol_and_remove_and_lists_no_names(tmp_path):
    """The app (served by uvicorn, asked over HTTP) follows the face processor's allow_enrolment: off means no
    names shown, enrol and remove refused with the reason, and the gallery file untouched."""
    import socket
    import threading
    import time

    import uvicorn

    from lsu_testing.http import http
    from lsu_web.app import WebConfig, create_app

    gallery = tmp_path / "gallery.db"
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        port = int(sock.getsockname()[1])
    graph = _GalleryClosedGraph(gallery)
    app = create_app(graph, WebConfig("127.0.0.1", port, access_for("127.0.0.1", None), tmp_path / "scans"),
                     Outbox())
    server = uvicorn.Server(uvicorn.Config(app, host="127.0.0.1", port=port, log_level="warning"))
    thread = threading.Thread(target=server.run, daemon=True)
    thread.start()

    def ask(path, method="GET", body=None):
        code, answer = http(f"http://127.0.0.1:{port}{path}", method, body)
        return code, json.loads(answer)

    try:
        for _ in range(200):
            if server.started:
                break
            time.sleep(0.05)
        assert server.started
        assert ask("/api/faces") == (200, {"enrolment": False, "names": []})
        code, answer = ask("/api/faces/enroll", "POST", {"scan_id": "any", "name": "alice"})
        assert code == 403 and "allow_enrolment" in answer["detail"]
        code, answer = ask("/api/faces/alice", "DELETE")
        assert code == 403 and "does not allow" in answer["detail"]
        assert graph.asked and set(graph.asked) == {"/lsu/face_processor"}
    finally:
        server.should_exit = True
        thread.join(timeout=20)
    assert not gallery.exists()  # nothing was written for the refused requests
