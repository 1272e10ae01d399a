"""PointCloud2 wire formats: coloured camera clouds and the occupied-voxel cloud (docs/architecture.md).

Camera clouds: fields ``x y z`` float32 + ``rgb`` float32-packed 0x00RRGGBB (PCL/realsense-ros
layout), ``point_step`` 16. Voxel clouds: one point per occupied voxel, ``x y z`` voxel
centre, ``rgb``, and ``i j k`` uint16 indices (``point_step`` 24), so the exact uint8
(4, R, R, R) grid comes back from any bag without extra metadata.

Decoders accept rclpy and rosbags messages alike and check them against what the receiver
expects (the frame; for voxels the grid's resolution, origin and voxel size: ``VoxelGridSpec``).
Anything else raises ``CloudError`` with a precise reason and a ``CloudReason`` code: missing,
repeated or mistyped fields, a wrong point_step, truncated data, NaN/inf points, big-endian
data, a foreign frame, voxels off the expected grid.
"""

from __future__ import annotations

import enum
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
# the datatypes a camera cloud's fields may have: coordinates float, colour packed in 4 bytes
_CLOUD_DATATYPES = {"x": (FLOAT32, FLOAT64), "y": (FLOAT32, FLOAT64), "z": (FLOAT32, FLOAT64), "rgb": (FLOAT32, UINT32)}


class CloudReason(enum.StrEnum):
    """Why a PointCloud2 was refused: nodes count each on /diagnostics (``dropped_<reason>``)."""

    LAYOUT = "layout"  # fields, datatypes, point_step, row_step, data size, endianness
    EMPTY = "empty"  # a camera cloud with no (finite) points
    NAN = "nan"  # NaN / inf points
    FRAME = "frame"  # header.frame_id is not the one the receiver expects
    GRID = "grid"  # voxels off the expected grid: index out of range, centre off the origin / voxel size, repeats
    FUTURE = "future"  # stamped further ahead of the receiver's clock than allowed


class CloudError(ValueError):
    """A PointCloud2 that cannot be used (and must be dropped, not guessed at); ``reason`` a ``CloudReason``."""

    def __init__(self, message: str, reason: CloudReason = CloudReason.LAYOUT):
        super().__init__(message)
        self.reason = CloudReason(reason)


@dataclass(frozen=True)
class VoxelGridSpec:
    """The voxel grid a receiver expects: ``resolution`` voxels per edge; with ``lower`` (the
    grid's minimum corner, m) and ``voxel_size`` every voxel centre is checked against them;
    with ``frame_id`` the header's frame."""

    resolution: int
    lower: tuple[float, float, float] | None = None
    voxel_size: float | None = None
    frame_id: str | None = None

    @classmethod
    def of(cls, workspace, frame_id: str | None = None) -> VoxelGridSpec:
        """The spec of a ``config.Workspace`` in ``frame_id``."""
        return cls(workspace.resolution, tuple(map(float, workspace.lower)), float(workspace.voxel_size), frame_id)


def check_frame(msg, frame_id: str | None) -> None:
    """CloudError (FRAME) unless ``frame_id`` is None or the header's frame."""
    if frame_id is not None and str(msg.header.frame_id) != frame_id:
        raise CloudError(f"frame_id {str(msg.header.frame_id)!r} is not {frame_id!r}", CloudReason.FRAME)


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


def _structured(msg, required: tuple[str, ...], datatypes: dict | None = None) -> tuple[np.ndarray, dict]:
    """The ``required`` fields of a PointCloud2 as a numpy record array (no copy), after checking
    its layout; ``datatypes`` maps a field to the datatypes it may have (default: any known)."""
    if msg.is_bigendian:
        raise CloudError("big-endian point clouds are not supported")
    names = [f.name for f in msg.fields]
    if len(set(names)) != len(names):
        raise CloudError(f"cloud repeats field names: {names}")
    fields = {f.name: f for f in msg.fields}
    missing = [name for name in required if name not in fields]
    if missing:
        raise CloudError(f"cloud lacks field(s) {missing} (has {sorted(fields)})")
    width, height, step = int(msg.width), int(msg.height), int(msg.point_step)
    if width < 0 or height < 0 or step <= 0:
        raise CloudError(f"cloud has width {width}, height {height}, point_step {step}")
    n = width * height
    for name in required:
        f = fields[name]
        allowed = (datatypes or {}).get(name, tuple(_NUMPY_OF))
        if f.datatype not in allowed:
            raise CloudError(f"field {name!r} has datatype {f.datatype}, expected one of {list(allowed)}")
        if int(f.count) != 1:
            raise CloudError(f"field {name!r} has count {f.count}, expected 1")
        if f.offset < 0 or f.offset + np.dtype(_NUMPY_OF[f.datatype]).itemsize > step:
            raise CloudError(f"field {name!r} (offset {f.offset}) does not fit point_step {step}")
    buf = uint8_buffer(msg.data)
    row_step = int(msg.row_step) if msg.row_step else step * width
    if n and row_step != step * width:
        raise CloudError(f"row_step {row_step} != point_step {step} x width {width} (padded rows unsupported)")
    if buf.size != n * step:
        raise CloudError(f"cloud data has {buf.size} bytes, expected {n} points x {step} = {n * step}")
    spec = [(name, fields[name].offset, fields[name].datatype) for name in required]
    try:
        dtype = _dtype(spec, step)
    except ValueError as err:  # overlapping fields
        raise CloudError(f"cloud fields {spec} do not fit together in point_step {step}: {err}") from err
    return np.frombuffer(buf, dtype=dtype, count=n), fields


def msg_to_cloud(msg, drop_invalid: bool = False, frame_id: str | None = None) -> Cloud:
    """PointCloud2 with x y z (float32/64) (+ rgb: float32 or uint32 packed 0x00RRGGBB) -> Cloud;
    NaN/inf points raise (or are dropped if asked); with ``frame_id``, a cloud in another frame raises."""
    check_frame(msg, frame_id)
    has_rgb = any(f.name == "rgb" for f in msg.fields)
    record, _ = _structured(msg, ("x", "y", "z", "rgb") if has_rgb else ("x", "y", "z"), _CLOUD_DATATYPES)
    if len(record) == 0:
        raise CloudError("cloud has zero points", CloudReason.EMPTY)
    points = np.stack([record["x"], record["y"], record["z"]], axis=1).astype(np.float32, copy=False)
    if has_rgb:
        colors = unpack_rgb(record["rgb"])
    else:
        colors = np.full((len(points), 3), 255, dtype=np.uint8)
    with np.errstate(over="ignore"):  # float64 beyond float32's range becomes inf: refused below
        finite = np.isfinite(points).all(axis=1)
    if not finite.all():
        if not drop_invalid:
            raise CloudError(f"cloud has {int((~finite).sum())} NaN/inf points of {len(points)}", CloudReason.NAN)
        points, colors = points[finite], colors[finite]
        if len(points) == 0:
            raise CloudError("cloud has no finite points", CloudReason.EMPTY)
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


def check_voxel_msg(msg, expected: VoxelGridSpec | int) -> tuple[np.ndarray, np.ndarray]:
    """Check an occupied-voxel PointCloud2 without building its grid; returns (its records, the (M, 3) voxel
    indices). Raises CloudError unless it is the wire format exactly (architecture.md note 2: fields,
    offsets, datatypes, point_step 24) and on the ``expected`` grid (an int: the resolution only): frame,
    indices below R, each centre at ``lower + (index + 0.5) * voxel_size``, no voxel twice. The recorder
    checks every grid so, at a fraction of decoding it."""
    spec = expected if isinstance(expected, VoxelGridSpec) else VoxelGridSpec(int(expected))
    R = spec.resolution
    check_frame(msg, spec.frame_id)
    layout = [(f.name, int(f.offset), int(f.datatype), int(f.count)) for f in msg.fields]
    if layout != [(n, o, d, 1) for n, o, d in VOXEL_FIELDS] or int(msg.point_step) != VOXEL_POINT_STEP:
        raise CloudError(
            f"voxel cloud layout {layout} with point_step {msg.point_step} is not "
            f"{[(n, o, d, 1) for n, o, d in VOXEL_FIELDS]} with point_step {VOXEL_POINT_STEP}"
        )
    record, _ = _structured(msg, ("x", "y", "z", "rgb", "i", "j", "k"))
    if len(record) == 0:
        return record, np.zeros((0, 3), np.int64)
    idx = np.stack([record["i"], record["j"], record["k"]], axis=1).astype(np.int64)
    if idx.max() >= R:
        raise CloudError(f"voxel index {int(idx.max())} out of range for resolution {R}", CloudReason.GRID)
    flat = np.ravel_multi_index(idx.T, (R, R, R))
    if len(np.unique(flat)) != len(flat):
        raise CloudError(f"voxel cloud lists {len(flat) - len(np.unique(flat))} voxel(s) twice", CloudReason.GRID)
    if spec.lower is not None and spec.voxel_size is not None:
        centres = np.stack([record["x"], record["y"], record["z"]], axis=1).astype(np.float64)
        expected_centres = np.asarray(spec.lower) + (idx + 0.5) * spec.voxel_size
        with np.errstate(invalid="ignore"):
            off = np.abs(centres - expected_centres).max(axis=1)
        bad = ~(off <= 0.01 * spec.voxel_size)  # float32 rounding is ~1e-7 m; NaN counts as off
        if bad.any():
            n = int(np.argmax(bad))
            raise CloudError(
                f"voxel {idx[n].tolist()} has centre {centres[n].round(4).tolist()}, not "
                f"{expected_centres[n].round(4).tolist()}: the grid's origin or voxel size is not "
                f"{list(spec.lower)} / {spec.voxel_size} m ({int(bad.sum())} of {len(bad)} voxels off)",
                CloudReason.GRID,
            )
    return record, idx


def voxel_msg_to_grid(msg, expected: VoxelGridSpec | int) -> np.ndarray:
    """Occupied-voxel PointCloud2 -> the exact uint8 grid (4, R, R, R), checked by ``check_voxel_msg``
    (CloudError)."""
    record, idx = check_voxel_msg(msg, expected)
    R = expected.resolution if isinstance(expected, VoxelGridSpec) else int(expected)
    grid = np.zeros((4, R, R, R), dtype=np.uint8)
    if len(record) == 0:
        return grid
    colors = unpack_rgb(record["rgb"])
    grid[0, idx[:, 0], idx[:, 1], idx[:, 2]] = 255
    for c in range(3):
        grid[1 + c, idx[:, 0], idx[:, 1], idx[:, 2]] = colors[:, c]
    return grid
