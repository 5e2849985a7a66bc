"""``semcal real-scene``: a real recording (image, lidar scans, calibration) as a scene folder.

The generic form is a contract other tools call (issue 17)::

    semcal real-scene --image IMG --scans SCAN [SCAN ...] --camera-info CAMERA_INFO.yaml
        [--extrinsic T.yaml] [--poses POSES.yaml]
        --cloud-labels geometric|semantickitti|FILE
        (--model M.onnx --model-config M.yaml | --labels L.png) --out SCENE

``--calib FILE [FILE ...]`` replaces ``--camera-info`` and ``--extrinsic`` with the recording's
own calibration files (KITTI odometry calib.txt, KITTI object calib, PJLab calib.txt or its two
JSON files). ``--truth-labels`` writes the ideal label image (the first scan's point labels
projected through the true extrinsic). See docs/real-data.md.
"""

from __future__ import annotations

import argparse
from pathlib import Path


def register(subparsers: argparse._SubParsersAction) -> None:
    p = subparsers.add_parser(
        "real-scene", help="turn a real camera image + lidar scans into a scene folder",
        description="Write a scene folder (map.ply, labels.png, image.png, camera_info.yaml, "
                    "ground_truth.yaml when the extrinsic is known, initial.yaml, "
                    "calibrator.yaml, scene.yaml, scans/) from one camera image and lidar scans "
                    "in the lidar frame. The map frame is the first scan's lidar frame.")
    p.add_argument("--image", required=True, type=Path, help="camera image (.png, .jpg)")
    p.add_argument("--scans", required=True, type=Path, nargs="+", metavar="SCAN",
                   help="lidar scans in the lidar frame: KITTI .bin, .pcd (ascii, binary, "
                        "binary_compressed) or .ply; the first one is the camera's")
    p.add_argument("--camera-info", type=Path,
                   help="camera_info YAML (camera_calibration_parsers format)")
    p.add_argument("--extrinsic", type=Path,
                   help="YAML with T_cam_lidar (4x4: first scan's lidar frame -> camera "
                        "optical frame), the true extrinsic: ground_truth.yaml is written")
    p.add_argument("--calib", type=Path, nargs="+", metavar="FILE",
                   help="the recording's calibration file(s) instead of --camera-info and "
                        "--extrinsic: KITTI odometry calib.txt (P2, Tr), KITTI object calib "
                        "(P2, R0_rect, Tr_velo_to_cam), K/D/T calib.txt, or the "
                        "SensorsCalibration intrinsic + extrinsic .json pair")
    p.add_argument("--calib-projection", default="P2",
                   help="projection matrix of a KITTI calib to use (default P2: left colour)")
    p.add_argument("--ignore-calib-size", action="store_true",
                   help="use --calib intrinsics although they state another image size than "
                        "the image's (check the overlay)")
    p.add_argument("--poses", type=Path,
                   help="poses of the scans: a scans/poses.yaml-format file (entries matched "
                        "by file name) or a KITTI poses.txt (rows by scan number; needs a KITTI "
                        "--calib for Tr); needed with more than one scan")
    p.add_argument("--initial", type=Path,
                   help="initial pose YAML (default: the truth perturbed by up to 1 m / 2 deg, "
                        "--seed)")
    p.add_argument("--cloud-labels", required=True, nargs="+", metavar="MODE_OR_FILE",
                   help="point labels: geometric (the geometric labeller), semantickitti "
                        "(SEQ/labels/NNNNNN.label beside each SEQ/velodyne/NNNNNN.bin; scans "
                        "without one take the nearest labelled point's label), or one file per "
                        "scan (.label or labelled .ply)")
    src = p.add_mutually_exclusive_group(required=True)
    src.add_argument("--model", type=Path, help="ONNX image segmenter for labels.png")
    src.add_argument("--labels", type=Path, help="use this label PNG (mono8 trainIds)")
    src.add_argument("--truth-labels", action="store_true",
                     help="labels.png from the first scan's point labels projected through the "
                          "true extrinsic (the ideal-label reference, not a segmenter)")
    p.add_argument("--model-config", type=Path, help="model config YAML of --model")
    p.add_argument("--probabilities", action="store_true",
                   help="with --model: also write the class probabilities as "
                        "SCENE/probabilities.npz (float16 H x W x 19, trainIds 0-18)")
    p.add_argument("--out", required=True, type=Path, help="scene folder to write")
    p.add_argument("--remove-vehicles", action="store_true",
                   help="remove every vehicle from the map (default: parked ones stay and "
                        "count, moving ones go)")
    p.add_argument("--keep-sidewalk", action="store_true",
                   help="do not merge sidewalk into road in calibrator.yaml")
    p.add_argument("--d-max", type=float,
                   help="drop points farther than this from the sensor, m (default: the map "
                        "builder's mapping.d_max)")
    p.add_argument("--voxel", type=float,
                   help="map voxel size, m (default: the map builder's mapping.voxel)")
    p.add_argument("--label-distance", type=float, default=0.3,
                   help="semantickitti: max distance to a labelled point for scans without "
                        "labels, m (default 0.3)")
    p.add_argument("--crop-margin-deg", type=float, default=5.0,
                   help="loss.crop_top keeps this much pitch above the map's top row seen from "
                        "the initial pose (default 5: the search's pitch bound)")
    p.add_argument("--crop-radius", type=float, default=0.0,
                   help="> 0: render.crop_radius (m) in calibrator.yaml")
    p.add_argument("--seed", type=int, default=0, help="seed of initial.yaml's perturbation")
    p.add_argument("--threads", type=int, default=0, help="onnxruntime threads (0: all cores)")
    p.add_argument("--overlay", action="store_true",
                   help="also write overlay.png: the map rendered at the true pose over the "
                        "image (checks the extrinsic convention: points on poles, cars, kerbs)")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from semcal_ros.workflows.real_scene import MAP_DEFAULTS, RealSceneOptions, write_real_scene

    map_defaults(args, MAP_DEFAULTS)
    if args.model is not None and args.model_config is None:
        raise ValueError("--model needs --model-config")
    if args.model is None and args.model_config is not None:
        raise ValueError("--model-config is only used with --model")
    if args.probabilities and args.model is None:
        raise ValueError("--probabilities needs --model (labels from a file or the truth have "
                         "no class probabilities)")
    for name in ("d_max", "voxel", "label_distance"):
        if not getattr(args, name) > 0:
            raise ValueError(f"--{name.replace('_', '-')} must be positive, got "
                             f"{getattr(args, name)}")
    inputs = gather_inputs(args)
    label_image = label_image_source(args, inputs)
    options = RealSceneOptions(d_max=args.d_max, voxel=args.voxel,
                               remove_vehicles=args.remove_vehicles,
                               merge_road_sidewalk=not args.keep_sidewalk,
                               crop_margin_deg=args.crop_margin_deg,
                               crop_radius=args.crop_radius, seed=args.seed)
    report = write_real_scene(inputs, args.out, label_image, options)
    print_report(args.out, inputs, report)
    if args.overlay:
        if not (args.out / "ground_truth.yaml").is_file():
            raise ValueError("--overlay needs the true extrinsic (--extrinsic or --calib)")
        write_truth_overlay(args.out)
        print(f"  overlay at the true pose: {args.out / 'overlay.png'}")
    return 0


def map_defaults(args: argparse.Namespace, defaults) -> None:
    """``--d-max`` / ``--voxel`` not given: the map builder's (one source for both commands)."""
    for name in ("d_max", "voxel"):
        if getattr(args, name) is None:
            setattr(args, name, getattr(defaults, name))


def write_truth_overlay(scene: Path, out: Path | None = None) -> Path:
    """The scene's map rendered at its ground truth over its image, with the scene's own
    calibrator.yaml label settings (merge, parked vehicles)."""
    from semcal_ros.io import files, ply
    from semcal_ros.engine.overlay import render_overlay
    from semcal_ros.engine.params import CalibrationParams
    from semcal_ros.engine.problem import mapping_for

    params = CalibrationParams.from_file(scene / "calibrator.yaml")
    picture = render_overlay(ply.read_ply(scene / "map.ply"),
                             files.read_camera_info(scene / "camera_info.yaml"),
                             files.read_pose(scene / "ground_truth.yaml"),
                             files.read_rgb_image(scene / "image.png"),
                             mapping_for(params), params.render)
    out = out or scene / "overlay.png"
    files.write_rgb_image(out, picture)
    return out


def gather_inputs(args: argparse.Namespace):
    """Read and check every input (image, camera, extrinsic, scans, poses, point labels)."""
    from semcal_ros.io import files, kitti
    from semcal_ros.io.calibration_files import read_calibration, read_extrinsic_yaml
    from semcal_ros.io.lidar_scans import read_lidar_scan, scan_poses_in_map
    from semcal_ros.segmentation.labellers import MODEL_FREE
    from semcal_ros.workflows.real_scene import RealSceneInputs
    from semcal_ros.workflows.scene_labels import label_scans

    if args.calib and (args.camera_info or args.extrinsic):
        raise ValueError("--calib replaces --camera-info and --extrinsic: give one or the other")
    if not args.calib and args.camera_info is None:
        raise ValueError("the camera is needed: give --camera-info (or --calib)")
    rgb = files.read_rgb_image(args.image)
    height, width = rgb.shape[:2]
    kitti_tr = None
    if args.calib:
        source = read_calibration(args.calib, args.calib_projection)
        if args.ignore_calib_size:
            from dataclasses import replace

            source = replace(source, size=None)
        camera = source.camera(width, height, source.description)
        t_cam_lidar = source.t_cam_lidar
        for path in args.calib:  # KITTI poses.txt are camera poses: they need Tr
            if path.suffix.lower() == ".txt" and "Tr:" in path.read_text(errors="replace"):
                kitti_tr = kitti.read_calib(path)["Tr"]
    else:
        camera = files.read_camera_info(args.camera_info)
        if (camera.width, camera.height) != (width, height):
            raise ValueError(f"{args.camera_info}: camera_info is {camera.width}x"
                             f"{camera.height}, the image {args.image} is {width}x{height}")
        t_cam_lidar = read_extrinsic_yaml(args.extrinsic) if args.extrinsic else None
    if args.truth_labels and t_cam_lidar is None:
        raise ValueError("--truth-labels needs the true extrinsic (--extrinsic or --calib)")
    initial = files.read_pose(args.initial) if args.initial else None
    if t_cam_lidar is None and initial is None:
        raise ValueError("without the extrinsic (--extrinsic / --calib) an --initial pose is "
                         "needed")
    for path in args.scans:  # formats first: a wrong file fails before any reading
        if path.suffix.lower() not in (".bin", ".pcd", ".ply"):
            raise ValueError(f"{path}: unknown scan format '{path.suffix}' (expected .bin, "
                             ".pcd or .ply)")
        if not path.is_file():
            raise FileNotFoundError(f"scan not found: {path}")
    poses = scan_poses_in_map(list(args.scans), args.poses, kitti_tr)
    clouds = [read_lidar_scan(p) for p in args.scans]
    clouds, described, notes = label_scans(list(args.scans), clouds, list(args.cloud_labels),
                                           poses, args.label_distance)
    labeller = args.cloud_labels[0] if list(args.cloud_labels) in ([m] for m in MODEL_FREE) \
        else None
    return RealSceneInputs(rgb, camera, clouds, [str(p) for p in args.scans], poses,
                           [0.1 * i for i in range(len(clouds))], t_cam_lidar, initial,
                           described, notes, labeller=labeller)


def label_image_source(args: argparse.Namespace, inputs):
    """``label_image(rgb) -> (labels, description)`` for the chosen source; a model is loaded
    (and checked) here, before any work."""
    from semcal_ros.io import files
    from semcal_ros.workflows.scene_labels import projected_truth_labels

    if args.model is not None:
        from semcal_ros.segmentation.image import ImageSegmenter
        from semcal_ros.segmentation.onnx_runner import RunnerParams

        segmenter = ImageSegmenter.from_files(args.model, args.model_config,
                                              RunnerParams(threads=args.threads))
        if args.probabilities:
            def with_probabilities(rgb):
                labels, probabilities = segmenter.segment_with_probabilities(rgb, "rgb8")
                return labels, f"model {args.model}", probabilities
            return with_probabilities
        return lambda rgb: (segmenter.segment(rgb, "rgb8"), f"model {args.model}")
    if args.labels is not None:
        labels = files.read_label_image(args.labels)
        return lambda rgb: (labels, f"file {args.labels}")
    first = inputs.scans[0]
    return lambda rgb: (projected_truth_labels(first, inputs.t_cam_lidar, inputs.camera),
                        f"first scan's point labels ({inputs.cloud_labels}) projected through "
                        "the true extrinsic")


def print_report(out: Path, inputs, report) -> None:
    """What was written, the label shares and the command to calibrate it."""
    def shares(d: dict[str, float], n: int = 8) -> str:
        items = list(d.items())
        text = ", ".join(f"{k} {100 * v:.1f} %" for k, v in items[:n])
        return text + (f", {len(items) - n} more" if len(items) > n else "")

    print(f"{out}: {len(inputs.scans)} scan(s), {sum(report.scan_points)} points -> map of "
          f"{report.map_points} points; point labels: {inputs.cloud_labels}; image labels: "
          f"{report.labels_source}")
    for note in inputs.label_notes:
        print(f"  {note}")
    if any(report.moved_vehicles):
        print(f"  vehicles that moved between scans (removed): {report.moved_vehicles} "
              "clusters per scan")
    removed = ("all vehicles" if "parked_vehicles" not in report.engine.get("labels", {})
               else "moving classes")
    print(f"  removed from the map: {report.removed_points} points ({removed})")
    print(f"  map label shares: {shares(report.map_shares)}")
    print(f"  image label shares (labelled pixels): {shares(report.image_shares)}")
    print(f"  calibrator.yaml engine: {report.engine}")
    print(f"  {report.seconds:.1f} s; calibrate with: semcal calibrate --config "
          f"{out / 'calibrator.yaml'} --map {out / 'map.ply'} --labels {out / 'labels.png'} "
          f"--camera-info {out / 'camera_info.yaml'} --initial {out / 'initial.yaml'} "
          f"--output result.yaml")
