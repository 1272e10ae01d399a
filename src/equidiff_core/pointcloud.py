"""PointCloud2 wire formats: coloured camera clouds and the occupied-voxel cloud (docs/architecture.md).

Camera clouds: fields ``x y z`` float32 + ``rgb`` float32-packed 0x00RRGGBB (PCL/realsense-ros
layout), ``point_step`` 16. Voxel clouds: one point per occupied voxel, ``x y z`` voxel
centre, ``rgb``, and ``i j k`` uint16 indices (``point_step`` 24), so the exact uint8
(4, R, R, R) grid comes back from any bag without extra metadata.

Decoders accept rclpy and rosbags messages alike and raise ``CloudError`` with a precise
reason on anything malformed: missing fields, wrong types or point_step, truncated data,
NaN/inf points, big-endian data.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .rosmsg import MsgFactory, stamp_to_ns, uint8_buffer

# sensor_msgs/PointField datatypes
INT8, UINT8, INT16, UINT16, INT32, UINT32, FLOAT32, FLOAT64 = range(1, 9)
_NUMPY_OF = {
    INT8: "i1",
    UINT8: "u1",
    INT16: "<i2",
    UINT16: "<u2",
    INT32: "<i4",
    UINT32: "<u4",
    FLOAT32: "<f4",
    FLOAT64: "<f8",
}

CLOUD_FIELDS = (("x", 0, FLOAT32), ("y", 4, FLOAT32), ("z", 8, FLOAT32), ("rgb", 12, FLOAT32))
CLOUD_POINT_STEP = 16
VOXEL_FIELDS = CLOUD_FIELDS + (("i", 16, UINT16), ("j", 18, UINT16), ("k", 20, UINT16))
VOXEL_POINT_STEP = 24


class CloudError(ValueError):
    """A PointCloud2 that cannot be used (and must be dropped, not guessed at)."""


@dataclass(frozen=True)
class Cloud:
    points: np.ndarray  # (N, 3) float32
    colors: np.ndarray  # (N, 3) uint8 RGB
    stamp_ns: int
    frame_id: str


def pack_rgb(colors: np.ndarray) -> np.ndarray:
    """(N, 3) uint8 -> (N,) float32 whose bits are 0x00RRGGBB."""
    c = np.asarray(colors, dtype=np.uint32)
    return ((c[:, 0] << 16) | (c[:, 1] << 8) | c[:, 2]).astype(np.uint32).view(np.float32)


def unpack_rgb(packed: np.ndarray) -> np.ndarray:
    """(N,) float32 (or uint32) packed 0x00RRGGBB -> (N, 3) uint8."""
    bits = np.ascontiguousarray(packed).view(np.uint32)
    return np.stack([(bits >> 16) & 0xFF, (bits >> 8) & 0xFF, bits & 0xFF], axis=-1).astype(np.uint8)


def _fields(factory: MsgFactory, spec) -> list:
    return [factory.make("sensor_msgs/msg/PointField", name=n, offset=o, datatype=d, count=1) for n, o, d in spec]


def _make_cloud_msg(factory: MsgFactory, record: np.ndarray, spec, step: int, stamp_ns: int, frame_id: str):
    return factory.make(
        "sensor_msgs/msg/PointCloud2",
        header=factory.header(stamp_ns, frame_id),
        height=1,
        width=len(record),
        fields=_fields(factory, spec),
        is_bigendian=False,
        point_step=step,
        row_step=step * len(record),
        data=factory.uint8_array(record.view(np.uint8).reshape(-1)),
        is_dense=True,
    )


def _dtype(spec, step: int) -> np.dtype:
    return np.dtype(
        {
            "names": [n for n, _, _ in spec],
            "formats": [_NUMPY_OF[d] for _, _, d in spec],
            "offsets": [o for _, o, _ in spec],
            "itemsize": step,
        }
    )


def cloud_to_msg(points: np.ndarray, colors: np.ndarray, stamp_ns: int, frame_id: str, factory: MsgFactory):
    """Coloured points (N, 3) + (N, 3) uint8 -> PointCloud2 (x y z rgb, point_step 16)."""
    points = np.asarray(points, dtype=np.float32)
    if points.ndim != 2 or points.shape[1] != 3 or colors.shape != points.shape:
        raise CloudError(f"points {points.shape} and colors {colors.shape} must both be (N, 3)")
    record = np.empty(len(points), dtype=_dtype(CLOUD_FIELDS, CLOUD_POINT_STEP))
    record["x"], record["y"], record["z"] = points[:, 0], points[:, 1], points[:, 2]
    record["rgb"] = pack_rgb(colors)
    return _make_cloud_msg(factory, record, CLOUD_FIELDS, CLOUD_POINT_STEP, stamp_ns, frame_id)


def _structured(msg, required: tuple[str, ...]) -> tuple[np.ndarray, dict]:
    if msg.is_bigendian:
        raise CloudError("big-endian point clouds are not supported")
    fields = {f.name: f for f in msg.fields}
    missing = [name for name in required if name not in fields]
    if missing:
        raise CloudError(f"cloud lacks field(s) {missing} (has {sorted(fields)})")
    n = int(msg.width) * int(msg.height)
    step = int(msg.point_step)
    for name in required:
        f = fields[name]
        if f.datatype not in _NUMPY_OF:
            raise CloudError(f"field {name!r} has unknown datatype {f.datatype}")
        if f.offset + np.dtype(_NUMPY_OF[f.datatype]).itemsize > step:
            raise CloudError(f"field {name!r} (offset {f.offset}) does not fit point_step {step}")
    buf = uint8_buffer(msg.data)
    row_step = int(msg.row_step) if msg.row_step else step * int(msg.width)
    if n and row_step != step * int(msg.width):
        raise CloudError(f"row_step {row_step} != point_step {step} x width {msg.width} (padded rows unsupported)")
    if buf.size != n * step:
        raise CloudError(f"cloud data has {buf.size} bytes, expected {n} points x {step} = {n * step}")
    spec = [(name, fields[name].offset, fields[name].datatype) for name in required]
    return np.frombuffer(buf, dtype=_dtype(spec, step), count=n), fields


def msg_to_cloud(msg, drop_invalid: bool = False) -> Cloud:
    """PointCloud2 with x y z (+ rgb) -> Cloud; NaN/inf points raise (or are dropped if asked)."""
    record, fields = _structured(msg, ("x", "y", "z"))
    if len(record) == 0:
        raise CloudError("cloud has zero points")
    for name in ("x", "y", "z"):
        if fields[name].datatype not in (FLOAT32, FLOAT64):
            raise CloudError(f"field {name!r} must be float32/float64")
    points = np.stack([record["x"], record["y"], record["z"]], axis=1).astype(np.float32, copy=False)
    if "rgb" in fields:
        rgb_record, _ = _structured(msg, ("rgb",))
        colors = unpack_rgb(rgb_record["rgb"])
    else:
        colors = np.full((len(points), 3), 255, dtype=np.uint8)
    finite = np.isfinite(points).all(axis=1)
    if not finite.all():
        if not drop_invalid:
            raise CloudError(f"cloud has {int((~finite).sum())} NaN/inf points of {len(points)}")
        points, colors = points[finite], colors[finite]
        if len(points) == 0:
            raise CloudError("cloud has no finite points")
    return Cloud(points, colors, stamp_to_ns(msg.header.stamp), str(msg.header.frame_id))


def grid_to_voxel_msg(
    grid: np.ndarray, lower: np.ndarray, voxel_size: float, stamp_ns: int, frame_id: str, factory: MsgFactory
):
    """uint8 grid (4, R, R, R) -> occupied-voxel PointCloud2 (architecture.md note 2)."""
    if grid.ndim != 4 or grid.shape[0] != 4 or grid.dtype != np.uint8:
        raise CloudError(f"grid must be uint8 (4, R, R, R), got {grid.dtype} {grid.shape}")
    idx = np.argwhere(grid[0] > 0)
    record = np.empty(len(idx), dtype=_dtype(VOXEL_FIELDS, VOXEL_POINT_STEP))
    centers = np.asarray(lower, dtype=np.float64) + (idx + 0.5) * voxel_size
    record["x"], record["y"], record["z"] = centers.T.astype(np.float32)
    colors = grid[1:4, idx[:, 0], idx[:, 1], idx[:, 2]].T
    record["rgb"] = pack_rgb(colors)
    record["i"], record["j"], record["k"] = idx.T.astype(np.uint16)
    return _make_cloud_msg(factory, record, VOXEL_FIELDS, VOXEL_POINT_STEP, stamp_ns, frame_id)


def voxel_msg_to_grid(msg, resolution: int) -> np.ndarray:
    """Occupied-voxel PointCloud2 -> the exact uint8 grid (4, R, R, R); raises CloudError if malformed."""
    record, _ = _structured(msg, ("rgb", "i", "j", "k"))
    grid = np.zeros((4, resolution, resolution, resolution), dtype=np.uint8)
    if len(record) == 0:
        return grid
    idx = np.stack([record["i"], record["j"], record["k"]], axis=1).astype(np.int64)
    if idx.max() >= resolution:
        raise CloudError(f"voxel index {int(idx.max())} out of range for resolution {resolution}")
    colors = unpack_rgb(record["rgb"])
    grid[0, idx[:, 0], idx[:, 1], idx[:, 2]] = 255
    for c in range(3):
        grid[1 + c, idx[:, 0], idx[:, 1], idx[:, 2]] = colors[:, c]
    return grid
