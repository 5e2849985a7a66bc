"""``semcal real-scene``: a real recording (image, lidar scans, calibration) as a scene folder.

The generic form is a contract other tools call (issue 17)::

    semcal real-scene --image IMG --scans SCAN [SCAN ...] --camera-info CAMERA_INFO.yaml
        [--extrinsic T.yaml] [--poses POSES.yaml]
        --cloud-labels geometric|semantickitti|FILE
        (--model M.onnx --model-config M.yaml | --labels L.png) --out SCENE

Several frames of one rig (a vehicle's camera and lidar: one extrinsic) in one call::

    semcal real-scene --image A.png B.png ... --scans SCAN_A1 [SCAN_A2 ...] SCAN_B1 [...] ...
        ... --out DIR

With N > 1 images, ``--scans`` holds N equal consecutive groups in image order (K =
len(scans) / N scans each; refused when not divisible); group k's first scan is image k's (the
camera's) scan and its map is built from its group in that scan's lidar frame (``--poses`` as
for one image when K > 1). ``--labels`` then takes N PNGs and ``--cloud-labels`` files (not a
mode) one per scan, in the same order. ``--out DIR`` gets one scene folder per image,
``DIR/<image file stem>/`` (duplicate stems are refused), each exactly as the one-image form
writes it, all with ONE ``initial.yaml`` pose (``--initial``, or the same ``--seed``
perturbation of the same truth: every frame of a rig shares the extrinsic), and
``DIR/frames.txt`` listing the folder names in image order, one a line. With ``--model`` the
network is loaded once. The one-image form writes into ``--out`` itself, as before. The end of
the output is the ``semcal calibrate --scene ...`` line that calibrates the frames together.

``--calib FILE [FILE ...]`` replaces ``--camera-info`` and ``--extrinsic`` with the recording's
own calibration files (KITTI odometry calib.txt, KITTI object calib, PJLab calib.txt or its two
JSON files). ``--truth-labels`` writes the ideal label image (the first scan's point labels
projected through the true extrinsic). See docs/real-data.md.
"""

from __future__ import annotations

import argparse
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

if TYPE_CHECKING:  # the labeller loads numba: imported when a scan is labelled
    from semcal_ros.segmentation.geometric import GeometricParams


def register(subparsers: argparse._SubParsersAction) -> None:
    p = subparsers.add_parser(
        "real-scene", help="turn a real camera image + lidar scans into a scene folder",
        description="Write a scene folder (map.ply, labels.png, image.png, camera_info.yaml, "
                    "ground_truth.yaml when the extrinsic is known, initial.yaml, "
                    "calibrator.yaml, scene.yaml, scans/) from one camera image and lidar scans "
                    "in the lidar frame. The map frame is the first scan's lidar frame. "
                    "Several images (frames of one rig): --scans holds one equal group of "
                    "scans per image, in image order (the group's first scan is the image's); "
                    "--out DIR gets DIR/<image stem>/ per image, all with one initial.yaml, and "
                    "DIR/frames.txt.")
    p.add_argument("--image", required=True, type=Path, nargs="+", metavar="IMG",
                   help="camera image (.png, .jpg); several: frames of one rig, one scene "
                        "folder each (DIR/<image file stem>/ under --out)")
    p.add_argument("--scans", required=True, type=Path, nargs="+", metavar="SCAN",
                   help="lidar scans in the lidar frame: KITTI .bin, .pcd (ascii, binary, "
                        "binary_compressed) or .ply; the first one is the camera's. With N "
                        "images: N equal consecutive groups in image order (K = len/N scans "
                        "each), each group's first scan the image's")
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
                        "--calib for Tr); without it several scans are registered to each "
                        "other by ICP, the first held fixed")
    p.add_argument("--initial", type=Path,
                   help="initial pose YAML (default: the truth perturbed by up to 1 m / 2 deg, "
                        "--seed)")
    p.add_argument("--cloud-labels", required=True, nargs="+", metavar="MODE_OR_FILE",
                   help="point labels: geometric (the geometric labeller), semantickitti "
                        "(SEQ/labels/NNNNNN.label beside each SEQ/velodyne/NNNNNN.bin; scans "
                        "without one take the nearest labelled point's label), or one file per "
                        "scan (.label or labelled .ply; with several images: one per scan of "
                        "every group, in --scans order)")
    src = p.add_mutually_exclusive_group(required=True)
    src.add_argument("--model", type=Path, help="ONNX image segmenter for labels.png")
    src.add_argument("--labels", type=Path, nargs="+", metavar="PNG",
                     help="use this label PNG (mono8 trainIds); with several images one per "
                          "image, in image order")
    src.add_argument("--truth-labels", action="store_true",
                     help="labels.png from the first scan's point labels projected through the "
                          "true extrinsic (the ideal-label reference, not a segmenter)")
    p.add_argument("--model-config", type=Path, help="model config YAML of --model")
    p.add_argument("--probabilities", action="store_true",
                   help="with --model: also write the class probabilities as "
                        "SCENE/probabilities.npz (float16 H x W x 19, trainIds 0-18)")
    p.add_argument("--out", required=True, type=Path,
                   help="scene folder to write; with several images the folder that gets "
                        "one scene folder per image (DIR/<image stem>/) and frames.txt")
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
    p.add_argument("--cloud-config", type=Path, default=None, metavar="YAML",
                   help="with --cloud-labels geometric: the labeller's parameters from this "
                        "cloud_segmenter params file (e.g. config/cloud_segmenter_sparse.yaml "
                        "for a lidar whose rings lie 1 deg apart or more)")
    p.add_argument("--label-distance", type=float, default=0.3,
                   help="semantickitti: max distance to a labelled point for scans without "
                        "labels, m (default 0.3)")
    p.add_argument("--crop-margin-deg", type=float, default=5.0,
                   help="loss.crop_top keeps this much pitch above the map's top row seen from "
                        "the initial pose (default 5: the search's pitch bound)")
    p.add_argument("--crop-radius", type=float, default=0.0,
                   help="> 0: render.crop_radius (m) in calibrator.yaml")
    p.add_argument("--blind-rows", type=float, default=None, metavar="SHARE",
                   help="loss.blind_rows in calibrator.yaml (0: none). Default: from the data, "
                        "0.2 where the lidar's near ground rings ahead of the camera lie more "
                        "than 2 deg apart (a top-mounted lidar such as PJLab's), else none "
                        "(docs/engine.md 'The lidar's blind zone')")
    p.add_argument("--seed", type=int, default=0,
                   help="seed of initial.yaml's perturbation (one pose for every frame)")
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
    if args.blind_rows is not None and not 0.0 <= args.blind_rows <= 0.5:
        raise ValueError(f"--blind-rows must be in [0, 0.5], got {args.blind_rows}")
    plans = plan_frames(args)  # every count and name checked before any reading
    geometric = geometric_params(args)  # read and checked once, for every frame
    segment = load_segmenter(args)  # the network, once for every frame
    options = RealSceneOptions(d_max=args.d_max, voxel=args.voxel,
                               remove_vehicles=args.remove_vehicles,
                               merge_road_sidewalk=not args.keep_sidewalk,
                               crop_margin_deg=args.crop_margin_deg,
                               crop_radius=args.crop_radius, blind_rows=args.blind_rows,
                               seed=args.seed)
    rig = len(plans) > 1
    shared_initial = None  # several frames: the first frame's initial pose, for every frame
    for k, plan in enumerate(plans):
        if rig:
            print(f"frame {k + 1}/{len(plans)}: {plan.image} with {len(plan.scans)} scan(s) -> "
                  f"{plan.out}", flush=True)
        inputs = gather_inputs(args, plan, geometric)
        if rig:
            if shared_initial is None:
                shared_initial = (inputs.initial if inputs.initial is not None
                                  else _perturbed_truth(inputs, args.seed))
            inputs.initial = shared_initial
        label_image = label_image_source(args, inputs, plan, segment)
        report = write_real_scene(inputs, plan.out, label_image, options)
        print_report(plan.out, inputs, report, command=not rig)
        if args.overlay:
            if not (plan.out / "ground_truth.yaml").is_file():
                raise ValueError("--overlay needs the true extrinsic (--extrinsic or --calib)")
            write_truth_overlay(plan.out)
            print(f"  overlay at the true pose: {plan.out / 'overlay.png'}")
        del inputs, label_image  # one frame's scans held at a time
    if rig:
        names = [plan.out.name for plan in plans]
        (args.out / "frames.txt").write_text("".join(f"{n}\n" for n in names))
        print(f"{len(plans)} frames of one rig in {args.out} (frames.txt); calibrate them "
              f"together with: semcal calibrate --scene "
              f"{' '.join(str(plan.out) for plan in plans)} "
              f"--initial {plans[0].out / 'initial.yaml'} --output result.yaml")
    return 0


@dataclass(frozen=True)
class FramePlan:
    """One image's share of the arguments: its scans, point label files, label PNG and folder."""

    image: Path
    scans: list[Path]
    cloud_labels: list[str]
    labels: Path | None
    out: Path


def geometric_params(args: argparse.Namespace) -> GeometricParams | None:
    """``--cloud-config``'s labeller parameters (None without it: the labeller's defaults)."""
    if args.cloud_config is None:
        return None
    if list(args.cloud_labels) != ["geometric"]:
        raise ValueError("--cloud-config configures the geometric labeller: it needs "
                         "--cloud-labels geometric")
    from semcal_ros.segmentation.geometric import params_from_file

    return params_from_file(args.cloud_config)


def plan_frames(args: argparse.Namespace) -> list[FramePlan]:
    """One plan per ``--image``: one image writes into ``--out`` as ever; N images split
    ``--scans`` (and per-scan ``--cloud-labels`` files, ``--labels``) into N equal groups in
    image order and write ``--out/<image stem>/`` each. Checked before anything is read."""
    from semcal_ros.segmentation.labellers import MODEL_FREE

    images, scans = list(args.image), list(args.scans)
    cloud_labels = [str(c) for c in args.cloud_labels]
    labels = list(args.labels) if args.labels is not None else None
    n = len(images)
    if labels is not None and len(labels) != n:
        raise ValueError(f"--labels: {len(labels)} label image(s) for {n} camera image(s): give "
                         "one per image, in image order")
    if n == 1:
        return [FramePlan(images[0], scans, cloud_labels, labels[0] if labels else None,
                          args.out)]
    if len(scans) % n:
        raise ValueError(f"--scans: {len(scans)} scans do not split into {n} equal groups (one "
                         f"per --image, the image's scan first)")
    stems = [im.stem for im in images]
    repeated = sorted({s for s in stems if stems.count(s) > 1})
    if repeated:
        raise ValueError(f"--image: several images named {', '.join(repeated)}: each frame's "
                         "folder is --out/<image file stem>, the stems must differ")
    missing = [str(p) for p in [*images, *scans, *(labels or [])] if not p.is_file()]
    if missing:  # before the first frame is written, not after
        raise FileNotFoundError(f"not found: {', '.join(missing)}")
    k = len(scans) // n
    per_scan_files = not (cloud_labels in ([m] for m in MODEL_FREE)
                          or cloud_labels == ["semantickitti"])
    if per_scan_files and len(cloud_labels) != len(scans):
        raise ValueError(f"--cloud-labels: {len(cloud_labels)} label file(s) for {len(scans)} "
                         "scans (one per scan, in --scans order)")
    return [FramePlan(images[i], scans[i * k:(i + 1) * k],
                      cloud_labels[i * k:(i + 1) * k] if per_scan_files else cloud_labels,
                      labels[i] if labels else None, args.out / stems[i])
            for i in range(n)]


def _perturbed_truth(inputs, seed: int):
    """The initial pose one frame would draw on its own (the truth perturbed with ``seed``), so
    a rig's shared pose is what every frame would draw anyway."""
    import numpy as np

    from semcal_ros.engine.pose import Pose, perturbed_initial

    m = np.linalg.inv(inputs.t_cam_lidar)
    return perturbed_initial(Pose.from_matrix(m[:3, :3], m[:3, 3]), np.random.default_rng(seed))


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


def gather_inputs(args: argparse.Namespace, plan: FramePlan,
                  geometric: GeometricParams | None = None):
    """Read and check every input of one frame (image, camera, extrinsic, scans, poses, point
    labels; ``geometric``: the geometric labeller's parameters, None for its defaults)."""
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
    rgb = files.read_rgb_image(plan.image)
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
                             f"{camera.height}, the image {plan.image} is {width}x{height}")
        t_cam_lidar = read_extrinsic_yaml(args.extrinsic) if args.extrinsic else None
    if args.truth_labels and t_cam_lidar is None:
        raise ValueError("--truth-labels needs the true extrinsic (--extrinsic or --calib)")
    initial = files.read_pose(args.initial) if args.initial else None
    if t_cam_lidar is None and initial is None:
        raise ValueError("without the extrinsic (--extrinsic / --calib) an --initial pose is "
                         "needed")
    for path in plan.scans:  # formats first: a wrong file fails before any reading
        if path.suffix.lower() not in (".bin", ".pcd", ".ply"):
            raise ValueError(f"{path}: unknown scan format '{path.suffix}' (expected .bin, "
                             ".pcd or .ply)")
        if not path.is_file():
            raise FileNotFoundError(f"scan not found: {path}")
    poses = scan_poses_in_map(list(plan.scans), args.poses, kitti_tr)
    clouds = [read_lidar_scan(p) for p in plan.scans]
    registered = []
    if poses is None:  # several scans, no poses: registered to each other, the first fixed
        import numpy as np

        from semcal_ros.mapping.odometry import scan_odometry

        poses = scan_odometry([c.xyz for c in clouds])
        registered = [f"{len(clouds)} scans without poses: registered scan to scan (ICP), "
                      f"{np.linalg.norm(poses[-1][:3, 3]):.2f} m from the first to the last"]
    clouds, described, notes = label_scans(list(plan.scans), clouds, list(plan.cloud_labels),
                                           poses, args.label_distance, geometric)
    notes = registered + list(notes)
    labeller = plan.cloud_labels[0] if list(plan.cloud_labels) in ([m] for m in MODEL_FREE) \
        else None
    return RealSceneInputs(rgb, camera, clouds, [str(p) for p in plan.scans], poses,
                           [0.1 * i for i in range(len(clouds))], t_cam_lidar, initial,
                           described, notes, labeller=labeller)


def load_segmenter(args: argparse.Namespace):
    """With ``--model``: the network loaded (and checked) once, before any work, as
    ``segment(rgb) -> (labels, description[, probabilities])``; else None."""
    if args.model is None:
        return None
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


def label_image_source(args: argparse.Namespace, inputs, plan: FramePlan, segment=None):
    """``label_image(rgb) -> (labels, description)`` of one frame for the chosen source: the
    loaded network (:func:`load_segmenter`), the frame's label PNG, or its truth labels."""
    from semcal_ros.io import files
    from semcal_ros.workflows.scene_labels import projected_truth_labels

    if segment is not None:
        return segment
    if plan.labels is not None:
        labels = files.read_label_image(plan.labels)
        return lambda rgb: (labels, f"file {plan.labels}")
    first = inputs.scans[0]
    return lambda rgb: (projected_truth_labels(first, inputs.t_cam_lidar, inputs.camera),
                        f"first scan's point labels ({inputs.cloud_labels}) projected through "
                        "the true extrinsic")


def print_report(out: Path, inputs, report, command: bool = True) -> None:
    """What was written, the label shares and (``command``) the command to calibrate it."""
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
    blind = report.engine.get("loss", {}).get("blind_rows", 0.0)
    print(f"  near ground rings ahead: at most {report.ground_gap_deg:.1f} deg apart"
          + (f" -> loss.blind_rows {blind:g}" if blind else ""))
    print(f"  calibrator.yaml engine: {report.engine}")
    if not command:
        print(f"  {report.seconds:.1f} s")
        return
    print(f"  {report.seconds:.1f} s; calibrate with: semcal calibrate --config "
          f"{out / 'calibrator.yaml'} --map {out / 'map.ply'} --labels {out / 'labels.png'} "
          f"--camera-info {out / 'camera_info.yaml'} --initial {out / 'initial.yaml'} "
          f"--output result.yaml")
