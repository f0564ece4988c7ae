"""PointCloud2 codec: round trips, byte order, padding, foreign layouts, rgb packing, NaN refusal."""

import struct

import numpy as np
import pytest

from lsu_bags.pointcloud2 import (
    FLOAT32,
    FLOAT64,
    LSU_FIELDS,
    UINT8,
    UINT32,
    Cloud,
    CloudError,
    PointField,
    decode,
    encode,
    pack_rgb,
    unpack_rgb,
)


def columns(n=37, seed=5):
    rng = np.random.default_rng(seed)
    return {"x": rng.normal(size=n), "y": rng.normal(size=n), "z": rng.uniform(0.2, 0.4, n),
            "rgb": pack_rgb(rng.integers(0, 256, (n, 3))), "u": rng.uniform(0, 640, n),
            "v": rng.uniform(0, 480, n), "snap": rng.integers(0, 200, n).astype(np.uint32)}


@pytest.mark.parametrize("bigendian", [False, True])
def test_lsu_layout_round_trip(bigendian):
    cols = columns()
    cloud = encode(cols, is_bigendian=bigendian)
    assert [f.name for f in cloud.fields] == ["x", "y", "z", "rgb", "u", "v", "snap"]
    assert cloud.point_step == 28 and cloud.row_step == 28 * 37 and len(cloud.data) == 28 * 37
    out = decode(cloud)
    for name in ("x", "y", "z", "u", "v"):
        assert np.array_equal(out[name], cols[name].astype(np.float32))
    assert np.array_equal(out["snap"], cols["snap"])
    assert np.array_equal(out["rgb"].view(np.uint32), cols["rgb"].view(np.uint32))


def test_byte_order_is_what_the_flag_says():
    cloud_le = encode({"x": [1.5], "y": [0.0], "z": [0.0], "rgb": [0.0], "u": [0.0], "v": [0.0], "snap": [7]})
    cloud_be = encode({"x": [1.5], "y": [0.0], "z": [0.0], "rgb": [0.0], "u": [0.0], "v": [0.0], "snap": [7]},
                      is_bigendian=True)
    assert cloud_le.data[:4] == struct.pack("<f", 1.5) and cloud_be.data[:4] == struct.pack(">f", 1.5)
    assert cloud_le.data[24:28] == struct.pack("<I", 7) and cloud_be.data[24:28] == struct.pack(">I", 7)


def test_padding_inside_points_is_zero_and_skipped():
    cols = columns(5)
    cloud = encode(cols, point_step=32)
    assert cloud.point_step == 32 and len(cloud.data) == 160
    raw = np.frombuffer(cloud.data, np.uint8).reshape(5, 32)
    assert not raw[:, 28:].any()
    assert np.array_equal(decode(cloud)["z"], cols["z"].astype(np.float32))


def test_row_padding_is_skipped():
    # A 2x3 organised cloud with 4 spare bytes at the end of each row, written by hand.
    rows = []
    for r in range(2):
        row = b"".join(struct.pack("<fff", r, c, r * 10 + c) for c in range(3))
        rows.append(row + b"\xff" * 4)
    fields = [PointField("x", 0, FLOAT32), PointField("y", 4, FLOAT32), PointField("z", 8, FLOAT32)]
    cloud = Cloud(fields, b"".join(rows), width=3, height=2, point_step=12, row_step=40)
    out = decode(cloud)
    assert out["z"].tolist() == [0, 1, 2, 10, 11, 12]


def test_foreign_xyz_only_cloud_reads():
    # PCL-style PointXYZ: x y z float32 + 4 bytes of padding, big-endian from another machine.
    pts = [(0.1, 0.2, 0.3), (1.0, -2.0, 3.5)]
    data = b"".join(struct.pack(">fff", *p) + b"\0\0\0\0" for p in pts)
    fields = [PointField("x", 0, FLOAT32), PointField("y", 4, FLOAT32), PointField("z", 8, FLOAT32)]
    cloud = Cloud(fields, data, width=2, point_step=16, row_step=32, is_bigendian=True)
    out = decode(cloud, ["x", "y", "z"])
    assert np.allclose(np.c_[out["x"], out["y"], out["z"]], pts)
    assert out["x"].dtype.byteorder in ("=", "<")
    with pytest.raises(CloudError, match="no field.*rgb"):
        decode(cloud, ["x", "rgb"])


def test_custom_fields_with_count_and_float64():
    fields = [PointField("xyz", 0, FLOAT64, 3), PointField("intensity", 24, UINT8)]
    xyz = np.arange(12.0).reshape(4, 3)
    cloud = encode({"xyz": xyz, "intensity": [1, 2, 3, 4]}, fields=fields)
    assert cloud.point_step == 25
    out = decode(cloud)
    assert np.array_equal(out["xyz"], xyz) and out["intensity"].tolist() == [1, 2, 3, 4]


def test_rgb_packing_matches_pcl_bits():
    packed = pack_rgb(np.array([[0x12, 0x34, 0x56]]))
    assert packed.dtype == np.float32
    assert packed.view(np.uint32)[0] == 0x00123456
    assert unpack_rgb(packed).tolist() == [[0x12, 0x34, 0x56]]


def test_nan_coordinates_are_refused():
    cols = columns(3)
    cols["y"][1] = np.nan
    with pytest.raises(CloudError, match="'y'.*NaN"):
        encode(cols)


def test_inconsistent_layouts_are_clear_errors():
    with pytest.raises(CloudError, match="needs"):
        decode(Cloud(LSU_FIELDS, b"\0" * 10, width=2, point_step=28, row_step=56))
    with pytest.raises(CloudError, match="does not fit"):
        decode(Cloud([PointField("x", 26, FLOAT32)], b"\0" * 28, width=1, point_step=28, row_step=28))
    with pytest.raises(CloudError, match="no data"):
        encode({"x": [1.0]})
    with pytest.raises(CloudError, match="unknown datatype"):
        decode(Cloud([PointField("x", 0, 42)], b"\0" * 4, width=1, point_step=4))


def test_empty_cloud_round_trip():
    cloud = encode({k: np.zeros(0) for k in ("x", "y", "z", "rgb", "u", "v", "snap")})
    assert cloud.width == 0 and cloud.data == b""
    assert decode(cloud)["x"].shape == (0,)
    assert UINT32 == 6  # sensor_msgs/PointField.UINT32
