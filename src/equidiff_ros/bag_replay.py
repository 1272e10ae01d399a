"""A recorded episode published into the live ROS graph (``equidiff replay``; its help text says what
``--restamp`` and ``--robot`` do)."""

from __future__ import annotations

import json
import sys
import time

import numpy as np
import rclpy
from rclpy.executors import SingleThreadedExecutor
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
from rclpy.serialization import deserialize_message
from rosbags.rosbag2 import Reader

from equidiff_core.data.bags import verify_bag
from equidiff_core.data.mcap_reader import BagError
from equidiff_core.wire.chunk import chunk_from_msg
from equidiff_core.wire.rosmsg import RclpyFactory, position_from_msg, split_ns, stamp_to_ns
from equidiff_core.wire.topics import TOPIC_COMMAND_CHUNK as COMMAND_TOPIC
from equidiff_core.wire.topics import TOPIC_EE_POSE, TOPIC_TF_STATIC
from equidiff_ros.common import LATCHED_QOS, SENSOR_QOS


def shift_stamps(msg, offset_ns: int) -> None:
    """Add ``offset_ns`` to every ``header.stamp`` in an rclpy message (nested ones too, e.g. TFMessage)."""
    stack = [msg]
    while stack:
        m = stack.pop()
        header = getattr(m, "header", None)
        if header is not None and hasattr(header, "stamp"):
            header.stamp.sec, header.stamp.nanosec = split_ns(stamp_to_ns(header.stamp) + offset_ns)
        for name in getattr(m, "get_fields_and_field_types", dict)():
            if name == "header":
                continue
            value = getattr(m, name)
            if isinstance(value, (list, tuple)):
                stack.extend(v for v in value if hasattr(v, "get_fields_and_field_types"))
            elif hasattr(value, "get_fields_and_field_types"):
                stack.append(value)


def _load(bag, topics, exclude, start_s):
    """({topic: type}, [(log_ns, topic, raw)] in time order) of the selected topics."""
    verify_bag(bag)  # every CRC checked first (rosbags' reader checks none): a damaged bag is not replayed
    try:
        with Reader(bag) as reader:
            conns = [c for c in reader.connections if (topics is None or c.topic in topics) and c.topic not in exclude]
            types = {c.topic: c.msgtype for c in conns}
            start = reader.start_time
            msgs = [(ts, c.topic, bytes(raw)) for c, ts, raw in reader.messages(connections=conns)] if conns else []
    except Exception as err:
        raise BagError(f"{bag}: unreadable bag ({type(err).__name__}: {err})") from err
    cut = start + int(start_s * 1e9)
    # /tf_static is always sent, first: it describes the whole episode
    msgs = [
        (max(ts, cut), t, raw) if t == TOPIC_TF_STATIC else (ts, t, raw)
        for ts, t, raw in msgs
        if ts >= cut or t == TOPIC_TF_STATIC
    ]
    msgs.sort(key=lambda m: (m[0], m[1] != TOPIC_TF_STATIC))
    return types, msgs


def _check_robot_start(node, executor, first_chunk_raw, max_dist: float, wait_s: float) -> str | None:
    """None if the TCP is close to the episode's first target, else the reason to refuse."""
    f = RclpyFactory()
    poses = []
    sub = node.create_subscription(f.cls("geometry_msgs/msg/PoseStamped"), TOPIC_EE_POSE, poses.append, SENSOR_QOS)
    end = time.monotonic() + wait_s
    while not poses and time.monotonic() < end:
        executor.spin_once(timeout_sec=0.05)
    node.destroy_subscription(sub)
    if not poses:
        return f"no {TOPIC_EE_POSE} within {wait_s:.0f} s: is franka_node running?"
    chunk = chunk_from_msg(deserialize_message(first_chunk_raw, f.cls("trajectory_msgs/msg/MultiDOFJointTrajectory")))
    dist = float(np.linalg.norm(chunk.poses[0, :3, 3] - position_from_msg(poses[-1])))
    if dist > max_dist:
        return (
            f"the TCP is {dist * 100:.1f} cm from the episode's first target (limit "
            f"{max_dist * 100:.1f} cm): move it to the start pose first"
        )
    return None


def run_replay(args) -> int:
    """``equidiff replay`` for its parsed arguments: publish the bag, then one JSON line; the exit status."""
    if args.rate <= 0:
        print("equidiff replay: --rate must be positive", file=sys.stderr)
        return 2
    topics = [COMMAND_TOPIC] if args.robot else args.topics
    try:
        types, msgs = _load(args.bag, set(topics) if topics else None, set(args.exclude), args.start)
    except BagError as err:
        print(f"equidiff replay: {err}", file=sys.stderr)
        return 1
    if not msgs:
        print(f"equidiff replay: nothing to publish from {args.bag} (topics {sorted(types)})", file=sys.stderr)
        return 1
    restamp = args.restamp or args.robot
    f = RclpyFactory()
    rclpy.init(args=None)
    node = rclpy.create_node("equidiff_replay")
    executor = SingleThreadedExecutor()
    executor.add_node(node)
    counts = {t: 0 for t in types}
    try:
        classes = {}
        for t, m in types.items():
            try:
                classes[t] = f.cls(m)
            except (ImportError, AttributeError) as err:  # e.g. tf2_msgs on a PyPI-only machine
                print(f"equidiff replay: skipping {t}: {m} is not installed here ({err})", file=sys.stderr)
        if not classes:
            print("equidiff replay: none of the recorded types is installed", file=sys.stderr)
            return 1
        msgs = [m for m in msgs if m[1] in classes]
        types = {t: m for t, m in types.items() if t in classes}
        counts = {t: 0 for t in types}
        # Reliable with a deep history: a replay publishes in bursts (4x speed, 100 Hz topics) and
        # a keep-last-10 writer would overwrite samples a busy subscriber has not acknowledged.
        replay_qos = QoSProfile(
            depth=200,
            reliability=ReliabilityPolicy.RELIABLE,
            durability=DurabilityPolicy.VOLATILE,
            history=HistoryPolicy.KEEP_LAST,
        )
        pubs = {
            t: node.create_publisher(classes[t], t, LATCHED_QOS if t == TOPIC_TF_STATIC else replay_qos) for t in types
        }
        if args.robot:
            pub = pubs[COMMAND_TOPIC]
            end = time.monotonic() + max(args.wait_subscribers, 5.0)
            while pub.get_subscription_count() == 0 and time.monotonic() < end:
                executor.spin_once(timeout_sec=0.05)
            if pub.get_subscription_count() == 0:
                print(
                    f"equidiff replay --robot: nobody subscribes to {COMMAND_TOPIC}: is franka_node running?",
                    file=sys.stderr,
                )
                return 1
            reason = _check_robot_start(node, executor, msgs[0][2], args.max_start_distance, 5.0)
            if reason:
                print(f"equidiff replay --robot: refusing: {reason}", file=sys.stderr)
                return 1
        elif args.wait_subscribers > 0:
            end = time.monotonic() + args.wait_subscribers
            while time.monotonic() < end and not all(p.get_subscription_count() for p in pubs.values()):
                executor.spin_once(timeout_sec=0.05)

        first_log = msgs[0][0]
        lateness = []
        while True:
            wall0 = time.monotonic()
            offset = (time.time_ns() - first_log) if restamp else 0
            for log_ns, topic, raw in msgs:
                due = wall0 + (log_ns - first_log) / 1e9 / args.rate
                delay = due - time.monotonic()
                if delay > 0:
                    time.sleep(delay)
                else:
                    lateness.append(-delay)
                if restamp:
                    msg = deserialize_message(raw, classes[topic])
                    shift_stamps(msg, offset)
                    pubs[topic].publish(msg)
                else:
                    pubs[topic].publish(raw)
                counts[topic] += 1
            if not args.loop:
                break
        # let reliable transports deliver the tail before the node goes away
        end = time.monotonic() + 0.5
        while time.monotonic() < end:
            executor.spin_once(timeout_sec=0.05)
        print(
            json.dumps(
                {
                    "bag": str(args.bag),
                    "published": counts,
                    "messages": sum(counts.values()),
                    "duration_s": round((msgs[-1][0] - first_log) / 1e9 / args.rate, 3),
                    "rate": args.rate,
                    "restamped": restamp,
                    "max_late_ms": round(max(lateness, default=0.0) * 1e3, 2),
                }
            )
        )
        return 0
    except KeyboardInterrupt:
        print(json.dumps({"bag": str(args.bag), "published": counts, "interrupted": True}))
        return 130
    finally:
        executor.shutdown()
        node.destroy_node()
        if rclpy.ok():
            rclpy.try_shutdown()
