"""The cameras' clouds fused into voxel grids: voxel_node's rule, and the same rule offline.

``CloudFusion`` takes each camera's clouds as they arrive and hands out one grid per new
complete set (stamps within ``slop``), at most one per observation period; voxel_node runs it
live, ``revoxelize_bag`` runs it over a recorded bag's clouds with new extrinsics, so a
re-voxelised demo is what the live node would have published with those extrinsics. The new
bag also carries those extrinsics: in ``/tf_static`` (each camera's transform replaced) and in
its metadata (``extrinsics_metadata``), so nothing in it still describes the old calibration.
"""

from __future__ import annotations

import shutil
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np
import yaml
from rosbags.rosbag2 import Reader

from ..cameras import extrinsics_tf_message
from ..config import LabConfig
from ..data.bags import close_derived_bag, find_bags, verify_bag
from ..data.mcap_reader import BagError
from ..data.mcap_writer import open_bag_writer
from ..data.recording import _qos as recorder_qos
from ..runtime.output_files import distinct_names, staged_output, unique_paths
from ..wire.pointcloud import CloudError, grid_to_voxel_msg, msg_to_cloud
from ..wire.rosmsg import rosbags_factory, stamp_to_ns
from ..wire.topics import CLOUD_TYPE, TF_TYPE, TOPIC_TF_STATIC, TOPIC_VOXELS
from .sync import ApproximateTimeMatcher, Match
from .voxels import Voxelizer, VoxelizerConfig

# A set newer than the last grid by less than this share of the period is not due yet
# (cameras faster than the observation rate): jitter must not skip a frame at the nominal rate.
RATE_CAP_FRACTION = 0.75


class CloudFusion:
    """Clouds in (``add``), one grid per new complete set out (``next_grid``)."""

    def __init__(self, lab: LabConfig, slop_ns: int, queue_size: int = 5, cleanup: VoxelizerConfig | None = None):
        self.lab = lab
        self.names = [c.name for c in lab.cameras]
        self.voxelizer = Voxelizer(lab.workspace, [c.extrinsics.matrix() for c in lab.cameras], cleanup)
        self.matcher: ApproximateTimeMatcher = ApproximateTimeMatcher(self.names, slop_ns, queue_size)
        self.period_ns = int(1e9 / lab.observation_hz)
        self._last_stamp: int | None = None

    def add(self, camera: str, stamp_ns: int, cloud) -> None:
        self.matcher.add(camera, stamp_ns, cloud)

    def next_grid(self) -> tuple[int, np.ndarray] | None:
        """(stamp of the set's newest cloud, grid) for a new set that is due, else None."""
        match: Match | None = self.matcher.newest()
        if match is None:
            return None
        if self._last_stamp is not None and match.newest_ns - self._last_stamp < RATE_CAP_FRACTION * self.period_ns:
            return None
        self._last_stamp = match.newest_ns
        return match.newest_ns, self.voxelizer([match.items[n] for n in self.names])


def extrinsics_metadata(lab: LabConfig) -> dict[str, str]:
    """Episode-metadata ``extra`` entries naming each camera's extrinsics (T_base_optical in
    ``lab.base_frame``): ``extrinsics.<camera>`` = a lab.yaml ``extrinsics`` mapping in YAML flow style."""
    out = {"extrinsics_base_frame": lab.base_frame}
    for cam in lab.cameras:
        e = cam.extrinsics
        out[f"extrinsics.{cam.name}"] = yaml.safe_dump(
            {"translation": list(e.translation), "quaternion_xyzw": list(e.quaternion_xyzw)},
            default_flow_style=True,
            sort_keys=False,
            width=1000,
        ).strip()
    return out


def replace_camera_transforms(msg, lab: LabConfig, factory):
    """A copy of the TFMessage ``msg`` in which every camera of ``lab`` has its extrinsics: a
    transform to a camera's optical frame is replaced (its stamp kept), one missing is added
    (stamped like the message's first transform); transforms to other frames are kept as they are."""
    stamps = [stamp_to_ns(t.header.stamp) for t in msg.transforms]
    default_stamp = stamps[0] if stamps else 0
    by_frame = {cam.frame_id: cam for cam in lab.cameras}
    out, done = [], set()
    for t, stamp in zip(msg.transforms, stamps):
        cam = by_frame.get(t.child_frame_id)
        if cam is None:
            out.append(t)
            continue
        out.extend(extrinsics_tf_message([cam], lab.base_frame, stamp, factory).transforms)
        done.add(cam.frame_id)
    missing = [cam for cam in lab.cameras if cam.frame_id not in done]
    out.extend(extrinsics_tf_message(missing, lab.base_frame, default_stamp, factory).transforms)
    return factory.make(TF_TYPE, transforms=out)


@dataclass(frozen=True)
class RevoxelizeReport:
    path: Path
    grids: int  # /voxels messages written
    replaced: int  # /voxels messages the source bag had
    clouds: dict[str, int]  # camera -> clouds read


def revoxelize_bag(
    source: str | Path, output: str | Path, lab: LabConfig, slop_s: float = 0.1, cleanup: VoxelizerConfig | None = None
) -> RevoxelizeReport:
    """A copy of the bag at ``source`` whose /voxels are rebuilt from its recorded camera clouds
    with ``lab``'s cameras and extrinsics, and whose ``/tf_static`` and metadata carry those
    extrinsics (``replace_camera_transforms``, ``extrinsics_metadata``; a bag without
    ``/tf_static`` gets one, logged with its first message). Every other topic and metadata
    entry is copied as is.

    A grid is written at the log time of the cloud that completed its set (as voxel_node
    publishes it). Raises ``BagError`` for a bag without the clouds of every camera in ``lab``
    (recorded without ``record_clouds``) or an ``output`` that exists."""

    source, output = Path(source), Path(output)
    if output.exists():
        raise BagError(f"{output} already exists: not overwriting")
    factory = rosbags_factory()
    camera_of = {c.topic: c.name for c in lab.cameras}
    fusion = CloudFusion(lab, int(slop_s * 1e9), cleanup=cleanup)
    ws = lab.workspace
    clouds = dict.fromkeys(camera_of.values(), 0)
    replaced = grids = 0
    verify_bag(source)  # every CRC, before anything is derived from it (rosbags' reader checks none)
    with Reader(source) as reader:
        missing = sorted(t for t in camera_of if t not in reader.topics)
        if missing:
            raise BagError(
                f"{source}: no recorded clouds on {', '.join(missing)} (recorded without "
                f"record_clouds?): nothing to re-voxelise from"
            )
        output.parent.mkdir(parents=True, exist_ok=True)
        writer = open_bag_writer(output, chunk_max_age_s=float("inf"))
        try:
            out_conns = {}
            for conn in reader.connections:
                if conn.topic != TOPIC_VOXELS:
                    out_conns[conn.id] = writer.add_connection(
                        conn.topic,
                        conn.msgtype,
                        msgdef=conn.msgdef.data,
                        rihs01=conn.digest,
                        serialization_format=conn.ext.serialization_format,
                        offered_qos_profiles=conn.ext.offered_qos_profiles,
                    )
            voxels_conn = writer.add_connection(TOPIC_VOXELS, CLOUD_TYPE, typestore=factory.typestore)
            tf_conn = None
            if TOPIC_TF_STATIC not in reader.topics:  # the recorder always writes one; older bags may lack it
                tf_conn = writer.add_connection(
                    TOPIC_TF_STATIC,
                    TF_TYPE,
                    typestore=factory.typestore,
                    offered_qos_profiles=[recorder_qos(transient_local=True)],
                )
            for conn, log_ns, raw in reader.messages():
                if tf_conn is not None:
                    tf = extrinsics_tf_message(lab.cameras, lab.base_frame, log_ns, factory)
                    writer.write(tf_conn, log_ns, factory.typestore.serialize_cdr(tf, TF_TYPE))
                    tf_conn = None
                if conn.topic == TOPIC_VOXELS:
                    replaced += 1
                    continue
                if conn.topic == TOPIC_TF_STATIC:
                    tf = replace_camera_transforms(factory.typestore.deserialize_cdr(raw, conn.msgtype), lab, factory)
                    writer.write(out_conns[conn.id], log_ns, factory.typestore.serialize_cdr(tf, conn.msgtype))
                    continue  # not a camera's cloud
                writer.write(out_conns[conn.id], log_ns, raw)
                name = camera_of.get(conn.topic)
                if name is None:
                    continue
                try:
                    cloud = msg_to_cloud(factory.typestore.deserialize_cdr(raw, conn.msgtype))
                except CloudError as err:
                    raise BagError(f"{source}: a cloud on {conn.topic} at {log_ns} ns: {err}") from err
                clouds[name] += 1
                fusion.add(name, cloud.stamp_ns, cloud)
                if (out := fusion.next_grid()) is not None:
                    stamp_ns, grid = out
                    msg = grid_to_voxel_msg(grid, ws.lower, ws.voxel_size, stamp_ns, lab.base_frame, factory)
                    writer.write(voxels_conn, log_ns, factory.typestore.serialize_cdr(msg, CLOUD_TYPE))
                    grids += 1
            close_derived_bag(
                writer,
                source,
                output,
                f"re-voxelised by equidiff dataset revoxelize from {source.name} ({grids} grids; "
                "/tf_static and extrinsics.* carry the extrinsics used)",
                extra=extrinsics_metadata(lab),
            )
        except BaseException:
            writer.abort()
            shutil.rmtree(output, ignore_errors=True)
            raise
    return RevoxelizeReport(output, grids, replaced, clouds)


def revoxelize_bags(
    sources: list[str | Path], out_dir: str | Path, lab: LabConfig, slop_s: float = 0.1, *, force: bool = False
) -> tuple[list[RevoxelizeReport], list[tuple[Path, str]]]:
    """``revoxelize_bag`` for every bag under ``sources`` (``data.bags.find_bags``) into ``out_dir``, a new folder:
    each bag under its own name, or its path below the bags' common folder where names repeat. ``out_dir``
    is written beside itself and renamed into place once every bag is done (``runtime.output_files.staged_output``):
    an existing one raises ``OutputExistsError`` unless ``force``; nothing lands when no bag could be
    re-voxelised. Returns (the reports, paths as in ``out_dir``; the failed bags with their reasons)."""
    out_dir = Path(out_dir)
    bags = unique_paths(find_bags(sources))
    reports: list[RevoxelizeReport] = []
    failed: list[tuple[Path, str]] = []
    with staged_output(out_dir, force=force) as staged:
        staged.path.mkdir()
        for bag, name in zip(bags, distinct_names(bags), strict=True):
            try:
                report = revoxelize_bag(bag, staged.path / name, lab, slop_s=slop_s)
            except BagError as err:
                failed.append((bag, str(err)))
                continue
            reports.append(replace(report, path=out_dir / name))
        if not reports:
            staged.discard()
    return reports, failed
