"""``RerunTrainingCallback``: loss curves and sampled vs ground-truth chunks while ``training.loop.train`` runs.

Implements the trainer's duck-typed callback protocol (``on_step``, ``on_eval``, ``on_end``).
Everything is on the ``step`` timeline:

| entity | what |
|---|---|
| ``train/<metric>`` | every numeric metric of ``on_step`` (loss, lr, sec_per_step) |
| ``eval/<metric>`` | every numeric metric of ``on_eval`` (val_loss, val_pos_err_m, val_width_err_m) |
| ``samples/<j>/{pred,gt}/{path,steps,gripper}`` | held-out sample j: the DDIM-sampled chunk and the recorded one, drawn like the live ``world/chunk`` |
| ``samples/<j>/ee`` | the observed TCP pose (axes) the prediction is conditioned on |
| ``eval/samples/<j>/{pos_err_mm,width_err_mm}`` | per-sample mean errors over the horizon |

The blueprint puts the curves on the left and one 3D view per sample on the right.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from .. import geometry
from .logger import log_pose_path
from .recording_setup import APPLICATION_ID, open_recording
from .rerun_sdk import require_rerun

# Importing this module is asking for rerun (e.g. `equidiff train --rerun`): fail here, as an
# ImportError naming the install extra, rather than midway through a training run.
require_rerun()

PRED_COLOR = (255, 140, 0)
GT_COLOR = (60, 200, 60)


def training_blueprint(max_samples: int) -> Any:
    require_rerun()
    import rerun.blueprint as rrb

    curves = rrb.Vertical(
        rrb.TimeSeriesView(name="train", origin="/train"), rrb.TimeSeriesView(name="eval", origin="/eval")
    )
    views = [
        rrb.Spatial3DView(name=f"sample {j}: prediction (orange) vs ground truth (green)", origin=f"/samples/{j}")
        for j in range(max_samples)
    ]
    if not views:
        return rrb.Blueprint(curves, rrb.TimePanel(timeline="step"), rrb.SelectionPanel(state="collapsed"))
    return rrb.Blueprint(
        rrb.Horizontal(curves, rrb.Grid(*views), column_shares=[2, 3]),
        rrb.TimePanel(timeline="step"),
        rrb.SelectionPanel(state="collapsed"),
    )


class RerunTrainingCallback:
    """Log training to rerun: ``path`` (.rrd file), or ``spawn=True`` / ``connect="host:port"`` for a live viewer."""

    def __init__(
        self,
        path: str | Path | None = None,
        *,
        spawn: bool = False,
        connect: str | None = None,
        recording_id: str | None = None,
        max_samples: int = 4,
        log_every: int = 1,
    ):
        if log_every < 1 or max_samples < 0:
            raise ValueError(f"log_every must be >= 1 and max_samples >= 0, got {log_every}, {max_samples}")
        self.rr = require_rerun()
        self.max_samples = max_samples
        self.log_every = log_every
        self.path = Path(path) if path is not None else None
        self.rec = open_recording(
            recording_id=recording_id or (self.path.stem if self.path else "training"),
            spawn=spawn,
            connect=connect,
            save=self.path,
            application_id=f"{APPLICATION_ID}_train",
            blueprint=training_blueprint(max_samples),
        )
        self.rec.log("samples", self.rr.ViewCoordinates.RIGHT_HAND_Z_UP, static=True)
        self.steps_logged = 0
        self.evals_logged = 0
        self.closed = False

    @classmethod
    def from_target(cls, target: str, **kwargs: Any) -> RerunTrainingCallback:
        """``--rerun`` value of a CLI: 'spawn', a FILE.rrd, or a viewer address host:port."""
        if target == "spawn":
            return cls(spawn=True, **kwargs)
        if target.endswith(".rrd"):
            return cls(target, **kwargs)
        return cls(connect=target, **kwargs)

    def _scalars(self, prefix: str, metrics: dict) -> None:
        for key, value in metrics.items():
            if key == "step" or isinstance(value, bool) or not isinstance(value, (int, float, np.floating, np.integer)):
                continue
            if np.isfinite(value):
                self.rec.log(f"{prefix}/{key}", self.rr.Scalars(float(value)))

    def on_step(self, step: int, metrics: dict) -> None:
        if step % self.log_every and step != 1:
            return
        self.rec.set_time("step", sequence=int(step))
        self._scalars("train", metrics)
        self.steps_logged += 1

    def on_eval(self, step: int, metrics: dict, samples: list[dict]) -> None:
        rr = self.rr
        self.rec.set_time("step", sequence=int(step))
        self._scalars("eval", metrics)
        for j, sample in enumerate(samples[: self.max_samples]):
            pred = np.asarray(sample["pred"], dtype=np.float64)
            gt = np.asarray(sample["gt"], dtype=np.float64)
            try:
                pred_poses, pred_w = geometry.action_to_pose(pred)
                gt_poses, gt_w = geometry.action_to_pose(gt)
            except geometry.GeometryError as err:  # e.g. NaN predictions early in training: say so, keep going
                self.rec.log(
                    f"samples/{j}/error",
                    rr.TextLog(f"step {step}: cannot draw sample: {err}", level=rr.TextLogLevel.WARN),
                )
                continue
            labels = [f"+{i} w={w * 1000:.0f}mm" for i, w in enumerate(pred_w)]
            log_pose_path(self.rec, f"samples/{j}/pred", pred_poses, pred_w, PRED_COLOR, labels)
            log_pose_path(
                self.rec,
                f"samples/{j}/gt",
                gt_poses,
                gt_w,
                GT_COLOR,
                [f"+{i} w={w * 1000:.0f}mm" for i, w in enumerate(gt_w)],
            )
            if "ee" in sample:
                try:
                    ee_pose, _ = geometry.action_to_pose(np.asarray(sample["ee"], dtype=np.float64))
                    p, q = geometry.pos_quat_from_pose(ee_pose)
                    self.rec.log(
                        f"samples/{j}/ee",
                        rr.Transform3D(translation=p, quaternion=rr.Quaternion(xyzw=q)),
                        rr.TransformAxes3D(0.03),
                    )
                except geometry.GeometryError:
                    pass  # the chunks are what matters here
            self.rec.log(
                f"eval/samples/{j}/pos_err_mm",
                rr.Scalars(float(np.linalg.norm(pred[:, :3] - gt[:, :3], axis=-1).mean() * 1e3)),
            )
            self.rec.log(
                f"eval/samples/{j}/width_err_mm", rr.Scalars(float(np.abs(pred[:, 9] - gt[:, 9]).mean() * 1e3))
            )
        self.evals_logged += 1

    def on_end(self, result: Any) -> None:
        self.close()

    def close(self) -> None:
        if not self.closed:
            self.rec.flush()
            self.rec.disconnect()
            self.closed = True
