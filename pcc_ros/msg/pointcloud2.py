"""``sensor_msgs/PointCloud2`` <-> numpy, zero-copy where the buffer allows, strict everywhere.

Works on any object with the message's attributes (``header``, ``height``, ``width``,
``fields``, ``is_bigendian``, ``point_step``, ``row_step``, ``data``, ``is_dense``):
rosbags dataclasses (``data`` a ``uint8`` numpy array), rclpy messages (``data`` an
``array.array('B')``), or anything whose ``data`` is ``bytes`` / ``bytearray`` /
``memoryview``.

* :func:`structured_view` - a read-only structured numpy view over ``data`` (no copy):
  shape ``(width,)`` for unorganized clouds, ``(height, width)`` for organized ones (rows
  may be padded: ``row_step > point_step * width``). Big-endian clouds get a big-endian
  dtype, so values read correctly and the message buffer is never byte-swapped in place
  (sensor_msgs_py's ``read_points`` swaps the caller's buffer).
* :func:`read_xyz` - contiguous native ``float32 (N, 3 + k)`` with x, y, z first, optionally
  dropping non-finite points. For the common layout (float32 fields, native byte order,
  4-byte aligned offsets) it views the buffer as a ``float32 (N, point_step / 4)`` matrix and
  gathers the wanted columns with one ``take``: a single strided copy, no structured dtype,
  no ``structured_to_unstructured``.
* :func:`create_cloud` - a message of any class flavour from a plain ``(N, C)`` / ``(H, W, C)``
  array with column names, or a structured array (padding, ``count > 1``, big-endian kept).

Malformed messages raise :class:`~pcc_ros.errors.MessageError` naming the problem, so a node
can log and skip the message.
"""

from __future__ import annotations

import array
import sys
from collections.abc import Sequence
from functools import cache, lru_cache
from itertools import pairwise

import numpy as np

from pcc_ros.errors import MessageError
from pcc_ros.msg.stamps import make_header
from pcc_ros.msg.typestore import ClassResolver, byte_array, is_rosbags_class, new_message, resolve

# sensor_msgs/PointField datatype constants -> (name, numpy type code).
DATATYPES: dict[int, tuple[str, str]] = {
    1: ("INT8", "i1"),
    2: ("UINT8", "u1"),
    3: ("INT16", "i2"),
    4: ("UINT16", "u2"),
    5: ("INT32", "i4"),
    6: ("UINT32", "u4"),
    7: ("FLOAT32", "f4"),
    8: ("FLOAT64", "f8"),
}
INT8, UINT8, INT16, UINT16, INT32, UINT32, FLOAT32, FLOAT64 = range(1, 9)
_CODE_TO_DATATYPE = {code: dt for dt, (_, code) in DATATYPES.items()}
_NATIVE_BIG = sys.byteorder == "big"

FieldKey = tuple[str, int, int, int]  # name, offset, datatype, count


def _field_keys(msg) -> tuple[FieldKey, ...]:
    try:
        keys = tuple((f.name, int(f.offset), int(f.datatype), int(f.count)) for f in msg.fields)
        bad = [k[0] for k in keys if not isinstance(k[0], str)]
        if bad:
            raise TypeError(f"field name {bad[0]!r} is not a string")
        return keys
    except (AttributeError, TypeError, ValueError) as exc:
        raise MessageError(f"PointCloud2 fields are malformed ({exc})") from None


@lru_cache(maxsize=512)
def _dtype(fields: tuple[FieldKey, ...], point_step: int, bigendian: bool) -> np.dtype:
    """The structured dtype of one point, after checking every field (cached per layout)."""
    order = ">" if bigendian else "<"
    names, formats, offsets, ends = [], [], [], []
    for name, offset, datatype, count in fields:
        if not isinstance(name, str) or not name:
            raise MessageError(f"PointCloud2 has a field with an empty or non-string name: {name!r}")
        if name in names:
            raise MessageError(f"PointCloud2 has duplicate field name {name!r}")
        if datatype not in DATATYPES:
            raise MessageError(f"PointCloud2 field {name!r} has unknown datatype {datatype} (valid: 1-8)")
        if count < 1:
            raise MessageError(f"PointCloud2 field {name!r} has count {count} (must be >= 1)")
        type_name, code = DATATYPES[datatype]
        base = np.dtype(order + code)
        end = offset + base.itemsize * count
        if offset < 0 or end > point_step:
            raise MessageError(
                f"PointCloud2 field {name!r} ({type_name} x{count} at offset {offset}) ends at byte {end}, "
                f"past point_step {point_step}"
            )
        names.append(name)
        formats.append(base if count == 1 else (base, (count,)))
        offsets.append(offset)
        ends.append(end)
    by_offset = sorted(range(len(offsets)), key=offsets.__getitem__)
    for a, b in pairwise(by_offset):  # per layout (cached): fields must not share bytes
        if ends[a] > offsets[b]:
            raise MessageError(f"PointCloud2 fields {names[a]!r} and {names[b]!r} overlap (bytes "
                               f"{offsets[a]}-{ends[a] - 1} and {offsets[b]}-{ends[b] - 1})")
    return np.dtype({"names": names, "formats": formats, "offsets": offsets, "itemsize": max(point_step, 1)})


def _buffer(data) -> np.ndarray:
    """``data`` as a flat ``uint8`` numpy array without copying when the type allows it."""
    if isinstance(data, np.ndarray):
        if data.dtype != np.uint8:
            if data.dtype.itemsize != 1 or data.dtype.kind not in "iub":
                raise MessageError(f"PointCloud2 data has dtype {data.dtype}, expected uint8")
            data = data.view(np.uint8)
        if data.ndim != 1:
            data = data.reshape(-1)
        return data if data.flags.c_contiguous else np.ascontiguousarray(data)
    if isinstance(data, array.array) and data.typecode not in "Bb":
        raise MessageError(f"PointCloud2 data is array.array({data.typecode!r}), expected 'B'")
    if isinstance(data, (bytes, bytearray, memoryview, array.array)):
        try:
            return np.frombuffer(data, dtype=np.uint8)
        except (ValueError, TypeError) as exc:  # non-contiguous memoryview
            raise MessageError(f"PointCloud2 data buffer is unusable ({exc})") from None
    if isinstance(data, (list, tuple)):
        try:
            values = np.asarray(data)
        except (ValueError, TypeError) as exc:
            raise MessageError(f"PointCloud2 data is not a byte sequence ({exc})") from None
        # checked here, not by the uint8 conversion: numpy 1.x wraps 300 to 44 (numpy 2 raises)
        if values.size and (values.dtype.kind not in "iub" or values.min() < 0 or values.max() > 255):
            raise MessageError(f"PointCloud2 data is not a byte sequence (values {values.dtype} outside 0..255)")
        return values.astype(np.uint8).reshape(-1)
    raise MessageError(f"PointCloud2 data has unsupported type {type(data).__name__}")


class _Cloud:
    """The validated geometry of one message: dtype, shape, strides and byte buffer."""

    __slots__ = ("bigendian", "buf", "dtype", "fields", "height", "point_step", "row_step", "width")

    def __init__(self, msg) -> None:
        try:
            self.height = int(msg.height)
            self.width = int(msg.width)
            self.point_step = int(msg.point_step)
            self.row_step = int(msg.row_step)
            self.bigendian = bool(msg.is_bigendian)
            data = msg.data
        except (AttributeError, TypeError, ValueError) as exc:
            raise MessageError(f"object is not a PointCloud2 ({exc})") from None
        if min(self.height, self.width, self.point_step, self.row_step) < 0:
            raise MessageError("PointCloud2 height, width, point_step and row_step must be non-negative")
        self.fields = _field_keys(msg)
        self.dtype = _dtype(self.fields, self.point_step, self.bigendian)
        if self.height * self.width and self.point_step == 0:
            raise MessageError(f"PointCloud2 has {self.height}x{self.width} points but point_step 0")
        if self.row_step < self.point_step * self.width:
            raise MessageError(
                f"PointCloud2 row_step {self.row_step} < point_step {self.point_step} * width {self.width}"
            )
        self.buf = _buffer(data)
        if self.buf.size != self.row_step * self.height:
            raise MessageError(
                f"PointCloud2 len(data) {self.buf.size} != row_step {self.row_step} * height {self.height}"
            )

    def field(self, name: str) -> FieldKey:
        for key in self.fields:
            if key[0] == name:
                return key
        raise MessageError(f"PointCloud2 has no field {name!r} (fields: {[k[0] for k in self.fields]})")

    def view(self) -> np.ndarray:
        if self.height == 1:
            shape, strides = (self.width,), (self.point_step,)
        else:
            shape, strides = (self.height, self.width), (self.row_step, self.point_step)
        if self.height * self.width == 0:
            return np.empty(shape, dtype=self.dtype)
        out = np.ndarray(shape, dtype=self.dtype, buffer=self.buf, strides=strides)
        out.flags.writeable = False
        return out


#: The per-point beam index field of spinning-LiDAR drivers (velodyne_pointcloud, ouster-ros,
#: HesaiLidar_ROS_2.0; nuScenes' scans): the filter's beam model reads it when present.
RING_FIELD = "ring"


def point_field_names(msg) -> tuple[str, ...]:
    """The names of the message's point fields (its layout checked)."""
    return tuple(key[0] for key in _Cloud(msg).fields)


def validate(msg) -> None:
    """Raise :class:`MessageError` if ``msg`` is not a well-formed PointCloud2."""
    _Cloud(msg)


def structured_view(msg) -> np.ndarray:
    """Read-only structured view over ``msg.data``: ``(width,)`` if ``height == 1`` else ``(height, width)``.

    Zero-copy for numpy / bytes / bytearray / memoryview / ``array.array('B')`` data. The
    dtype carries the message's byte order, field offsets, ``count > 1`` as sub-arrays and
    ``point_step`` as its itemsize.
    """
    return _Cloud(msg).view()


def read_xyz(msg, extra_fields: Sequence[str] = (), skip_nonfinite: bool = True) -> np.ndarray:
    """Contiguous native ``float32 (N, 3 + k)``: x, y, z, then ``extra_fields`` (a field with
    ``count = c`` contributes ``c`` columns). Organized clouds are flattened row-major.

    With ``skip_nonfinite`` points whose x, y or z is NaN / inf are dropped (extra columns
    may still hold non-finite values); without it ``N == height * width``.
    """
    cloud = _Cloud(msg)
    keys = [cloud.field(name) for name in ("x", "y", "z", *extra_fields)]
    for name, _, datatype, count in keys[:3]:
        if count != 1:
            raise MessageError(f"PointCloud2 field {name!r} has count {count}; x, y, z must have count 1")
        if datatype not in (FLOAT32, FLOAT64):  # an integer x in mm would be read as metres
            raise MessageError(f"PointCloud2 field {name!r} is {DATATYPES[datatype][0]}; x, y, z must be "
                               "FLOAT32 or FLOAT64")
    n = cloud.height * cloud.width
    k = sum(key[3] for key in keys)
    if n == 0:
        return np.empty((0, k), dtype=np.float32)
    fast = (
        cloud.bigendian == _NATIVE_BIG
        and cloud.point_step % 4 == 0
        and cloud.row_step % 4 == 0
        and all(datatype == FLOAT32 and offset % 4 == 0 for _, offset, datatype, _ in keys)
    )
    if fast:
        out = _gather_float32(cloud, keys)
    else:
        out = np.empty((cloud.height, cloud.width, k), dtype=np.float32)
        view = cloud.view().reshape(cloud.height, cloud.width)
        column = 0
        for name, _, _, count in keys:  # loop over fields, each a vectorised cast
            out[:, :, column : column + count] = view[name].reshape(cloud.height, cloud.width, count)
            column += count
        out = out.reshape(n, k)
    if skip_nonfinite:
        out = _drop_nonfinite(out)
    return out


def _gather_float32(cloud: _Cloud, keys: list[FieldKey]) -> np.ndarray:
    """One ``take`` of the wanted float32 columns from the buffer seen as a float32 matrix."""
    columns = [offset // 4 + j for _, offset, _, count in keys for j in range(count)]
    words = cloud.point_step // 4
    flat = cloud.buf.view(np.float32)  # len(data) == row_step * height, a multiple of 4
    n = cloud.height * cloud.width
    if cloud.row_step == cloud.point_step * cloud.width:
        matrix = flat.reshape(n, words)
        return matrix.take(columns, axis=1)
    rows = flat.reshape(cloud.height, cloud.row_step // 4)[:, : cloud.width * words]
    return rows.reshape(cloud.height, cloud.width, words).take(columns, axis=2).reshape(n, len(columns))


_QUARTER = np.full(3, 0.25, dtype=np.float32)
COMPACT_ROWS = 32768  # rows per in-place compaction step: the chunk stays in L2


def _drop_nonfinite(points: np.ndarray) -> np.ndarray:
    """Rows of the freshly gathered ``points`` whose first three columns are finite.

    The row test for ``(N, 3)`` is one BLAS mat-vec: ``0.25 x + 0.25 y + 0.25 z`` is
    non-finite iff a coordinate is NaN / inf (0.25 keeps sums of finite float32 values from
    overflowing; no weight is zero, so no BLAS zero-skipping can hide a NaN).
    ``isfinite(...).all(axis=1)`` over the 3-wide axis is ~20x slower. Kept rows are then
    compacted in place, chunk by chunk (a loop over ~4 chunks, not over points): a second
    full-size array would cost a fresh allocation and its page faults on every message.
    """
    if points.shape[1] == 3:
        with np.errstate(invalid="ignore"):  # inf - inf inside the sum is expected, not an error
            keep = np.isfinite(points @ _QUARTER)
    else:
        finite = np.isfinite(points[:, :3])
        keep = finite[:, 0] & finite[:, 1] & finite[:, 2]
    if keep.all():
        return points
    kept = 0
    for start in range(0, len(points), COMPACT_ROWS):
        stop = start + COMPACT_ROWS
        chunk_keep = keep[start:stop]
        count = int(np.count_nonzero(chunk_keep))
        if count == len(chunk_keep):
            if kept != start:
                points[kept : kept + count] = points[start:stop]  # overlapping move, numpy buffers it
        elif count:
            points[kept : kept + count] = np.compress(chunk_keep, points[start:stop], axis=0)
        kept += count
    return points[:kept]


def _datatype_of(dtype: np.dtype, name: str) -> int:
    code = f"{dtype.kind}{dtype.itemsize}"
    if code not in _CODE_TO_DATATYPE:
        raise MessageError(f"field {name!r} has dtype {dtype}, which PointField cannot represent")
    return _CODE_TO_DATATYPE[code]


def _is_big(dtype: np.dtype) -> bool:
    return dtype.byteorder == ">" or (dtype.byteorder == "=" and _NATIVE_BIG)


def create_cloud(
    points: np.ndarray,
    fields: Sequence[str] | None,
    frame_id: str,
    stamp_ns: int,
    classes: ClassResolver | None = None,
):
    """Build a ``sensor_msgs/msg/PointCloud2`` (class from ``classes``; ``None`` = rosbags).

    ``points`` is either a plain ``(N, C)`` or organized ``(H, W, C)`` array whose ``C``
    columns are named by ``fields`` (all columns share the array's dtype, which must be one
    of the eight PointField types; float32 for the usual clouds), or a structured ``(N,)``
    / ``(H, W)`` array (``fields=None``, or a subset of its names to keep) whose offsets,
    padding, sub-arrays (``count > 1``) and byte order are kept. The data is always copied,
    so the message never aliases the caller's array. ``is_dense`` is true iff x, y, z (or,
    without them, every float field) are finite.
    """
    points = np.asarray(points)
    if points.dtype.names is None:
        if fields is None:
            raise MessageError("create_cloud: a plain array needs field names")
        names = list(fields)
        if points.ndim not in (2, 3) or points.shape[-1] != len(names):
            raise MessageError(f"create_cloud: points of shape {points.shape} do not match fields {names}")
        if len(set(names)) != len(names):
            raise MessageError(f"create_cloud: duplicate field names {names}")
        base = points.dtype
        _datatype_of(base, names[0])
        structured = np.dtype(
            {"names": names, "formats": [base] * len(names), "offsets": [i * base.itemsize for i in range(len(names))]}
        )
        contiguous = np.array(points, dtype=base, order="C", copy=True)
        grid = contiguous.reshape(*points.shape[:-1], len(names)).view(structured)[..., 0]
    else:
        grid = points if fields is None else points[list(fields)]
        if grid.ndim not in (1, 2):
            raise MessageError(f"create_cloud: structured points must be (N,) or (H, W), got {grid.shape}")
        grid = zero_padded_copy(grid, grid.dtype)
    grid, bigendian = _uniform_byte_order(grid)
    height, width = (1, grid.shape[0]) if grid.ndim == 1 else grid.shape
    point_step = grid.dtype.itemsize
    field_msgs = []
    for name in grid.dtype.names:
        fdtype, offset = grid.dtype.fields[name][:2]
        if fdtype.names is not None:
            raise MessageError(f"create_cloud: field {name!r} is itself structured")
        count = int(np.prod(fdtype.shape)) if fdtype.shape else 1
        field_msgs.append(
            new_message(
                "sensor_msgs/msg/PointField",
                classes,
                name=str(name),
                offset=int(offset),
                datatype=_datatype_of(fdtype.base, name),
                count=count,
            )
        )
    data = grid.reshape(-1).view(np.uint8) if grid.size else np.zeros(0, dtype=np.uint8)
    cls = resolve(classes)("sensor_msgs/msg/PointCloud2")
    rosbags = is_rosbags_class(cls)
    msg = new_message(
        "sensor_msgs/msg/PointCloud2",
        classes,
        header=make_header(frame_id, stamp_ns, classes),
        height=int(height),
        width=int(width),
        fields=field_msgs,
        is_bigendian=bigendian,
        point_step=int(point_step),
        row_step=int(point_step * width),
        data=data if rosbags else byte_array(cls, data[:0]),
        is_dense=_is_dense(grid),
    )
    if not rosbags:
        # rclpy's constructor copies the data it is given into a new array.array, and the setter
        # it calls copies it again: the data goes in through the setter alone (one copy fewer of
        # a multi-megabyte cloud, as sensor_msgs_py's create_cloud does).
        msg.data = byte_array(cls, data)
    return msg


def _uniform_byte_order(grid: np.ndarray) -> tuple[np.ndarray, bool]:
    """Keep one byte order for the whole cloud (PointCloud2 has one flag); mixed -> native."""
    bases = [grid.dtype.fields[n][0].base for n in grid.dtype.names]
    orders = {_is_big(base) for base in bases if base.itemsize > 1}
    if len(orders) <= 1:
        return grid, (orders.pop() if orders else _NATIVE_BIG)
    native = np.dtype(
        {
            "names": list(grid.dtype.names),
            "formats": [grid.dtype.fields[n][0].newbyteorder("=") for n in grid.dtype.names],
            "offsets": [grid.dtype.fields[n][1] for n in grid.dtype.names],
            "itemsize": grid.dtype.itemsize,
        }
    )
    return zero_padded_copy(grid, native), _NATIVE_BIG


def zero_padded_copy(grid: np.ndarray, dtype: np.dtype) -> np.ndarray:
    """A C-contiguous copy whose padding bytes are zero (numpy copies structured arrays field
    by field, so ``np.array(copy=True)`` would put uninitialised memory on the wire).

    Same layout: one byte copy, then the padding byte ranges zeroed (several times faster than
    numpy's field-by-field structured assignment). Another layout (byte order): assignment.
    """
    if grid.dtype != dtype:
        out = np.zeros(grid.shape, dtype=dtype)
        out[...] = grid
        return out
    raw = np.ascontiguousarray(grid).reshape(-1).view(np.uint8).reshape(-1, dtype.itemsize).copy()
    for start, stop in _padding_runs(dtype):
        raw[:, start:stop] = 0
    return raw.reshape(-1).view(dtype).reshape(grid.shape)


@cache
def _padding_runs(dtype: np.dtype) -> tuple[tuple[int, int], ...]:
    """Byte ranges of a structured dtype's items that no field covers."""
    used = np.zeros(dtype.itemsize, dtype=bool)
    for name in dtype.names:
        fdtype, offset = dtype.fields[name][:2]
        used[offset : offset + fdtype.itemsize] = True
    pad = np.flatnonzero(~used)
    if not len(pad):
        return ()
    breaks = np.flatnonzero(np.diff(pad) > 1)
    starts = np.r_[pad[0], pad[breaks + 1]]
    stops = np.r_[pad[breaks], pad[-1]] + 1
    return tuple(zip(starts.tolist(), stops.tolist()))


def _is_dense(grid: np.ndarray) -> bool:
    names = [n for n in ("x", "y", "z") if n in grid.dtype.names]
    if not names:
        names = [n for n in grid.dtype.names if grid.dtype.fields[n][0].base.kind == "f"]
    return bool(all(np.isfinite(grid[n]).all() for n in names))
