"""face_processor round trip: PointCloud2 in -> Marker, Mesh and nose out; services; bad clouds never crash it."""

from __future__ import annotations

import numpy as np
import pytest

sim = pytest.importorskip("lsu_sim")
from lsu_faces.synthetic import fast_scan  # noqa: E402


@pytest.fixture(scope="module")
def head_scan():
    people = pytest.importorskip("lsu_sim.people")
    rig = sim.load_rig()
    centre = rig.rig_center + (rig.subject_distance_m + 0.10) * rig.rig_axes[2]
    objs = people.person_objects(people.make_person(people.PersonSpec(8, yaw_deg=10)), centre)
    sample = fast_scan(objs, rig, np.arange(0, 471, 5), noise_m=5e-5, drop_fraction=0.1, seed=8)
    return sample.columns, objs[0].extra["nose_tip_m"]


def _msg(columns, fields=None):
    from std_msgs.msg import Header

    from lsu_bags.pointcloud2 import FLOAT32, encode, layout
    from lsu_reconstruct.node import cloud_to_msg

    if fields is None:
        cloud = encode(columns)
    else:
        f, step = layout([(n, FLOAT32) for n in fields])
        cloud = encode({n: columns[n] for n in fields}, f, step)
    return cloud_to_msg(cloud, Header(frame_id="lsu_left_optical"))


def test_cloud_in_mesh_and_nose_out_then_enroll_identify(ros_node, tmp_path, head_scan):
    from geometry_msgs.msg import PointStamped
    from rclpy.parameter import Parameter
    from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
    from sensor_msgs.msg import PointCloud2
    from shape_msgs.msg import Mesh
    from visualization_msgs.msg import Marker

    from lsu_faces.node import FaceProcessorNode
    from lsu_interfaces.srv import Enroll, Identify

    columns, truth = head_scan
    node = ros_node.add(FaceProcessorNode(context=ros_node.context, parameter_overrides=[
        Parameter("output_dir", value=str(tmp_path / "out")), Parameter("gallery_file", value=str(tmp_path / "g.db")),
        Parameter("render_size_px", value=96), Parameter("allow_enrolment", value=True)]))
    latched = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE, durability=DurabilityPolicy.TRANSIENT_LOCAL)
    got = {}
    h = ros_node.node
    h.create_subscription(Marker, "/lsu/scan/mesh", lambda m: got.setdefault("marker", m), latched)
    h.create_subscription(Mesh, "/lsu/scan/mesh_shape", lambda m: got.setdefault("shape", m), latched)
    h.create_subscription(PointStamped, "/lsu/face/nose", lambda m: got.setdefault("nose", m), 10)
    pub = h.create_publisher(PointCloud2, "/lsu/scan/cloud", latched)
    pub.publish(_msg(columns))
    assert ros_node.spin_until(lambda: {"marker", "shape", "nose"} <= set(got), 180.0), f"got only {sorted(got)}"
    marker = got["marker"]
    assert marker.type == Marker.TRIANGLE_LIST and len(marker.points) % 3 == 0 and len(marker.points) > 0
    assert len(marker.colors) == len(marker.points)
    assert len(got["shape"].triangles) > 0
    p = got["nose"].point
    assert np.linalg.norm(np.array([p.x, p.y, p.z]) - truth) < 0.005
    assert got["nose"].header.frame_id == "lsu_left_optical"
    wanted = {"mesh.ply", "mesh.obj", "render_front.png", "render_side.png"}

    def written() -> set:
        return {f.name for f in (tmp_path / "out").rglob("*") if f.is_file()}

    # files are written after the mesh and nose are published
    assert ros_node.spin_until(lambda: wanted <= written() and node.processed == 1, 30.0), written()

    enroll = h.create_client(Enroll, "/lsu/face/enroll")
    r = ros_node.call(enroll, Enroll.Request(name="eve"), 60.0)
    assert r.success, r.message
    assert r.entry_id > 0 and r.points_used > 100
    identify = h.create_client(Identify, "/lsu/face/identify")
    r = ros_node.call(identify, Identify.Request(max_results=3), 60.0)
    assert r.success and r.accepted and r.best_name == "eve" and r.scores[0] > 0.9
    r = ros_node.call(identify, Identify.Request(cloud_file=str(tmp_path / "missing.ply")), 30.0)
    assert not r.success and "not found" in r.message
    r = ros_node.call(enroll, Enroll.Request(name=""), 30.0)
    assert not r.success and "name" in r.message


def test_published_mesh_bytes_are_the_mesh_messages():
    """marker_cdr/shape_cdr (what the node publishes) deserialize to mesh_to_marker/mesh_to_shape."""
    from builtin_interfaces.msg import Time
    from rclpy.serialization import deserialize_message, serialize_message
    from shape_msgs.msg import Mesh
    from std_msgs.msg import Header
    from visualization_msgs.msg import Marker

    from lsu_faces.mesh import FaceMesh
    from lsu_faces.node import marker_cdr, mesh_to_marker, mesh_to_shape, shape_cdr

    rng = np.random.default_rng(3)
    vertices = rng.normal(size=(40, 3))
    triangles = rng.integers(0, 30, size=(25, 3))   # vertices 30..39 unused: the shape drops them
    colors = rng.integers(0, 256, size=(40, 3)).astype(np.uint8)
    header = Header(stamp=Time(sec=17, nanosec=123456789), frame_id="lsu_left_optical")
    for mesh in (FaceMesh(vertices, triangles, colors), FaceMesh(vertices, triangles[:1], None),
                 FaceMesh(vertices[:3], np.zeros((0, 3)), None)):
        for max_triangles in (0, 7):
            want = serialize_message(mesh_to_marker(mesh, header, max_triangles))
            got = marker_cdr(mesh, header, max_triangles)
            # equal up to the padding bytes, which rclpy leaves unset
            assert len(got) == len(want)
            assert deserialize_message(got, Marker) == deserialize_message(want, Marker)
        want, got = serialize_message(mesh_to_shape(mesh)), shape_cdr(mesh)
        assert len(got) == len(want)
        assert deserialize_message(got, Mesh) == deserialize_message(want, Mesh)


def test_bad_clouds_give_errors_not_exceptions(ros_node, tmp_path, head_scan):
    from rclpy.parameter import Parameter
    from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
    from sensor_msgs.msg import PointCloud2

    from lsu_faces.node import FaceProcessorNode

    columns, _ = head_scan
    node = ros_node.add(FaceProcessorNode(context=ros_node.context, parameter_overrides=[
        Parameter("output_dir", value=str(tmp_path / "out")), Parameter("write_files", value=False),
        Parameter("gallery_file", value=str(tmp_path / "g.db"))]))
    empty = {k: v[:0] for k, v in columns.items()}
    tiny = {k: v[:10] for k, v in columns.items()}
    cases = [(empty, None, "empty"), (tiny, None, "fewer than")]
    latched = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE, durability=DurabilityPolicy.TRANSIENT_LOCAL)
    pub = ros_node.node.create_publisher(PointCloud2, "/lsu/scan/cloud", latched)
    for cols, fields, words in cases:
        before = (node.errors, node.processed, node.latest)
        pub.publish(_msg(cols, fields))
        assert ros_node.spin_until(lambda: (node.errors, node.processed, node.latest) != before, 30.0)
        text = node.last_error + " ".join(node.latest.messages if node.latest else [])
        assert words in text, text
    # enrolment through ROS is off unless the read-only parameter allows it; nothing is written
    from lsu_interfaces.srv import Enroll

    enroll = ros_node.node.create_client(Enroll, "/lsu/face/enroll")
    r = ros_node.call(enroll, Enroll.Request(name="mallory"), 30.0)
    assert not r.success and "allow_enrolment" in r.message
    assert not (tmp_path / "g.db").exists()
    assert not node.set_parameters([Parameter("allow_enrolment", value=True)])[0].successful


def test_every_face_parameter_takes_effect_when_set_or_is_refused(ros_node, tmp_path):
    from lsu_faces.node import FaceProcessorNode

    node = ros_node.add(FaceProcessorNode(context=ros_node.context, namespace="/lsu_faces_params"))
    pp = node.process_params
    used = lambda name, value: (lambda: node._value(name) == value)  # noqa: E731  (read where used)
    ros_node.check_parameters(node, {
        "output_dir": (str(tmp_path), lambda: node._folder().parent == tmp_path),
        "gallery_file": (str(tmp_path / "g.db"), used("gallery_file", str(tmp_path / "g.db"))),
        "scans_dir": (str(tmp_path), used("scans_dir", str(tmp_path))),
        "write_files": (False, used("write_files", False)),
        "render_size_px": (256, used("render_size_px", 256)),
        "marker_max_triangles": (1000, used("marker_max_triangles", 1000)),
        "false_accept_rate": (0.05, used("false_accept_rate", 0.05)),
        "max_edge_factor": (4.0, lambda: pp().mesh.max_edge_factor == 4.0),
        "max_stretch": (5.0, lambda: pp().mesh.max_stretch == 5.0),
        "smoothing": ("laplacian", lambda: pp().smoothing.method == "laplacian"),
        "smoothing_iterations": (12, lambda: pp().smoothing.iterations == 12),
        "laplacian_factor": (0.2, lambda: pp().smoothing.factor == 0.2),
        "taubin_lambda": (0.4, lambda: pp().smoothing.taubin_lambda == 0.4),
        "taubin_mu": (-0.45, lambda: pp().smoothing.taubin_mu == -0.45),
        "nose_method": ("svd", lambda: pp().face.nose_method == "svd"),
        "signature_method": ("fft", lambda: pp().signature.method == "fft"),
    })
    for name, value in (("smoothing", "blur"), ("false_accept_rate", 0.0), ("max_stretch", 1.0),
                        ("render_size_px", -1)):
        refused = ros_node.set_parameter("/lsu_faces_params/face_processor", name, value)
        assert not refused.successful and refused.reason, name
    assert pp().smoothing.method == "laplacian" and node._value("false_accept_rate") == 0.05
