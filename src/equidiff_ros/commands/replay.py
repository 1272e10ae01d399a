"""`equidiff replay BAG`: publish a recorded episode into the live ROS graph (what `ros2 bag play` does, without rosbag2).

Every recorded topic is published with its recorded type at the recorded pace (bag receive
times) times ``--rate``; headers keep their original stamps, or with ``--restamp`` are shifted
by one constant so the episode happens *now* (relative timing inside and across messages
preserved, chunk step times included since they are relative to the header). Messages without
re-stamping are published as the recorded CDR bytes, untouched.

``--robot`` re-executes the episode on the robot: only /franka/command_chunk is published,
re-stamped, to the franka node (which applies its safety limits as for any command). It
first checks that the franka node is listening and that the robot's measured pose is within
``--max-start-distance`` of the episode's first target, and refuses otherwise.
"""

from __future__ import annotations

from equidiff_ros.bag_replay import run_replay


def add_arguments(parser) -> None:
    parser.add_argument("bag", help="episode bag directory")
    parser.add_argument("--rate", type=float, default=1.0, help="speed factor (2 = twice as fast)")
    parser.add_argument("--restamp", action="store_true", help="shift header stamps so the episode starts now")
    parser.add_argument("--topics", nargs="+", help="only these topics (default: all recorded ones)")
    parser.add_argument("--exclude", nargs="+", default=[], help="skip these topics")
    parser.add_argument("--start", type=float, default=0.0, help="skip the first S seconds")
    parser.add_argument("--loop", action="store_true", help="replay until interrupted")
    parser.add_argument(
        "--wait-subscribers",
        type=float,
        default=2.0,
        help="wait up to S seconds for subscribers before starting (default 2)",
    )
    parser.add_argument(
        "--robot", action="store_true", help="re-execute the recorded commanded targets through the franka node"
    )
    parser.add_argument(
        "--max-start-distance",
        type=float,
        default=0.05,
        help="--robot: refuse if the TCP is farther than this (m) from the first target",
    )


def run(args) -> int:
    return run_replay(args)
