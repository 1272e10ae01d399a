"""`equidiff check equivariance`: C4 and 45 deg equivariance errors on twin-like scenes, every inference path.

EquiDiff is exactly C4-equivariant and only approximately C8 (a 3^3 kernel on a cubic grid is
exact under 90 deg rotations, not 45 deg ones); this command measures both, on scenes built
from the twin's objects (``models.equivariance.twin_scenes``), for the denoiser output at one
diffusion step and for the full DDIM-sampled actions from fixed noise.

Prints one JSON line: ``preset``, ``policy``, ``control``, ``weights`` (``random`` or the
checkpoint's path), ``scenes``, ``timestep``, ``cpu`` and, per subject, ``{"denoiser": S,
"sampling": S}`` with S = ``{"c4_max_rel_err" (90/180/270 deg), "rot45_max_rel_err" (45/135/225/315
deg), "per_element"}``:

* ``escnn``: the training-time model (escnn for EquiDiff; null for an exported EquiDiff file,
  which holds no escnn weights);
* ``exported_fp32`` / ``exported_bf16``: the exported plain-torch policy (``inference``), traced,
  as the policy node runs it (bf16 is emulated, hence slow, on CPUs without native bf16);
* ``baseline``: DiffPo-C with random weights, same preset and normaliser, in the same run, so the
  contrast is visible (absent when the subject is the baseline already).

Random weights by default; ``--checkpoint`` measures a training ``last.ckpt`` or an exported ``policy.pt``.
"""

from __future__ import annotations

from equidiff_core.benches.equivariance_check import EquivarianceSettings, run_equivariance_check
from equidiff_ros.commands import print_result


def add_arguments(parser) -> None:
    parser.add_argument("--preset", default="compact", help="paper | compact | tiny (ignored with --checkpoint)")
    parser.add_argument(
        "--policy", default="equidiff", choices=["equidiff", "baseline"], help="ignored with --checkpoint"
    )
    parser.add_argument("--control", default="absolute", choices=["absolute", "relative"])
    parser.add_argument("--checkpoint", default=None, help="a training checkpoint (last.ckpt) or exported policy.pt")
    parser.add_argument("--scenes", type=int, default=2, help="twin-like scenes per group element")
    parser.add_argument("--timestep", type=int, default=10, help="diffusion step at which the denoiser is compared")
    parser.add_argument("--seed", type=int, default=0)


def run(args) -> int:
    settings = EquivarianceSettings(
        preset=args.preset,
        policy=args.policy,
        control=args.control,
        checkpoint=args.checkpoint,
        scenes=args.scenes,
        timestep=args.timestep,
        seed=args.seed,
    )
    return print_result(run_equivariance_check(settings), "check equivariance")
