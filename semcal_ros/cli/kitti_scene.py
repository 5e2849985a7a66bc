"""``semcal kitti-scene``: a KITTI odometry frame as a scene folder, the paper's real case.

Map from the labelled scans placed with the ground-truth poses, label image from a real
segmenter (``--model``/``--model-config``, e.g. an export of ``semcal export-model``), a given
PNG (``--labels``) or the frame's own lidar labels (``--truth-labels``), ground truth from P2
and Tr, and ``calibrator.yaml`` with the paper's KITTI settings. See docs/real-data.md.
"""

from __future__ import annotations

import argparse
from pathlib import Path


def register(subparsers: argparse._SubParsersAction) -> None:
    p = subparsers.add_parser(
        "kitti-scene", help="turn a KITTI odometry frame into a scene folder (real data)",
        description="Write a scene folder (map.ply, labels.png, image.png, camera_info.yaml, "
                    "ground_truth.yaml, initial.yaml, calibrator.yaml, scans/) for one frame of "
                    "a KITTI odometry sequence folder (velodyne/, labels/, image_2/, poses.txt, "
                    "calib.txt). Scans without SemanticKITTI labels are labelled from the "
                    "nearest labelled point within --label-distance; their other points are "
                    "dropped.")
    p.add_argument("--kitti", required=True, type=Path, help="KITTI odometry sequence folder")
    p.add_argument("--frame", type=int, default=0, help="camera frame (default 0)")
    p.add_argument("--scans", default="0-5", help="scans for the map, e.g. 0-5 or 0,1,2 "
                                                  "(default 0-5)")
    p.add_argument("--out", required=True, type=Path, help="scene folder to write")
    src = p.add_mutually_exclusive_group(required=True)
    src.add_argument("--model", type=Path, help="ONNX image segmenter for labels.png")
    src.add_argument("--labels", type=Path, help="use this label PNG (mono8 trainIds)")
    src.add_argument("--truth-labels", action="store_true",
                     help="labels.png from the frame's SemanticKITTI point labels projected "
                          "into the image (an ideal-label reference, not a segmenter)")
    p.add_argument("--model-config", type=Path, help="model config YAML of --model")
    p.add_argument("--threads", type=int, default=0, help="onnxruntime threads (0: all cores)")
    p.add_argument("--d-max", type=float,
                   help="drop points farther than this from the sensor, m (default: the map "
                        "builder's mapping.d_max)")
    p.add_argument("--voxel", type=float,
                   help="map voxel size, m (default: the map builder's mapping.voxel)")
    p.add_argument("--label-distance", type=float, default=0.3,
                   help="max distance to a labelled point for scans without labels, m "
                        "(default 0.3)")
    p.add_argument("--seed", type=int, default=0, help="seed of initial.yaml's perturbation")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    import numpy as np

    from semcal_ros.io import files, kitti
    from semcal_ros.cli.real_scene import map_defaults
    from semcal_ros.workflows.kitti_scene import parse_scans, projected_truth_labels, write_kitti_scene
    from semcal_ros.workflows.real_scene import MAP_DEFAULTS

    map_defaults(args, MAP_DEFAULTS)
    scans = parse_scans(args.scans)
    if args.model is not None and args.model_config is None:
        raise ValueError("--model needs --model-config")
    if args.model is None and args.model_config is not None:
        raise ValueError("--model-config is only used with --model")
    if args.label_distance <= 0:
        raise ValueError(f"--label-distance must be positive, got {args.label_distance}")
    segmenter = None
    if args.model is not None:  # load (and check) the model before any work
        from semcal_ros.segmentation.image import ImageSegmenter
        from semcal_ros.segmentation.onnx_runner import RunnerParams

        segmenter = ImageSegmenter.from_files(args.model, args.model_config,
                                              RunnerParams(threads=args.threads))

    def label_image(rgb: np.ndarray, image_path: str) -> tuple[np.ndarray, str]:
        if segmenter is not None:
            return segmenter.segment(rgb, "rgb8"), f"model {args.model}"
        if args.labels is not None:
            return files.read_label_image(args.labels), f"file {args.labels}"
        calib = kitti.read_calib(args.kitti / "calib.txt")
        camera, t_cam_lidar = kitti.camera_from_calib(calib, rgb.shape[1], rgb.shape[0])
        label_path = args.kitti / "labels" / f"{args.frame:06d}.label"
        scan = kitti.read_scan(args.kitti / "velodyne" / f"{args.frame:06d}.bin", label_path)
        return (projected_truth_labels(scan, t_cam_lidar, camera),
                f"projected SemanticKITTI labels of scan {args.frame}")

    report = write_kitti_scene(args.kitti, args.frame, scans, args.out, label_image,
                               d_max=args.d_max, voxel=args.voxel,
                               label_distance=args.label_distance, seed=args.seed)
    print(f"{args.out}: KITTI frame {args.frame}, scans {args.scans} -> map of "
          f"{report.map_points} points, labels from {report.labels_source}")
    print(f"  SemanticKITTI labels: scans {', '.join(map(str, report.labelled))}")
    for scan, share in report.transferred.items():
        print(f"  scan {scan}: no labels; labelled from the nearest labelled point within "
              f"{args.label_distance} m ({100 * share:.1f} % of its points), the rest dropped")
    frame_labels = args.kitti / "labels" / f"{args.frame:06d}.label"
    if not args.truth_labels and frame_labels.is_file():
        from semcal_ros.segmentation.agreement import label_agreement

        calib = kitti.read_calib(args.kitti / "calib.txt")
        scan = kitti.read_scan(args.kitti / "velodyne" / f"{args.frame:06d}.bin", frame_labels)
        labels = files.read_label_image(args.out / "labels.png")
        agreement = label_agreement(labels, scan.xyz, scan.label, calib["P2"] @ calib["Tr"])
        print("  labels.png vs projected SemanticKITTI labels of the frame's scan (road and "
              "sidewalk merged):\n    " + agreement.table().replace("\n", "\n    "))
    print(f"  {report.seconds:.1f} s; calibrate with: semcal calibrate --config "
          f"{args.out / 'calibrator.yaml'} --map {args.out / 'map.ply'} --labels "
          f"{args.out / 'labels.png'} --camera-info {args.out / 'camera_info.yaml'} --initial "
          f"{args.out / 'initial.yaml'} --output result.yaml")
    return 0
