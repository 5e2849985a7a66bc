"""``map_builder``: labelled lidar scans + poses -> the labelled map, published on ``map``.

Inputs (relative names, remap them): ``scan`` (PointCloud2 with x, y, z and a ``label`` field of
SemanticKITTI ids; unlabelled scans go through ``cloud_segmenter`` first), and the lidar's (or,
with ``lidar_extrinsic``, the vehicle's) pose in the map frame on ``odom`` (nav_msgs/Odometry) or
``pose`` (geometry_msgs/PoseStamped). A scan gets its pose by interpolating the pose stream at the
scan's stamp, so a scan waits (bounded queue) until a pose at or after its stamp has arrived.
A scan with a per-point time field (``t``, ``time``, ``timestamp``: Ouster, Velodyne, Livox
drivers) is de-skewed with the pose stream's motion around its stamp (``mapping.deskew.*``;
diagnostics value ``scans_deskewed``).

The work happens in a thread of its own, so a slow registration never blocks the subscriptions:
callbacks only check and enqueue. The worker, the scan queue, the work clock and the time-jump
rules are :class:`semcal_ros.workflows.live_map.LiveMap` (ROS-free); this node is its wiring.
The map (x, y, z, label) is published on ``map`` (transient local: a calibrator started later
still gets it) at most every ``publish_period`` seconds while it changes. Services:
``~/save_map`` (semcal_interfaces/SaveMap: PLY file) and ``~/reset`` (std_srvs/Trigger).

Time going back (a bag started over, a simulator reset) resets the map when
``reset_on_time_jump`` is set, but only when it is sustained: ``jump_confirm`` messages in a row
(scans or poses, in arrival order) each more than ``time_jump`` s older than the newest of its
own stream, or ``/clock`` going back by more than ``time_jump``. Fewer such messages are strays
(a late packet, a driver's bad stamp): they are dropped with a warning and the map stays. A reset
is a warning in the log and in the diagnostics (``resets``, ``last_reset``).
"""

from __future__ import annotations

import sys
from pathlib import Path
from typing import Any

from geometry_msgs.msg import PoseStamped
from nav_msgs.msg import Odometry
from rosgraph_msgs.msg import Clock
from rclpy.callback_groups import MutuallyExclusiveCallbackGroup
from rclpy.node import Node
from sensor_msgs.msg import PointCloud2
from std_srvs.srv import Trigger

from semcal_interfaces.srv import SaveMap
from semcal_ros.engine.cloud import LabelledCloud
from semcal_ros.ros import conversions as conv
from semcal_ros.ros import qos
from semcal_ros.ros.diagnostics import Diagnostics, Level
from semcal_ros.ros.params import declare_and_read
from semcal_ros.ros.runtime import run_node
from semcal_ros.workflows.live_map import LiveMap, LiveMapParams

#: The node's parameters (their home is the workflow; the name is the node's).
MapBuilderNodeParams = LiveMapParams


class MapBuilderNode(Node):
    def __init__(self) -> None:
        super().__init__("map_builder")
        self.opts = declare_and_read(self, MapBuilderNodeParams())
        self.frame = self.opts.map_frame
        self.map_pub = None  # created below; the worker starts after it
        self.live = LiveMap(
            self.opts, conv.pointcloud2_to_cloud, self._publish_map,
            self.get_logger().warning,
            f"'{self.resolve_topic_name('odom')}' or '{self.resolve_topic_name('pose')}'")

        overrides = qos.overridable()
        inputs = MutuallyExclusiveCallbackGroup()
        self.create_subscription(PointCloud2, "scan", self._on_scan, qos.sensor(10),
                                 callback_group=inputs, qos_overriding_options=overrides)
        self.create_subscription(Odometry, "odom", self._on_pose, qos.sensor(50),
                                 callback_group=inputs, qos_overriding_options=overrides)
        self.create_subscription(PoseStamped, "pose", self._on_pose, qos.sensor(50),
                                 callback_group=inputs, qos_overriding_options=overrides)
        self.create_subscription(Clock, "/clock", self._on_clock, qos.reliable(10),
                                 callback_group=inputs)
        self.map_pub = self.create_publisher(PointCloud2, "map", qos.latched(),
                                             qos_overriding_options=overrides)
        services = MutuallyExclusiveCallbackGroup()
        self.create_service(SaveMap, "~/save_map", self._on_save, callback_group=services)
        self.create_service(Trigger, "~/reset", self._on_reset, callback_group=services)
        self.diagnostics = Diagnostics(self, self._report, self.opts.diagnostics_period,
                                       callback_group=MutuallyExclusiveCallbackGroup())
        self.live.start()
        self.get_logger().info(
            f"ready: scans on '{self.resolve_topic_name('scan')}', poses on "
            f"'{self.resolve_topic_name('odom')}' / '{self.resolve_topic_name('pose')}', map on "
            f"'{self.resolve_topic_name('map')}' (voxel {self.opts.mapping.voxel} m, "
            f"ICP {'on' if self.opts.mapping.icp else 'off'})")

    def close(self) -> None:
        self.live.close()

    # --- callbacks: check and enqueue only ----------------------------------------------------
    def _on_scan(self, msg: PointCloud2) -> None:
        self.live.counts.received += 1
        try:  # the layout is checked here, the points are read by the worker
            names = conv.pointcloud2_dtype(msg).names or ()
            missing = [n for n in ("x", "y", "z") if n not in names]
            if missing:
                raise ValueError(f"PointCloud2 has no {', '.join(missing)} field "
                                 f"(fields: {', '.join(names) or 'none'})")
            if self.opts.require_labels and "label" not in names:
                raise ValueError(f"PointCloud2 has no 'label' field (fields: {', '.join(names)}"
                                 f"); run cloud_segmenter first or set require_labels false")
        except ValueError as exc:
            self.live.rejected("fields", f"scan ignored: {exc}")
            return
        self.live.arrive("scan", conv.stamp_to_seconds(msg.header.stamp), msg)

    def _on_pose(self, msg: Any) -> None:
        try:
            stamp, pose, frame = conv.stamped_pose(msg)
        except ValueError as exc:
            self.live.rejected("pose", f"pose ignored: {exc}")
            return
        if not self.frame:
            self.frame = frame or "map"
        self.live.arrive("pose", stamp, pose)

    def _on_clock(self, msg: Clock) -> None:
        self.live.clock(conv.stamp_to_seconds(msg.clock))

    def _publish_map(self, cloud: LabelledCloud) -> None:
        header = conv.make_header(self.frame or "map", self.get_clock().now().to_msg())
        self.map_pub.publish(conv.cloud_to_pointcloud2(cloud, header, extra_fields=False))

    # --- services -----------------------------------------------------------------------------
    def _on_save(self, request: SaveMap.Request, response: SaveMap.Response) -> SaveMap.Response:
        from semcal_ros.io.ply import write_ply

        path = Path(request.path or self.opts.save_path).expanduser().resolve()
        try:
            cloud = self.live.snapshot(finish=request.finish)
            write_ply(path, cloud)
        except (OSError, ValueError) as exc:
            response.success, response.message = False, f"could not save the map: {exc}"
            return response
        if request.finish:
            self.live.mark_changed()
        response.success, response.path, response.points = True, str(path), len(cloud)
        response.message = f"saved {len(cloud)} points to {path}"
        self.get_logger().info(response.message)
        return response

    def _on_reset(self, request: Trigger.Request, response: Trigger.Response
                  ) -> Trigger.Response:
        dropped = self.live.reset()
        response.success = True
        response.message = f"map reset ({dropped} queued scans dropped)"
        self.get_logger().info(response.message)
        return response

    def _report(self) -> tuple[Level, str, dict[str, Any]]:
        status = self.live.status()
        return Level.WARN if status.warn else Level.OK, status.message, status.values


def main(args: list[str] | None = None) -> int:
    return run_node(MapBuilderNode, threads=3, args=args)


if __name__ == "__main__":
    sys.exit(main())
