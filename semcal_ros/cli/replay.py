"""``semcal replay BAG``: play a rosbag2 into the live ROS graph (the bag_player node's engine)."""

from __future__ import annotations

import argparse


def register(subparsers: argparse._SubParsersAction) -> None:
    p = subparsers.add_parser(
        "replay", help="play a rosbag2 (mcap or sqlite3) into the ROS graph",
        description="Publish a rosbag2's messages with their recorded timing (scaled by --rate); "
                    "waits for reliable subscribers to acknowledge the last messages before "
                    "exiting.")
    p.add_argument("bag", help="bag folder (metadata.yaml + .mcap or .db3)")
    p.add_argument("--rate", type=float, default=1.0, help="playback speed factor (default 1)")
    p.add_argument("--clock", action="store_true", help="publish /clock with the bag's time")
    p.add_argument("--loop", action="store_true", help="start over at the end until Ctrl-C")
    p.add_argument("--topics", nargs="+", default=[], metavar="TOPIC",
                   help="play only these topics")
    p.add_argument("--wait", type=float, default=2.0, metavar="S",
                   help="seconds to wait for subscribers before playing (default 2)")
    p.add_argument("--delay", type=float, default=1.0, metavar="S",
                   help="seconds between subscribers appearing and the first message "
                        "(default 1: they need a moment to match the player)")
    p.add_argument("--remap", action="append", default=[], metavar="FROM:=TO",
                   help="rename a topic, e.g. /lidar/points:=/points (repeatable)")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    import rclpy
    from rclpy.node import Node
    from tqdm import tqdm

    from semcal_ros.ros.replay import BagReplay, ReplayParams
    from semcal_ros.ros.runtime import use_default_fastdds_profile

    params = ReplayParams(bag=args.bag, rate=args.rate, clock=args.clock, loop=args.loop,
                          topics=tuple(args.topics), wait_for_subscribers=args.wait,
                          start_delay=args.delay)
    use_default_fastdds_profile()
    ros_args = []
    for rule in args.remap:
        if ":=" not in rule:
            raise ValueError(f"--remap needs FROM:=TO, got '{rule}'")
        ros_args += ["-r", rule]
    rclpy.init(args=["semcal", "--ros-args", *ros_args] if ros_args else ["semcal"])
    node = Node("semcal_replay")
    try:
        replay = BagReplay(node, params, log=lambda text: tqdm.write(text))
        total = None if params.loop else replay.message_count
        with tqdm(total=total, unit="msg", desc="replay") as bar:
            stats = replay.run(should_stop=lambda: not rclpy.ok(),
                               on_message=lambda topic, stamp: bar.update())
        replay.close()
        print(f"played {stats.messages} messages ({stats.bag_seconds:.1f} s of bag) in "
              f"{stats.wall_seconds:.1f} s")
        if stats.unacknowledged:
            print(f"warning: not acknowledged in time on {', '.join(stats.unacknowledged)}")
            return 1
        return 0
    finally:
        node.destroy_node()
        rclpy.try_shutdown()
