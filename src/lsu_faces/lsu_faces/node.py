"""The ``face_processor`` node: scan cloud -> mesh, renders, nose tip; face gallery services.

A thin adapter over :mod:`lsu_faces.pipeline` and :mod:`lsu_faces.gallery`:

- subscribes ``scan/cloud`` (PointCloud2 x y z rgb u v snap; reliable, transient-local) and
  ``scan/events`` (to learn the scan id and its output folder);
- publishes ``scan/mesh`` (Marker TRIANGLE_LIST with vertex colours) and ``scan/mesh_shape``
  (shape_msgs/Mesh), both transient-local, and ``face/nose`` (PointStamped);
- writes mesh.ply, mesh.obj and front/side renders into the scan's folder (``output_dir`` of the
  scan events, else ``<output_dir>/<scan id or time>``);
- serves ``face/identify`` and, only when the read-only parameter ``allow_enrolment`` is true,
  ``face/enroll`` (lsu_interfaces/srv/Enroll, Identify) on a private SQLite gallery (``gallery_file``;
  any process on the DDS domain can call a service, and a gallery is biometric data). Identify
  accepts the best match at the stated ``false_accept_rate`` (a stranger's chance calibrated on the
  gallery's own searches or impostor distances, see :mod:`lsu_faces.gallery`).

Bad input (empty or tiny cloud, no u/v, not a face, unreadable files, locked or corrupt gallery) is
logged as one line and returned in the service message; no exception escapes a callback.
"""

from __future__ import annotations

import datetime as _dt
import struct
import sys
from pathlib import Path
from typing import Any

import numpy as np
from diagnostic_msgs.msg import DiagnosticArray
from geometry_msgs.msg import Point, PointStamped
from sensor_msgs.msg import PointCloud2
from shape_msgs.msg import Mesh, MeshTriangle
from std_msgs.msg import ColorRGBA, Header
from visualization_msgs.msg import Marker

from lsu_common import diagnostics, qos
from lsu_common.arrays import AnyArray
from lsu_common.node import LsuNode, main_of
from lsu_common.params import Param, declare_parameters
from lsu_interfaces.msg import ScanEvent
from lsu_interfaces.srv import Enroll, Identify

from .face import NOSE_METHODS, FaceParams
from .gallery import DEFAULT_FALSE_ACCEPT, Gallery, GalleryError
from .mesh import FaceMesh, MeshParams
from .pipeline import ProcessParams, ScanResult, load_cloud_file, process_cloud, write_outputs
from .signature import SIGNATURE_METHODS, SignatureParams
from .smoothing import METHODS as SMOOTH_METHODS
from .smoothing import SmoothParams

__all__ = ["FaceProcessorNode", "mesh_to_marker", "mesh_to_shape", "marker_cdr", "shape_cdr", "main"]

LATCHED = qos.LATCHED
EVENTS = qos.EVENTS


def _marker_template(header: Header) -> Marker:
    m = Marker(header=header, ns="lsu_scan_mesh", id=0, type=Marker.TRIANGLE_LIST, action=Marker.ADD)
    m.pose.orientation.w = 1.0
    m.scale.x = m.scale.y = m.scale.z = 1.0
    m.color = ColorRGBA(r=0.8, g=0.8, b=0.8, a=1.0)
    return m


def _marker_arrays(mesh: FaceMesh, max_triangles: int) -> tuple[AnyArray, AnyArray | None]:
    """Points (3 per triangle) and their RGBA colours in [0, 1] (or None) of the TRIANGLE_LIST of ``mesh``."""
    tri = mesh.triangles
    if max_triangles and len(tri) > max_triangles:
        # RViz draws every point of the list: keep an even subset of a huge mesh
        tri = tri[np.linspace(0, len(tri) - 1, max_triangles).astype(np.int64)]
    flat = tri.reshape(-1)
    if mesh.colors is None:
        return mesh.vertices[flat], None
    rgba = np.ones((len(flat), 4))
    rgba[:, :3] = mesh.colors[flat].astype(np.float64) / 255.0
    return mesh.vertices[flat], rgba


def mesh_to_marker(mesh: FaceMesh, header: Header, max_triangles: int = 0) -> Marker:
    """A TRIANGLE_LIST Marker (three points per triangle, one colour per point) of ``mesh``."""
    v, rgba = _marker_arrays(mesh, max_triangles)
    m = _marker_template(header)
    m.points = [Point(x=float(a), y=float(b), z=float(c)) for a, b, c in v.tolist()]
    if rgba is not None:
        m.colors = [ColorRGBA(r=float(r), g=float(g), b=float(b), a=1.0) for r, g, b, _ in rgba.tolist()]
    return m


def mesh_to_shape(mesh: FaceMesh) -> Mesh:
    """shape_msgs/Mesh of ``mesh`` (unused vertices dropped)."""
    m = mesh.compact()
    out = Mesh()
    out.vertices = [Point(x=float(a), y=float(b), z=float(c)) for a, b, c in m.vertices.tolist()]
    out.triangles = [MeshTriangle(vertex_indices=np.asarray(t, dtype=np.uint32)) for t in m.triangles.tolist()]
    return out


# The node publishes the two mesh messages as serialized bytes written from the numpy arrays, not as
# the message objects above: those hold one Python object per point, triangle and colour (several per
# triangle of the mesh). Building and dropping that many small objects every scan makes CPython's
# object allocator map fresh 1 MiB arenas, and any long-lived object allocated meanwhile keeps its
# arena mapped after the scan (gc.collect and malloc_trim cannot release it), so the node's resident
# memory grew with every scan although nothing was kept. The bytes must deserialize to the same
# message as the objects' serialization (test_node checks it).
_SCALARS = {"boolean": "<?", "octet": "<B", "uint8": "<B", "int8": "<b", "int16": "<h", "uint16": "<H",
            "int32": "<i", "uint32": "<I", "int64": "<q", "uint64": "<Q", "float": "<f", "double": "<d"}


class _Cdr:
    """Little-endian CDR, as rclpy's ``serialize_message`` writes it and ``Publisher.publish(bytes)`` sends it,
    of messages whose large sequences are given as arrays; every other sequence must be empty. Alignment
    counts from after the 4-byte encapsulation header; padding bytes are zero."""

    def __init__(self) -> None:
        self.parts: list[bytes] = [b"\x00\x01\x00\x00"]  # CDR_LE, options 0
        self.size = 0

    def _put(self, data: bytes, align: int = 1) -> None:
        pad = -self.size % align
        if pad:
            self.parts.append(bytes(pad))
        self.parts.append(data)
        self.size += pad + len(data)

    def message(self, msg: Any, arrays: dict[str, tuple[int, int, bytes]] | None = None) -> _Cdr:
        """Append ``msg``; ``arrays`` maps a sequence field to (element count, element alignment, element bytes)."""
        for name, kind in msg.get_fields_and_field_types().items():
            value = getattr(msg, name)
            if arrays and name in arrays:
                count, align, data = arrays[name]
                self._put(struct.pack("<I", count), 4)
                if count:
                    self._put(data, align)
            elif kind in _SCALARS:
                fmt = _SCALARS[kind]
                self._put(struct.pack(fmt, value), struct.calcsize(fmt))
            elif kind == "string":
                self._put(struct.pack("<I", len(value.encode()) + 1) + value.encode() + b"\x00", 4)
            elif kind.startswith("sequence<"):
                if len(value):
                    raise ValueError(f"{type(msg).__name__}.{name}: only empty sequences are written field by field")
                self._put(struct.pack("<I", 0), 4)
            elif "/" in kind and not kind.endswith("]"):
                self.message(value)
            else:
                raise ValueError(f"{type(msg).__name__}.{name}: field type {kind} not supported")
        return self

    def tobytes(self) -> bytes:
        return b"".join(self.parts)


def marker_cdr(mesh: FaceMesh, header: Header, max_triangles: int = 0) -> bytes:
    """``mesh_to_marker(mesh, header, max_triangles)`` serialized, without building its point objects."""
    v, rgba = _marker_arrays(mesh, max_triangles)
    arrays = {"points": (len(v), 8, np.ascontiguousarray(v, dtype="<f8").tobytes())}
    if rgba is not None:
        arrays["colors"] = (len(rgba), 4, np.ascontiguousarray(rgba, dtype="<f4").tobytes())
    return _Cdr().message(_marker_template(header), arrays).tobytes()


def shape_cdr(mesh: FaceMesh) -> bytes:
    """``mesh_to_shape(mesh)`` serialized, without building its point and triangle objects."""
    m = mesh.compact()
    return _Cdr().message(Mesh(), {
        "triangles": (m.n_triangles, 4, np.ascontiguousarray(m.triangles, dtype="<u4").tobytes()),
        "vertices": (m.n_vertices, 8, np.ascontiguousarray(m.vertices, dtype="<f8").tobytes())}).tobytes()


def parameter_table() -> dict[str, Param]:
    """The node's parameters: every one is read where it is used, so a set takes effect at the next scan or call."""
    mp, sp, fp, gp = MeshParams(), SmoothParams(), FaceParams(), SignatureParams()
    return {
        "output_dir": Param("~/.lsu/faces", "folder for mesh.ply, mesh.obj and renders when the scan events name no "
                            "folder (a sub-folder per scan)"),
        "gallery_file": Param("~/.lsu/faces/gallery.db", "SQLite face gallery used by face/enroll and face/identify"),
        "scans_dir": Param("", "folder searched for <scan_id>/cloud.ply by the services' scan_id (empty: output_dir)"),
        "write_files": Param(True, "write mesh.ply, mesh.obj and the renders for every scan"),
        "render_size_px": Param(480, "side of the square front/side renders [px]", (16, 8192)),
        "max_edge_factor": Param(mp.max_edge_factor, "cull triangles with an edge longer than this x the median edge "
                                 "(> 1)", (1.0, 1000.0)),
        "max_stretch": Param(mp.max_stretch, "cull triangles stretched more than this x the median (depth jumps; > 1)",
                             (1.0, 1000.0)),
        "smoothing": Param(sp.method, "mesh smoothing: taubin (no shrinkage), laplacian (thesis) or none"),
        "smoothing_iterations": Param(sp.iterations, "Laplacian iterations or Taubin passes", (0, 10000)),
        "laplacian_factor": Param(sp.factor, "Laplacian step towards the neighbour centroid (thesis: 0.1)",
                                  (0.0, 1.0)),
        "taubin_lambda": Param(sp.taubin_lambda, "Taubin shrink step (0..1)", (0.0, 1.0)),
        "taubin_mu": Param(sp.taubin_mu, "Taubin inflate step (< -taubin_lambda)", (-1.0, 0.0)),
        "allow_enrolment": Param(False, "serve face/enroll (biometric data: off unless the lab decides; set at "
                                 "launch only). face/identify is always served", read_only=True),
        "nose_method": Param(fp.nose_method, "nose tip finder: template (verified by the face's layout), "
                             "protrusion or svd (thesis)"),
        "signature_method": Param(gp.method, "face signature: depthmap (ICP-aligned) or fft (thesis)"),
        "false_accept_rate": Param(DEFAULT_FALSE_ACCEPT, "identify accepts the best match only when the chance that "
                                   "a stranger's search comes as close (calibrated on the gallery itself) is at most this "
                                   "(FPIR per search, 0..1)",
                                   (0.0, 1.0)),
        "marker_max_triangles": Param(60000, "triangles sent in the scan/mesh Marker (0 = all)", (0, 100_000_000)),
    }


class FaceProcessorNode(LsuNode):
    """Meshes every scan cloud, finds the face, and serves the gallery (see module doc)."""

    def __init__(self, **kwargs: Any) -> None:
        super().__init__("face_processor", **{"namespace": "/lsu", **kwargs})
        declare_parameters(self, parameter_table(), check=self._check_parameters)

        self.latest: ScanResult | None = None
        self.scan_id = ""
        self.scan_dir = ""
        self.processed = 0
        self.errors = 0
        self.last_error = ""
        self._gallery: Gallery | None = None
        self._gallery_path = ""
        self.mesh_pub = self.create_publisher(Marker, "scan/mesh", LATCHED)
        self.shape_pub = self.create_publisher(Mesh, "scan/mesh_shape", LATCHED)
        self.nose_pub = self.create_publisher(PointStamped, "face/nose", 10)
        self.diag_pub = self.create_publisher(DiagnosticArray, "/diagnostics", 10)
        self.create_subscription(PointCloud2, "scan/cloud", self.on_cloud, LATCHED)
        self.create_subscription(ScanEvent, "scan/events", self.on_event, EVENTS)
        self.create_service(Enroll, "face/enroll", self.on_enroll)
        self.create_service(Identify, "face/identify", self.on_identify)
        self.create_timer(1.0, self.publish_diagnostics)

    # ------------------------------------------------------------------ parameters
    def _check_parameters(self, params: list[Any]) -> str | None:
        """Choices and open bounds (the closed ranges are in the descriptors, checked by rclpy)."""
        choices = {"smoothing": SMOOTH_METHODS, "nose_method": NOSE_METHODS, "signature_method": SIGNATURE_METHODS}
        for p in params:
            if p.name in choices and p.value not in choices[p.name]:
                return f"{p.name} must be one of {', '.join(choices[p.name])}"
            if p.name == "false_accept_rate" and not 0.0 < p.value < 1.0:
                return "false_accept_rate must be between 0 and 1 (e.g. 0.01 for 1 %)"
            if p.name in ("max_edge_factor", "max_stretch") and p.value <= 1.0:
                return f"{p.name} must be greater than 1"
        return None

    def _value(self, name: str) -> Any:
        return self.get_parameter(name).value

    def process_params(self) -> ProcessParams:
        """The processing chain's settings from the node parameters."""
        v = self._value
        return ProcessParams(
            mesh=MeshParams(max_edge_factor=float(v("max_edge_factor")), max_stretch=float(v("max_stretch"))),
            smoothing=SmoothParams(method=str(v("smoothing")), iterations=int(v("smoothing_iterations")),
                                   factor=float(v("laplacian_factor")), taubin_lambda=float(v("taubin_lambda")),
                                   taubin_mu=float(v("taubin_mu"))),
            face=FaceParams(nose_method=str(v("nose_method"))),
            signature=SignatureParams(method=str(v("signature_method"))))

    def gallery(self) -> Gallery:
        """The gallery named by ``gallery_file`` (one object per file: its index and calibration are kept,
        and checked against the file on every use)."""
        path = str(self._value("gallery_file"))
        if self._gallery is None or str(self._gallery_path) != path:
            self._gallery, self._gallery_path = Gallery(path), path
        return self._gallery

    def _error(self, text: str) -> str:
        self.errors += 1
        self.last_error = text
        self.get_logger().error(text)
        return text

    # ------------------------------------------------------------------ scan data
    def on_event(self, msg: ScanEvent) -> None:
        """Remember the running scan's id and folder (files of its cloud go there)."""
        if msg.type == ScanEvent.STARTED or (msg.scan_id and msg.scan_id != self.scan_id):
            self.scan_id = msg.scan_id
            self.scan_dir = msg.output_dir
        elif msg.output_dir:
            self.scan_dir = msg.output_dir

    def _folder(self) -> Path:
        if self.scan_dir:
            return Path(self.scan_dir).expanduser()
        name = self.scan_id or _dt.datetime.now().strftime("%Y%m%d-%H%M%S")
        return Path(str(self._value("output_dir"))).expanduser() / name

    def on_cloud(self, msg: PointCloud2) -> None:
        """Mesh, smooth, texture, write, find the face; publish mesh and nose."""
        try:
            result = self._process_msg(msg)
        except Exception as exc:  # noqa: BLE001 - a bad cloud must never take the node down
            self._error(f"scan cloud not processed: {exc.__class__.__name__}: {exc}")
            return
        if result is None:
            return
        self.latest = result
        self.processed += 1
        frame_id = msg.header.frame_id or "lsu_left_optical"
        header = Header(stamp=msg.header.stamp, frame_id=frame_id)
        if result.mesh is not None:
            self.mesh_pub.publish(marker_cdr(result.mesh, header, int(self._value("marker_max_triangles"))))
            self.shape_pub.publish(shape_cdr(result.mesh))
        if result.nose is not None:
            tip = result.frame.origin if result.frame is not None else result.nose.tip
            self.nose_pub.publish(PointStamped(header=header, point=Point(x=float(tip[0]), y=float(tip[1]),
                                                                          z=float(tip[2]))))
        files: list[Path] = []
        if result.mesh is not None and bool(self._value("write_files")):
            try:
                files = write_outputs(result, self._folder(), int(self._value("render_size_px")))
            except (OSError, ValueError) as exc:
                self._error(f"cannot write the mesh files to {self._folder()}: {exc}")
        for text in result.messages:
            self.get_logger().warning(f"scan {self.scan_id or '(no id)'}: {text}")
        what = f"scan {self.scan_id or '(no id)'}: {len(result.points)} points"
        if result.mesh is not None:
            what += f", mesh of {result.mesh.n_triangles} triangles"
        if result.nose is not None:
            what += f", nose at {np.round(result.nose.tip * 1000, 1).tolist()} mm"
        if files:
            what += f", {len(files)} files in {files[0].parent}"
        self.get_logger().info(what)

    def _process_msg(self, msg: PointCloud2) -> ScanResult | None:
        from lsu_bags.pointcloud2 import decode, from_msg

        cloud = from_msg(msg)
        names = [f.name for f in msg.fields]
        missing = [n for n in ("x", "y", "z") if n not in names]
        if missing:
            self._error(f"scan cloud has no {', '.join(missing)} field(s); it has {', '.join(names) or 'none'}: not an "
                        f"LSU cloud")
            return None
        if cloud.n_points == 0:
            self._error("scan cloud is empty: no points were triangulated (is the laser visible to both cameras?)")
            return None
        wanted = [n for n in ("x", "y", "z", "rgb", "u", "v") if n in names]
        columns = decode(cloud, wanted)
        try:
            return process_cloud(columns, self.process_params())
        except ValueError as exc:
            self._error(f"scan cloud not processed: {exc}")
            return None

    # ------------------------------------------------------------------ services
    def _result_for(self, cloud_file: str, scan_id: str) -> ScanResult:
        if scan_id:
            base = Path(str(self._value("scans_dir") or self._value("output_dir"))).expanduser()
            hits = [p for p in (base / scan_id / "cloud.ply",) if p.is_file()] or sorted(base.glob(f"*{scan_id}*/cloud.ply"))
            if not hits:
                raise FileNotFoundError(f"no cloud.ply of scan '{scan_id}' under {base}")
            cloud_file = str(hits[0])
        if cloud_file:
            loaded = load_cloud_file(cloud_file)
            return process_cloud(loaded["columns"], self.process_params(), loaded["faces"])  # type: ignore[arg-type]
        if self.latest is None:
            raise LookupError("no scan cloud received yet on scan/cloud; scan first or give cloud_file")
        return self.latest

    def on_enroll(self, request: Enroll.Request, response: Enroll.Response) -> Enroll.Response:
        """face/enroll: add the face of a cloud (file, scan id or the latest scan) under ``name``."""
        try:
            if not bool(self._value("allow_enrolment")):
                raise PermissionError("enrolment through the ROS services is off (parameter allow_enrolment, set at "
                                      "launch); enrol with 'lsu face enroll' as the gallery's owner, or launch the "
                                      "face_processor with allow_enrolment:=true")
            if not request.name.strip():
                raise ValueError("name is empty; give the person's name")
            result = self._result_for(request.cloud_file, request.scan_id)
            if result.signature is None:
                raise ValueError("; ".join(result.messages) or "no face in this cloud")
            mesh_file = ""
            if request.cloud_file:
                mesh_file = request.cloud_file
            elif result.mesh is not None:
                mesh_file = str(self._folder() / "mesh.ply")
            response.entry_id = self.gallery().enroll(request.name, result.signature, mesh_file)
            response.points_used = int(result.signature.points_used)
            response.success = True
            self.get_logger().info(f"enrolled '{request.name}' as entry {response.entry_id}")
        except (ValueError, LookupError, OSError, GalleryError) as exc:
            response.success = False
            response.message = self._error(f"enrol failed: {exc}")
        return response

    def on_identify(self, request: Identify.Request, response: Identify.Response) -> Identify.Response:
        """face/identify: rank the gallery against the face of a cloud."""
        try:
            result = self._result_for(request.cloud_file, request.scan_id)
            if result.signature is None:
                raise ValueError("; ".join(result.messages) or "no face in this cloud")
            ident = self.gallery().identify(result.signature, int(request.max_results or 5),
                                            float(self._value("false_accept_rate")))
            matches = ident.matches
            response.names = [m.name for m in matches]
            response.scores = [float(m.score) for m in matches]
            response.entry_ids = [int(m.entry_id) for m in matches]
            response.accepted = ident.accepted
            response.best_name = matches[0].name if response.accepted else ""
            response.success = True
            if not matches:
                response.message = "the gallery is empty; enrol faces first"
            elif not response.accepted:
                response.message = f"rejected: {ident.reason}"
        except (ValueError, LookupError, OSError, GalleryError) as exc:
            response.success = False
            response.message = self._error(f"identify failed: {exc}")
        return response

    # ------------------------------------------------------------------ diagnostics
    def publish_diagnostics(self) -> None:
        """Processing counts and the last error on /diagnostics."""
        self.diag_pub.publish(diagnostics.status_array(
            self, diagnostics.WARN if self.errors else diagnostics.OK,
            f"{self.get_fully_qualified_name()}: face processing",
            f"{self.processed} clouds processed, {self.errors} errors",
            {"processed": self.processed, "errors": self.errors, "last_error": self.last_error},
            hardware_id="lsu_faces"))


main = main_of(FaceProcessorNode)


if __name__ == "__main__":
    sys.exit(main())
