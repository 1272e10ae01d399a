"""Read an .rrd back with rerun's own reader (``rerun.chunk.RrdReader``): what was logged, how often, when.

Used by the tests and handy to check a conversion without opening the viewer.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from .rerun_sdk import require_rerun


@dataclass
class EntitySummary:
    rows: int = 0  # temporal rows (log calls at some time)
    static_rows: int = 0
    components: set[str] = field(default_factory=set)  # "Archetype:field", temporal or static
    static_components: set[str] = field(default_factory=set)  # static ones shadow temporal data in rerun
    time_ranges: dict[str, tuple[int, int]] = field(default_factory=dict)  # timeline -> (min, max) raw int64
    instances: dict[str, list[int]] = field(default_factory=dict)  # component -> instance count per row, in time order
    _keyed: dict[str, list[tuple[int, int, int]]] = field(default_factory=dict, repr=False)

    def time_range_ns(self, timeline: str = "ros_time") -> tuple[int, int]:
        return self.time_ranges[timeline]


@dataclass
class RrdSummary:
    path: Path
    recording_ids: list[str]
    has_blueprint: bool
    entities: dict[str, EntitySummary]

    def __getitem__(self, entity: str) -> EntitySummary:
        entity = entity if entity.startswith("/") else f"/{entity}"
        if entity not in self.entities:
            raise KeyError(f"{self.path}: no entity {entity}; has {sorted(self.entities)}")
        return self.entities[entity]

    def __contains__(self, entity: str) -> bool:
        return (entity if entity.startswith("/") else f"/{entity}") in self.entities


_CONTROL_COLUMNS = ("rerun.controls.RowId",)


def summarize_rrd(
    path: str | Path, recording_id: str | None = None, count_instances: tuple[str, ...] = ()
) -> RrdSummary:
    """Entities, row counts and time ranges of one recording in ``path`` (the first, or ``recording_id``).

    ``count_instances`` lists components ("Boxes3D:centers") whose per-row instance counts to collect.
    """
    require_rerun()
    from rerun.chunk import RrdReader

    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"{path}: no such .rrd file")
    reader = RrdReader(path)
    recordings = reader.recordings()
    store = None
    if recording_id is not None:
        matches = [r for r in recordings if r.recording_id == recording_id]
        if not matches:
            raise KeyError(f"{path}: no recording {recording_id!r}; has {[r.recording_id for r in recordings]}")
        store = matches[0]
    entities: dict[str, EntitySummary] = {}
    for chunk in reader.stream(store=store):
        summary = entities.setdefault(chunk.entity_path, EntitySummary())
        batch = chunk.to_record_batch()
        timelines = set(chunk.timeline_names)
        names = {n for n in batch.schema.names if n not in _CONTROL_COLUMNS and n not in timelines}
        summary.components.update(names)
        if chunk.is_static:
            summary.static_rows += chunk.num_rows
            summary.static_components.update(names)
            continue
        summary.rows += chunk.num_rows
        for timeline in timelines:
            values = batch.column(timeline).cast("int64").to_numpy(zero_copy_only=False)
            values = values[~np.isnan(values.astype(np.float64))] if values.dtype.kind == "f" else values
            if len(values):
                lo, hi = int(values.min()), int(values.max())
                old = summary.time_ranges.get(timeline)
                summary.time_ranges[timeline] = (lo, hi) if old is None else (min(old[0], lo), max(old[1], hi))
        order = next((t for t in ("ros_time", "step") if t in timelines), min(timelines) if timelines else None)
        times = (
            batch.column(order).cast("int64").fill_null(0).to_numpy(zero_copy_only=False)
            if order
            else np.zeros(chunk.num_rows, np.int64)
        )
        for component in count_instances:
            if component in batch.schema.names:
                import pyarrow.compute as pc

                lengths = pc.fill_null(pc.list_value_length(batch.column(component)), 0).to_numpy(zero_copy_only=False)
                keyed = summary._keyed.setdefault(component, [])
                keyed.extend((int(t), len(keyed) + r, int(n)) for r, (t, n) in enumerate(zip(times, lengths)))
    for summary in entities.values():  # chunks need not come in time order: sort rows by their time
        summary.instances = {c: [n for _, _, n in sorted(rows)] for c, rows in summary._keyed.items()}
    return RrdSummary(path, [r.recording_id for r in recordings], bool(reader.blueprints()), entities)
