"""PointCloud2 <-> numpy: property tests over random layouts, real scans, every validation error."""

from __future__ import annotations

import array
import dataclasses
import sys

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from pcc_ros.errors import MessageError
from pcc_ros.msg.pointcloud2 import DATATYPES, create_cloud, read_xyz, structured_view, validate
from pcc_ros.msg.stamps import stamp_to_ns
from pcc_ros.msg.typestore import get_typestore, new_message

PC2 = "sensor_msgs/msg/PointCloud2"


# ----------------------------------------------------------------------------- helpers
@st.composite
def layouts(draw, require_xyz: bool = False):
    """A random point layout: (dtype, height, width, seed). Fields may be unaligned, padded,
    of any of the 8 types, with count > 1; the whole cloud is big- or little-endian."""
    bigendian = draw(st.booleans())
    order = ">" if bigendian else "<"
    names = ["x", "y", "z"] if require_xyz else []
    extra = draw(
        st.lists(st.sampled_from(["intensity", "ring", "t", "rgb", "label", "normal"]), unique=True, max_size=3)
    )
    names += extra
    if not names:
        names = ["a"]
    names = draw(st.permutations(names))
    fields, offset = [], 0
    for name in names:
        offset += draw(st.integers(0, 5))  # padding before the field, alignment not guaranteed
        code = DATATYPES[draw(st.integers(7, 8) if name in "xyz" else st.integers(1, 8))][1]  # x, y, z: float
        count = 1 if name in "xyz" else draw(st.integers(1, 3))
        fields.append((name, np.dtype(order + code), count, offset))
        offset += np.dtype(code).itemsize * count
    point_step = offset + draw(st.integers(0, 8))
    dtype = np.dtype(
        {
            "names": [f[0] for f in fields],
            "formats": [f[1] if f[2] == 1 else (f[1], (f[2],)) for f in fields],
            "offsets": [f[3] for f in fields],
            "itemsize": point_step,
        }
    )
    height = draw(st.integers(1, 4))
    width = draw(st.integers(0, 17))
    return dtype, height, width, draw(st.integers(0, 2**31))


def random_points(dtype: np.dtype, height: int, width: int, seed: int) -> np.ndarray:
    """Values covering each type's full range; floats include NaN and +-inf."""
    rng = np.random.default_rng(seed)
    shape = (width,) if height == 1 else (height, width)
    out = np.zeros(shape, dtype=dtype)
    for name in dtype.names:
        fdtype = dtype.fields[name][0]
        base, sub = fdtype.base, fdtype.shape
        full = shape + sub
        if base.kind == "f":
            values = rng.normal(0, 50, full)
            special = rng.random(full)
            values[special < 0.05] = np.nan
            values[(special >= 0.05) & (special < 0.08)] = np.inf
            values[(special >= 0.08) & (special < 0.1)] = -np.inf
        else:
            info = np.iinfo(base)
            values = rng.integers(info.min, info.max, full, endpoint=True, dtype=base.newbyteorder("="))
        out[name] = values
    return out


def assert_struct_equal(a: np.ndarray, b: np.ndarray) -> None:
    assert a.shape == b.shape
    assert list(a.dtype.names) == list(b.dtype.names)
    for name in a.dtype.names:
        x, y = a[name], b[name]
        assert x.dtype.newbyteorder("=") == y.dtype.newbyteorder("=")
        assert np.array_equal(x, y, equal_nan=x.dtype.kind == "f"), name


def expected_xyz(points: np.ndarray, extra: tuple[str, ...], skip: bool) -> np.ndarray:
    flat = points.reshape(-1)
    if not len(flat):
        width = sum(int(np.prod(points.dtype[name].shape or (1,))) for name in ("x", "y", "z", *extra))
        return np.empty((0, width), np.float32)
    columns = [flat[name].reshape(len(flat), -1).astype(np.float32) for name in ("x", "y", "z", *extra)]
    out = np.concatenate(columns, axis=1)
    if skip:
        out = out[np.isfinite(out[:, :3]).all(axis=1)]
    return out


def cdr_round_trip(msg):
    store = get_typestore()
    return store.deserialize_cdr(store.serialize_cdr(msg, PC2), PC2)


def with_row_padding(msg, pad: int):
    """The same cloud with ``pad`` junk bytes after each row (row_step > point_step * width)."""
    rows = np.asarray(msg.data).reshape(msg.height, msg.row_step)
    junk = np.full((msg.height, pad), 0xAB, dtype=np.uint8)
    data = np.ascontiguousarray(np.concatenate([rows, junk], axis=1)).reshape(-1)
    return dataclasses.replace(msg, row_step=msg.row_step + pad, data=data)


def xyzi_cloud(n: int = 10, seed: int = 0):
    pts = np.random.default_rng(seed).normal(size=(n, 4)).astype(np.float32)
    return pts, create_cloud(pts, ["x", "y", "z", "intensity"], "velodyne", 1_700_000_000_123_456_789)


# ----------------------------------------------------------------------------- properties
SETTINGS = settings(max_examples=120, deadline=None, suppress_health_check=[HealthCheck.too_slow])


@SETTINGS
@given(layouts())
def test_decode_encode_round_trip(layout):
    dtype, height, width, seed = layout
    points = random_points(dtype, height, width, seed)
    msg = create_cloud(points, None, "lidar", 42)
    wide = [dtype.fields[n][0].base for n in dtype.names if dtype.fields[n][0].base.itemsize > 1]
    assert msg.is_bigendian == (wide[0].byteorder == ">" if wide else sys.byteorder == "big")
    assert msg.point_step == dtype.itemsize and msg.row_step == dtype.itemsize * width
    assert (msg.height, msg.width) == (height, width)
    assert len(msg.data) == msg.row_step * msg.height
    assert_struct_equal(structured_view(msg), points)
    back = cdr_round_trip(msg)
    assert_struct_equal(structured_view(back), points)
    if height > 1 and width > 0:
        assert_struct_equal(structured_view(with_row_padding(back, 3)), points)


@SETTINGS
@given(layouts(require_xyz=True), st.booleans(), st.booleans())
def test_read_xyz_matches_fields(layout, skip, with_extra):
    dtype, height, width, seed = layout
    points = random_points(dtype, height, width, seed)
    extra = tuple(n for n in dtype.names if n not in "xyz")[:2] if with_extra else ()
    msg = create_cloud(points, None, "lidar", 0)
    before = bytes(msg.data)
    want = expected_xyz(points, extra, skip)
    got = read_xyz(msg, extra, skip_nonfinite=skip)
    assert got.dtype == np.float32 and got.flags.c_contiguous
    np.testing.assert_array_equal(got, want)
    if height > 1 and width > 0:
        np.testing.assert_array_equal(read_xyz(with_row_padding(msg, 4), extra, skip_nonfinite=skip), want)
    assert bytes(msg.data) == before  # never byte-swapped or otherwise touched


@SETTINGS
@given(
    st.integers(0, 300),
    st.integers(1, 3),
    st.integers(0, 4),
    st.sampled_from(["<", ">"]),
    st.integers(0, 2**31),
)
def test_float32_fast_path_layouts(n, height, pad_words, order, seed):
    """Driver-like layouts: xyz float32 at 0, 4, 8, padding words, extra fields after."""
    words = 4 + pad_words
    dtype = np.dtype(
        {
            "names": ["x", "y", "z", "intensity"],
            "formats": [order + "f4"] * 4,
            "offsets": [0, 4, 8, 4 * (words - 1)],
            "itemsize": 4 * words,
        }
    )
    points = random_points(dtype, height, n, seed)
    msg = cdr_round_trip(create_cloud(points, None, "os_sensor", 0))
    padded = with_row_padding(msg, 8) if n else msg  # 4-byte aligned row padding keeps the fast path
    for extra in ((), ("intensity",)):
        for skip in (True, False):
            want = expected_xyz(points, extra, skip)
            np.testing.assert_array_equal(read_xyz(msg, extra, skip), want)
            np.testing.assert_array_equal(read_xyz(padded, extra, skip), want)


# ----------------------------------------------------------------------------- plain arrays, containers
def test_plain_array_encoding_fields_and_header():
    pts, msg = xyzi_cloud(5)
    assert [(f.name, f.offset, f.datatype, f.count) for f in msg.fields] == [
        ("x", 0, 7, 1),
        ("y", 4, 7, 1),
        ("z", 8, 7, 1),
        ("intensity", 12, 7, 1),
    ]
    assert (msg.point_step, msg.row_step, msg.height, msg.width) == (16, 80, 1, 5)
    assert msg.is_dense and msg.is_bigendian == (sys.byteorder == "big")
    assert msg.header.frame_id == "velodyne"
    assert stamp_to_ns(msg.header.stamp) == 1_700_000_000_123_456_789
    np.testing.assert_array_equal(read_xyz(msg, ["intensity"]), pts)


def test_encoding_copies_and_flags_nonfinite():
    pts = np.zeros((4, 3), np.float32)
    msg = create_cloud(pts, ["x", "y", "z"], "f", 0)
    pts[0, 0] = 5.0  # the message must not alias the caller's array
    assert read_xyz(msg)[0, 0] == 0.0
    pts[1, 2] = np.nan
    msg = create_cloud(pts, ["x", "y", "z"], "f", 0)
    assert not msg.is_dense
    assert len(read_xyz(msg)) == 3 and len(read_xyz(msg, skip_nonfinite=False)) == 4


def test_organized_plain_array_and_float64():
    grid = np.arange(2 * 3 * 3, dtype=np.float64).reshape(2, 3, 3)
    msg = create_cloud(grid, ["x", "y", "z"], "f", 0)
    assert (msg.height, msg.width, msg.point_step, msg.fields[0].datatype) == (2, 3, 24, 8)
    view = structured_view(msg)
    assert view.shape == (2, 3)
    np.testing.assert_array_equal(view["y"], grid[..., 1])
    np.testing.assert_array_equal(read_xyz(msg), grid.reshape(-1, 3).astype(np.float32))


def test_structured_subset_and_mixed_byte_order():
    dtype = np.dtype([("x", "<f4"), ("y", ">f4"), ("z", "<f8"), ("ring", "<u2")])
    points = random_points(dtype, 1, 9, 3)
    msg = create_cloud(points, None, "f", 0)  # mixed order -> converted to native
    assert msg.is_bigendian == (sys.byteorder == "big")
    assert_struct_equal(structured_view(msg), points)
    sub = create_cloud(points, ["x", "ring"], "f", 0)
    assert [f.name for f in sub.fields] == ["x", "ring"]
    np.testing.assert_array_equal(structured_view(sub)["ring"], points["ring"])


@pytest.mark.parametrize("kind", ["ndarray", "bytes", "bytearray", "memoryview", "array", "list"])
def test_data_containers(kind):
    pts, msg = xyzi_cloud(7)
    raw = np.asarray(msg.data)
    data = {
        "ndarray": raw,
        "bytes": raw.tobytes(),
        "bytearray": bytearray(raw.tobytes()),
        "memoryview": memoryview(raw.tobytes()),
        "array": array.array("B", raw.tobytes()),  # what rclpy messages hold
        "list": raw.tolist(),
    }[kind]
    msg = dataclasses.replace(msg, data=data)
    np.testing.assert_array_equal(read_xyz(msg, ["intensity"]), pts)
    view = structured_view(msg)
    assert not view.flags.writeable
    if kind == "array":  # zero-copy over rclpy's container
        assert view.__array_interface__["data"][0] == data.buffer_info()[0]
    if kind == "ndarray":
        assert np.shares_memory(view, data)


def test_big_endian_buffer_is_not_mutated():
    dtype = np.dtype([("x", ">f4"), ("y", ">f4"), ("z", ">f4"), ("t", ">u4")])
    points = random_points(dtype, 1, 50, 1)
    msg = create_cloud(points, None, "f", 0)
    assert msg.is_bigendian
    before = bytes(msg.data)
    view = structured_view(msg)
    assert view.dtype["x"].byteorder == ">" and np.shares_memory(view, msg.data)
    np.testing.assert_array_equal(read_xyz(msg, ["t"], skip_nonfinite=False), expected_xyz(points, ("t",), False))
    assert bytes(msg.data) == before


def test_rosbags_and_duck_typed_classes_build():
    """create_cloud through a non-rosbags class (anything taking keywords) gets array.array data."""

    class Plain:
        def __init__(self, **fields):
            self.__dict__.update(fields)

    msg = create_cloud(np.ones((3, 3), np.float32), ["x", "y", "z"], "f", 5, classes=lambda name: Plain)
    assert isinstance(msg.data, array.array) and msg.data.typecode == "B"
    assert msg.header.stamp.nanosec == 5 and msg.fields[2].name == "z"
    np.testing.assert_array_equal(read_xyz(msg), np.ones((3, 3), np.float32))


def test_empty_cloud():
    msg = create_cloud(np.zeros((0, 3), np.float32), ["x", "y", "z"], "f", 0)
    assert read_xyz(msg).shape == (0, 3)
    assert structured_view(msg).shape == (0,)
    validate(cdr_round_trip(msg))


# ----------------------------------------------------------------------------- real scans
def _real_scans(shared_data):
    scans = sorted((shared_data / "kitti_object" / "training" / "velodyne").glob("*.bin"))
    scans += sorted((shared_data / "kitti_tracking" / "training" / "velodyne" / "0000").glob("*.bin"))[:3]
    assert scans, "no KITTI scans under shared data"
    return scans


def test_real_kitti_scans_round_trip(shared_data):
    for path in _real_scans(shared_data):
        pts = np.fromfile(path, dtype=np.float32).reshape(-1, 4)
        msg = cdr_round_trip(create_cloud(pts, ["x", "y", "z", "intensity"], "velodyne", 0))
        assert msg.width == len(pts) > 10_000 and msg.is_dense
        np.testing.assert_array_equal(read_xyz(msg, ["intensity"]), pts)
        view = structured_view(msg)
        np.testing.assert_array_equal(view["z"], pts[:, 2])
        assert np.abs(read_xyz(msg)).max() < 200  # metres: a LiDAR scan, not garbage bytes


def test_real_scan_in_padded_organized_layout(shared_data):
    """A real scan re-packed like an Ouster driver (32-byte points, rows, NaN no-returns)."""
    pts = np.fromfile(_real_scans(shared_data)[0], dtype=np.float32).reshape(-1, 4)
    n = (len(pts) // 64) * 64
    dtype = np.dtype(
        {
            "names": ["x", "y", "z", "intensity", "t", "reflectivity", "ring"],
            "formats": ["<f4", "<f4", "<f4", "<f4", "<u4", "<u2", "<u2"],
            "offsets": [0, 4, 8, 16, 20, 24, 26],
            "itemsize": 32,
        }
    )
    cloud = np.zeros((64, n // 64), dtype=dtype)
    for i, name in enumerate(["x", "y", "z", "intensity"]):
        cloud[name] = pts[:n, i].reshape(64, -1)
    cloud["ring"] = np.arange(64)[:, None]
    cloud["x"][::7, ::5] = np.nan
    msg = cdr_round_trip(create_cloud(cloud, None, "os_sensor", 0))
    assert not msg.is_dense and (msg.height, msg.point_step) == (64, 32)
    got = read_xyz(msg, ["ring"])
    np.testing.assert_array_equal(got, expected_xyz(cloud, ("ring",), True))
    assert len(got) == n - np.isnan(cloud["x"]).sum()


# ----------------------------------------------------------------------------- validation errors
def _broken(**changes):
    _, msg = xyzi_cloud(4)
    return dataclasses.replace(msg, **changes)


def _field(name, offset, datatype=7, count=1):
    return new_message("sensor_msgs/msg/PointField", name=name, offset=offset, datatype=datatype, count=count)


XYZI = [("x", 0), ("y", 4), ("z", 8), ("intensity", 12)]


@pytest.mark.parametrize(
    ("changes", "pattern"),
    [
        ({"data": np.zeros(63, np.uint8)}, r"len\(data\) 63 != row_step 64 \* height 1"),
        ({"height": 2}, r"len\(data\) 64 != row_step 64 \* height 2"),
        ({"row_step": 48}, r"row_step 48 < point_step 16 \* width 4"),
        ({"point_step": 12, "row_step": 64}, r"'intensity' .* ends at byte 16, past point_step 12"),
        ({"fields": [_field(n, o) for n, o in XYZI[:3]] + [_field("x", 12)]}, "duplicate field name 'x'"),
        ({"fields": [_field(n, o) for n, o in XYZI[:3]] + [_field("intensity", 12, datatype=9)]}, "unknown datatype 9"),
        ({"fields": [_field(n, o) for n, o in XYZI[:3]] + [_field("intensity", 12, datatype=0)]}, "unknown datatype 0"),
        ({"fields": [_field(n, o) for n, o in XYZI[:3]] + [_field("intensity", 12, count=0)]}, "count 0"),
        ({"fields": [_field(n, o) for n, o in XYZI[:3]] + [_field("", 12)]}, "empty or non-string name"),
        ({"fields": [_field(n, o) for n, o in XYZI[:3]] + [_field("rgb", 14)]}, "'rgb' .* past point_step 16"),
        ({"data": np.zeros(16, np.float32)}, "dtype float32, expected uint8"),
        ({"data": array.array("f", [0.0] * 16)}, r"array.array\('f'\)"),
        ({"data": "not bytes"}, "unsupported type str"),
        ({"data": [300] * 64}, "not a byte sequence"),
        ({"point_step": 0, "fields": [], "row_step": 0, "data": np.zeros(0, np.uint8)}, "point_step 0"),
    ],
)
def test_validation_errors(changes, pattern):
    msg = _broken(**changes)
    with pytest.raises(MessageError, match=pattern):
        structured_view(msg)
    with pytest.raises(MessageError, match=pattern):
        read_xyz(msg)


@pytest.mark.parametrize("missing", ["x", "y", "z"])
def test_missing_xyz(missing):
    fields = [_field(n, o) for n, o in XYZI if n != missing]
    msg = _broken(fields=fields)
    assert structured_view(msg).shape == (4,)  # a view does not need xyz
    with pytest.raises(MessageError, match=f"no field '{missing}'"):
        read_xyz(msg)


def test_read_xyz_errors():
    with pytest.raises(MessageError, match="no field 'ring'"):
        read_xyz(_broken(), ["ring"])
    fields = [_field("x", 0, count=2), _field("y", 8), _field("z", 12)]
    with pytest.raises(MessageError, match="'x' has count 2"):
        read_xyz(_broken(fields=fields))
    with pytest.raises(MessageError, match="not a PointCloud2"):
        read_xyz(object())
    with pytest.raises(MessageError, match="fields are malformed"):
        structured_view(_broken(fields=[object()]))


def test_create_cloud_errors():
    with pytest.raises(MessageError, match="do not match fields"):
        create_cloud(np.zeros((3, 4), np.float32), ["x", "y", "z"], "f", 0)
    with pytest.raises(MessageError, match="needs field names"):
        create_cloud(np.zeros((3, 3), np.float32), None, "f", 0)
    with pytest.raises(MessageError, match="duplicate field names"):
        create_cloud(np.zeros((3, 3), np.float32), ["x", "x", "z"], "f", 0)
    with pytest.raises(MessageError, match="PointField cannot represent"):
        create_cloud(np.zeros((3, 3), np.int64), ["x", "y", "z"], "f", 0)
    with pytest.raises(MessageError, match="PointField cannot represent"):
        create_cloud(np.zeros(3, dtype=[("x", "f4"), ("ok", "?")]), None, "f", 0)
    with pytest.raises(MessageError, match="itself structured"):
        create_cloud(np.zeros(3, dtype=[("x", "f4"), ("n", [("a", "f4")])]), None, "f", 0)
    with pytest.raises(MessageError, match=r"\(N,\) or \(H, W\)"):
        create_cloud(np.zeros((2, 2, 2), dtype=[("x", "f4")]), None, "f", 0)


@pytest.mark.parametrize("extra", [(), ("intensity",)])
def test_nonfinite_compaction_across_chunks(extra):
    """Large clouds are compacted chunk by chunk: an all-NaN chunk, an all-finite chunk after
    a gap (an overlapping move), a partial chunk and a partial tail."""
    from pcc_ros.msg.pointcloud2 import COMPACT_ROWS

    n = 3 * COMPACT_ROWS + 77
    pts = np.random.default_rng(5).normal(size=(n, 4)).astype(np.float32)
    pts[:COMPACT_ROWS, 0] = np.nan  # chunk 0: nothing kept
    pts[2 * COMPACT_ROWS :: 3, 1] = np.inf  # chunk 2 and tail: partial
    pts[-1, 2] = -np.inf
    msg = create_cloud(pts, ["x", "y", "z", "intensity"], "f", 0)
    got = read_xyz(msg, extra)
    want = pts[np.isfinite(pts[:, :3]).all(axis=1)][:, : 3 + len(extra)]
    assert got.flags.c_contiguous
    np.testing.assert_array_equal(got, want)


@settings(max_examples=300, deadline=None)
@given(
    st.fixed_dictionaries(
        {},
        optional={
            "height": st.integers(0, 5),
            "width": st.integers(0, 12),
            "point_step": st.integers(0, 40),
            "row_step": st.integers(0, 300),
            "is_bigendian": st.booleans(),
            "data_len": st.integers(0, 400),
            "field": st.tuples(
                st.integers(0, 3),
                st.sampled_from(["x", "y", "z", "i", ""]),
                st.integers(0, 40),
                st.integers(0, 10),
                st.integers(0, 4),
            ),
        },
    )
)
def test_malformed_clouds_raise_message_error_only(mutation):
    """Any mutation of a valid cloud either decodes or raises MessageError - nothing else."""
    _, msg = xyzi_cloud(6)
    changes = {k: v for k, v in mutation.items() if k not in ("data_len", "field")}
    if "data_len" in mutation:
        changes["data"] = np.zeros(mutation["data_len"], np.uint8)
    if "field" in mutation:
        index, name, offset, datatype, count = mutation["field"]
        fields = list(msg.fields)
        fields[index] = _field(name, offset, datatype, count)
        changes["fields"] = fields
    broken = dataclasses.replace(msg, **changes)
    for decode in (structured_view, read_xyz, lambda m: read_xyz(m, ["i"], skip_nonfinite=False)):
        try:
            decode(broken)
        except MessageError:
            pass


def test_structured_copy_zeroes_padding_and_unselected_fields():
    """create_cloud's byte copy: padding bytes and fields left out are zero on the wire."""
    from pcc_ros.msg.pointcloud2 import zero_padded_copy

    dtype = np.dtype({"names": ["x", "ring"], "formats": ["<f4", "<u2"], "offsets": [0, 8], "itemsize": 16})
    raw = np.frombuffer(np.arange(64, dtype=np.uint8).tobytes(), dtype=dtype)  # garbage in the padding
    out = zero_padded_copy(raw, dtype)
    assert out.flags.c_contiguous and not np.shares_memory(out, raw)
    assert np.array_equal(out["x"], raw["x"]) and np.array_equal(out["ring"], raw["ring"])
    b = out.view(np.uint8).reshape(4, 16)
    assert not b[:, 4:8].any() and not b[:, 10:16].any()
    organized = np.zeros((3, 4), dtype=dtype)
    organized["x"] = 2.5
    view = organized[:, ::2]  # not contiguous
    copy = zero_padded_copy(view, dtype)
    assert copy.shape == (3, 2) and np.array_equal(copy["x"], view["x"])
    assert not copy.view(np.uint8).reshape(6, 16)[:, 4:8].any()
