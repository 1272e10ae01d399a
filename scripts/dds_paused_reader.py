"""Does a paused reader hold back a reliable writer's messages from the other readers? (docs/twin.md, stalls)

One publisher sends ``--size`` bytes (PointCloud2, reliable, keep last 5, like /voxels) at 5 Hz
and a small best-effort message at 200 Hz (like the twin's /clock); two readers in their own
processes subscribe to both: ``watcher`` reliably, ``paused`` with ``--paused-qos``. Once both readers receive, the paused reader gets SIGSTOP for ``--stop`` s, then SIGCONT.
Prints, per reader, every hole in the sequence or gap over 1 s, and the last message it got.

    python scripts/dds_paused_reader.py --size 150000 --stop 25 --paused-qos reliable
"""

from __future__ import annotations

import argparse
import os
import signal
import subprocess
import sys
import threading
import time


def qos(kind: str):
    from rclpy.qos import HistoryPolicy, QoSProfile, ReliabilityPolicy

    reliability = ReliabilityPolicy.RELIABLE if kind == "reliable" else ReliabilityPolicy.BEST_EFFORT
    return QoSProfile(depth=5, reliability=reliability, history=HistoryPolicy.KEEP_LAST)


def role(name: str, seconds: float, size: int, kind: str) -> None:
    import rclpy
    from sensor_msgs.msg import PointCloud2
    from std_msgs.msg import String

    rclpy.init()
    node = rclpy.create_node(name)
    start = time.monotonic()
    if name == "publisher":
        pub = node.create_publisher(PointCloud2, "/paused_reader_test", qos("reliable"))
        tick = node.create_publisher(String, "/paused_reader_tick", qos("best_effort"))
        i = 0
        while time.monotonic() - start < seconds:
            msg = PointCloud2()
            msg.header.frame_id, msg.data = str(i), bytes(size)
            pub.publish(msg)
            i += 1
            for _ in range(40):
                tick.publish(String(data="t"))
                time.sleep(0.005)
        print(f"publisher: sent {i}", flush=True)
        return
    last = [-1, start]

    def on_msg(msg):
        now, seq = time.monotonic(), int(msg.header.frame_id)
        if last[0] < 0:
            print(f"{name}: first message {seq} (t={now - start:.1f} s)", flush=True)
        elif seq != last[0] + 1 or now - last[1] > 1.0:
            print(f"{name}: {last[0]} -> {seq} after {now - last[1]:.1f} s (t={now - start:.1f} s)", flush=True)
        last[:] = [seq, now]

    node.create_subscription(PointCloud2, "/paused_reader_test", on_msg, qos(kind))
    node.create_subscription(String, "/paused_reader_tick", lambda msg: None, qos("best_effort"))
    while time.monotonic() - start < seconds:
        rclpy.spin_once(node, timeout_sec=0.1)
    print(f"{name}: last message {last[0]}", flush=True)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--size", type=int, default=150_000, help="bytes per message")
    parser.add_argument("--stop", type=float, default=25.0, help="seconds the paused reader is stopped")
    parser.add_argument("--paused-qos", choices=("reliable", "best_effort"), default="reliable")
    parser.add_argument("--role", help=argparse.SUPPRESS)
    parser.add_argument("--seconds", type=float, help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.role:
        role(args.role, args.seconds, args.size, args.paused_qos if args.role == "paused" else "reliable")
        return 0
    env = {**os.environ, "ROS_AUTOMATIC_DISCOVERY_RANGE": "LOCALHOST"}
    env.setdefault("ROS_DOMAIN_ID", str(150 + os.getpid() % 60))
    total = 60.0 + args.stop + 20.0  # the publisher's run: start-up, the pause, and after it

    def spawn(name: str, seconds: float, **kw) -> subprocess.Popen:
        cmd = [sys.executable, __file__, "--role", name, "--seconds", str(seconds), "--size", str(args.size)]
        return subprocess.Popen(cmd + ["--paused-qos", args.paused_qos], env=env, **kw)

    def echo(proc: subprocess.Popen, receiving: threading.Event) -> None:
        for line in proc.stdout:
            print(line, end="", flush=True)
            if "first message" in line:
                receiving.set()

    readers, receiving = [], []
    for name in ("watcher", "paused"):
        readers.append(spawn(name, total + 15, stdout=subprocess.PIPE, text=True))
        receiving.append(threading.Event())
        threading.Thread(target=echo, args=(readers[-1], receiving[-1]), daemon=True).start()
    publisher = spawn("publisher", total)
    for event in receiving:  # both readers matched and receiving (rclpy starts slowly on a loaded machine)
        event.wait(60.0)
    time.sleep(5.0)
    os.kill(readers[1].pid, signal.SIGSTOP)
    print(f"paused reader stopped for {args.stop:.0f} s", flush=True)
    time.sleep(args.stop)
    os.kill(readers[1].pid, signal.SIGCONT)
    print("paused reader continued", flush=True)
    for proc in (publisher, *readers):
        proc.wait()
    return 0


if __name__ == "__main__":
    sys.exit(main())
