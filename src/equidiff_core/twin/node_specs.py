"""The twin stack's nodes and their parameters (ROS-free): what ``equidiff_ros.twin.TwinStack``
starts, as separate processes or composed into one, and as twin.launch.py starts them.

A spec is ``name -> (executable, parameters, remaps)``, in start order.
"""

from __future__ import annotations

from pathlib import Path

from ..config import LabConfig, default_config_dir
from ..control import load_control_config
from ..wire.topics import TOPIC_COMMAND_CHUNK, TOPIC_TWIN_POLICY_CHUNK
from .config import TWIN_PRECISION

NodeSpecs = dict[str, tuple[str, dict, dict]]


def twin_node_params(
    lab_path: Path,
    twin_path: Path,
    host: str,
    seed: int,
    sim: bool,
    latency_s: float,
    stall_timeout_s: float,
    max_speed: float,
) -> dict:
    """twin_node's parameters; ``sim``: it owns the clock (/clock) and steps in lockstep."""
    return {
        "lab_config": str(lab_path),
        "twin_config": str(twin_path),
        "host": host,
        "seed": seed,
        "clock": "sim" if sim else "realtime",
        "latency_s": float(latency_s),
        "stall_timeout_s": float(stall_timeout_s),
        "max_speed": float(max_speed),
    }


def pipeline_specs(
    lab: LabConfig,
    lab_path: Path,
    out_dir: Path,
    host: str,
    task: str,
    record_clouds: bool,
    sim: bool,
    lenient: bool,
    latency_s: float,
    policy: str | None = None,
    device: str = "cpu",
    precision: str = TWIN_PRECISION,
    torch_threads: int = 1,
    policy_parameters: dict | None = None,
) -> NodeSpecs:
    """Every node but twin_node, in start order: one camera_node per camera, named
    ``camera_<camera>``, voxel_node, franka_node (robot_ip = the twin's ``host``), recorder_node
    and, with a ``policy``, policy_node with its chunks remapped to the supervisor's gate (and
    ``policy_parameters`` beside the twin's own, e.g. the doubt gate's).

    ``sim``: every node runs on twin_node's clock; ``lenient``: accept older observations (CI
    machines too loaded to hold 5 Hz; real time only), never for reported numbers."""
    common = {"lab_config": str(lab_path), "use_sim_time": sim}  # twin_node owns the clock
    clouds = {"reliable_clouds": True} if sim else {}  # the lockstep owes every frame a chunk
    specs = {}
    for cam in lab.cameras:
        specs[f"camera_{cam.name}"] = (
            "camera_node",
            {
                **common,
                **clouds,
                "backend": "twin",
                "camera": cam.name,
                **({"backend_options": "{lockstep: true}"} if sim else {}),
            },
            {},
        )
    voxel = {"stale_after_s": 3.0, "slop_s": 0.15} if lenient and not sim else {}
    specs["voxel_node"] = ("voxel_node", {**common, **clouds, **voxel}, {})
    # run_dir: its unclean-exit marker lives with this job's logs, not in the machine's tmp
    specs["franka_node"] = (
        "franka_node",
        # require_ack_on_start: the supervisor is the twin's operator (it acknowledges stops before homing)
        {
            **common,
            "robot_ip": host,
            "realtime": False,
            "run_dir": str(out_dir / "logs"),
            "require_ack_on_start": False,
        },
        {},
    )
    specs["recorder_node"] = (
        "recorder_node",
        {
            **common,
            "output_dir": str(out_dir / "bags"),
            "task": task,
            "record_clouds": record_clouds,
        },
        {},
    )
    if policy:
        if sim:  # an observation is at most L old in sim time when its chunk is due
            # the twin holds each chunk until its stamp + L exactly: the policy bridges that L
            # (its latency_s auto would see only the publication, not the hold)
            timing = {"max_observation_age_s": max(0.5, latency_s + 0.2), "latency_s": float(latency_s)}
        else:
            timing = {"max_observation_age_s": 4.0, "max_state_offset_s": 0.5} if lenient else {}
        control = load_control_config(default_config_dir() / "control.yaml")  # franka_node's, as started here
        specs["policy_node"] = (
            "policy_node",
            {
                **common,
                "checkpoint": str(policy),
                "device": device,
                "precision": precision,
                "torch_threads": torch_threads,
                "rtc_max_gap_m": control.safety.max_first_step_jump_m,
                **timing,
                **(policy_parameters or {}),
            },
            {TOPIC_COMMAND_CHUNK: TOPIC_TWIN_POLICY_CHUNK},
        )
    return specs
