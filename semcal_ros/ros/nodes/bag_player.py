"""``bag_player``: replays a rosbag2 into the graph (parameters: ``config/bag_player.yaml``).

The node plays once (or loops) and exits when done, after reliable subscribers acknowledged the
last messages; ``semcal replay`` is the same engine behind a command line. Messages go out as
the bytes recorded, so image_transport's ``<topic>/compressed`` streams (CompressedImage) replay as
they were recorded, for nodes with ``image_transport: compressed`` (docs/deployment.md).
"""

from __future__ import annotations

import sys

from semcal_ros.ros.runtime import use_default_fastdds_profile


def main(args: list[str] | None = None) -> int:
    import rclpy
    from rclpy.node import Node

    from semcal_ros.ros.params import declare_and_read
    from semcal_ros.ros.replay import BagReplay, ReplayParams

    use_default_fastdds_profile()
    rclpy.init(args=sys.argv if args is None else args)
    node = Node("bag_player")
    code = 0
    try:
        params = declare_and_read(node, ReplayParams())
        replay = BagReplay(node, params)
        node.get_logger().info(
            f"playing {params.bag}: {replay.message_count} messages on {len(replay.publishers)} "
            f"topics, {replay.stats.bag_seconds:.1f} s at rate {params.rate}"
            + (" with /clock" if params.clock else "") + (", looping" if params.loop else ""))
        stats = replay.run(should_stop=lambda: not rclpy.ok())
        replay.close()
        node.get_logger().info(
            f"done: {stats.messages} messages in {stats.wall_seconds:.1f} s "
            f"({stats.loops} complete pass(es))")
        if stats.unacknowledged:
            node.get_logger().warning(
                f"not acknowledged in time on: {', '.join(stats.unacknowledged)}")
    except (ValueError, FileNotFoundError) as exc:
        print(f"bag_player: error: {exc}", file=sys.stderr)
        code = 1
    except KeyboardInterrupt:
        pass
    finally:
        node.destroy_node()
        rclpy.try_shutdown()
    return code


if __name__ == "__main__":
    sys.exit(main())
