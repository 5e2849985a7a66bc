"""``semcal export-pose``: a pose YAML as URDF, a static_transform_publisher line or matrices.

The core is :mod:`semcal_ros.export`; this module only parses the command line and writes the
text to stdout or ``--out``.
"""

from __future__ import annotations

import argparse


def register(subparsers: argparse._SubParsersAction) -> None:
    p = subparsers.add_parser(
        "export-pose", help="write a pose YAML as URDF, a static-tf line or 4x4 matrices",
        description="Export a pose YAML of docs/CONTRACTS.md (a result or a ground truth; parent "
                    "= frame_id, child = child_frame_id) in a form other ROS tools read: a URDF "
                    "fixed joint (fixed-axis roll, pitch, yaw), one `ros2 run tf2_ros "
                    "static_transform_publisher` line, or T_<parent>_<child> and its inverse.")
    p.add_argument("pose", metavar="POSE.yaml", help="the pose file")
    p.add_argument("--format", required=True, choices=("urdf", "static-tf", "matrix"),
                   help="urdf | static-tf | matrix")
    p.add_argument("--body-frame", metavar="NAME",
                   help="urdf only: the calibrated joint goes to this REP-103 body frame (x "
                        "forward, y left, z up), and a fixed joint rpy=-pi/2 0 -pi/2 (written as "
                        "plain numbers) to the optical child frame (e.g. camera_link)")
    p.add_argument("--out", metavar="FILE", help="write here instead of stdout")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from pathlib import Path

    from semcal_ros.export import export_pose, read_framed_pose

    text = export_pose(read_framed_pose(args.pose), args.format, args.body_frame)
    if args.out:
        out = Path(args.out)
        if out.parent and not out.parent.is_dir():
            raise FileNotFoundError(f"--out: folder not found: {out.parent}")
        out.write_text(text)
    else:
        print(text, end="")
    return 0
