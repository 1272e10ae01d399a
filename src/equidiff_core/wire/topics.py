"""Every topic name of the stack, and the type of each recorded one: the one place they are written.

The nodes (through ``equidiff_ros.common``), the recorder, the dataset reader and the twin's
in-process demos all take names from here, so a renamed topic cannot leave a reader behind.
docs/architecture.md lists each with its rate, frame and QoS. Camera clouds are per camera:
``config.CameraConfig.topic`` (``/cameras/<name>/points``).
"""

from __future__ import annotations

TOPIC_VOXELS = "/voxels"
TOPIC_EE_POSE = "/franka/ee_pose"
TOPIC_JOINT_STATES = "/franka/joint_states"
TOPIC_COMMAND_CHUNK = "/franka/command_chunk"
TOPIC_EXECUTED_TARGET = "/franka/executed_target"
TOPIC_DIAGNOSTICS = "/diagnostics"
TOPIC_JOY = "/spacenav/joy"
TOPIC_RECORDER_COMMAND = "/recorder/command"
TOPIC_POLICY_SKIPPED = "/policy/skipped"
TOPIC_POLICY_STATE = "/policy/state"  # running / paused <reason>, latched
# each chunk's doubt (policy.doubt), geometry_msgs/Vector3Stamped stamped with the chunk's stamp (wire.rosmsg.doubt_msg)
TOPIC_POLICY_DOUBT = "/policy/doubt"
TOPIC_POLICY_EPISODE = "/policy/episode"  # {"seed", "start_ns"}: the sampling seeds of an episode, latched
TOPIC_TELEOP_ACTIVE = "/teleop/active"  # an operator's takeover (intervention), latched
TOPIC_RECORDER_STATUS = "/recorder/status"  # idle / recording <path> / ..., latched
# franka_node's state for operators, latched JSON: {"state": moving | holding | homing | awaiting_ack | faulted,
# "reason": why it holds or faulted ("" otherwise), "last_fault": the newest fault's text, "last_fault_ns"}
TOPIC_FRANKA_STATUS = "/franka/status"
TOPIC_CLOCK = "/clock"
TOPIC_TF = "/tf"  # franka_node: base -> TCP, where tf2_msgs is installed
TOPIC_TF_STATIC = "/tf_static"
CAMERA_TOPIC_PREFIX = "/cameras/"
# Each camera's colour image: image_transport's compressed transport of the base topic .../color/image_raw
CAMERA_COLOR_SUFFIX = "/color/image_raw/compressed"
# The twin's own (twin_node and its supervisor)
TOPIC_TWIN_RESET = "/twin/reset"
TOPIC_TWIN_SCENE = "/twin/scene"
TOPIC_TWIN_STATE = "/twin/state"
TOPIC_TWIN_AWAIT_POLICY = "/twin/await_policy"
TOPIC_TWIN_POLICY_CHUNK = "/twin/policy_chunk"  # policy_node's chunks, remapped, when the supervisor gates them

# Services (std_srvs): the operator flow (`equidiff lab`) and the twin's supervisor call them.
SERVICE_RECORDER_START = "/recorder/start"  # Trigger
SERVICE_RECORDER_STOP = "/recorder/stop"  # Trigger: keep the episode, marked successful
SERVICE_RECORDER_STOP_FAILURE = "/recorder/stop_failure"  # Trigger: keep it, marked failed
SERVICE_RECORDER_DISCARD = "/recorder/discard"  # Trigger
SERVICE_POLICY_ENABLE = "/policy/enable"  # SetBool: true runs the policy, false pauses it
SERVICE_FRANKA_ACKNOWLEDGE = "/franka/acknowledge"  # Trigger: go on after a robot error / divergence stop
SERVICE_FRANKA_HOME = "/franka/home"  # Trigger: glide slowly to the configured home pose (refused awaiting ack)

CLOUD_TYPE = "sensor_msgs/msg/PointCloud2"
POSE_TYPE = "geometry_msgs/msg/PoseStamped"
DOUBT_TYPE = "geometry_msgs/msg/Vector3Stamped"
TF_TYPE = "tf2_msgs/msg/TFMessage"
COMPRESSED_IMAGE_TYPE = "sensor_msgs/msg/CompressedImage"

# What an episode bag holds (the recorder's default topics; camera clouds are optional extras).
RECORDED_TOPICS: dict[str, str] = {
    TOPIC_VOXELS: CLOUD_TYPE,
    TOPIC_EE_POSE: POSE_TYPE,
    TOPIC_JOINT_STATES: "sensor_msgs/msg/JointState",
    TOPIC_COMMAND_CHUNK: "trajectory_msgs/msg/MultiDOFJointTrajectory",
    TOPIC_EXECUTED_TARGET: POSE_TYPE,
    TOPIC_JOY: "sensor_msgs/msg/Joy",
    TOPIC_DIAGNOSTICS: "diagnostic_msgs/msg/DiagnosticArray",
    TOPIC_TELEOP_ACTIVE: "std_msgs/msg/Bool",
    TOPIC_POLICY_STATE: "std_msgs/msg/String",
    TOPIC_POLICY_DOUBT: DOUBT_TYPE,
}
# What training needs of a bag: the in-process demos write just these.
TRAINING_TOPICS: dict[str, str] = {
    t: RECORDED_TOPICS[t] for t in (TOPIC_VOXELS, TOPIC_EE_POSE, TOPIC_JOINT_STATES, TOPIC_COMMAND_CHUNK)
}


def camera_color_topic(camera: str) -> str:
    """``/cameras/<camera>/color/image_raw/compressed``: the camera's JPEG colour image (sensor_msgs/CompressedImage)."""
    return f"{CAMERA_TOPIC_PREFIX}{camera}{CAMERA_COLOR_SUFFIX}"


def camera_of_color_topic(topic: str) -> str | None:
    """The camera name of a colour-image topic, None for any other topic."""
    if topic.startswith(CAMERA_TOPIC_PREFIX) and topic.endswith(CAMERA_COLOR_SUFFIX):
        name = topic[len(CAMERA_TOPIC_PREFIX) : -len(CAMERA_COLOR_SUFFIX)]
        return name if name and "/" not in name else None
    return None
