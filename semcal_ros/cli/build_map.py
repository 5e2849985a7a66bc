"""``semcal build-map``: scans and poses into the engine's labelled map (``map.ply``).

Input is a scene folder (``scans/NNNNNN.ply`` + ``scans/poses.yaml``) or a KITTI odometry
sequence (``velodyne/*.bin``, ``labels/*.label``, ``poses.txt``, ``calib.txt``). Scans are read
one at a time while the builder registers groups as they fill, so memory follows the map, not
the number of scans.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path


def register(subparsers: argparse._SubParsersAction) -> None:
    parser = subparsers.add_parser(
        "build-map", help="build a labelled map from lidar scans and poses (grouped multiway ICP)",
        description="Drop far points, register groups of three neighbouring scans with multiway "
                    "ICP recursively until one cloud remains (voxel-downsampled at every level, "
                    "majority label per voxel), remove dynamic classes, crop, and write map.ply.")
    parser.add_argument("input", type=Path, metavar="INPUT",
                        help="scene folder (scans/poses.yaml) or KITTI odometry sequence folder")
    parser.add_argument("-o", "--output", type=Path, default=None,
                        help="map PLY to write (default INPUT/map.ply; an existing file needs "
                             "--force)")
    parser.add_argument("--force", action="store_true", help="overwrite an existing output file")
    parser.add_argument("--config", type=Path, default=None,
                        help="ROS 2 parameter file of the map_builder node; its mapping.* "
                             "group is used (flags win)")
    parser.add_argument("--d-max", type=float, default=None,
                        help="drop points farther than this from the sensor, m (default 60)")
    parser.add_argument("--voxel", type=float, default=None,
                        help="map voxel size at every level, m (default 0.1)")
    parser.add_argument("--no-icp", action="store_true",
                        help="accumulate with the given poses only (no registration)")
    parser.add_argument("--pose-noise", type=float, nargs=2, default=None,
                        metavar=("TRANS_M", "ROT_DEG"),
                        help="for experiments: move every pose by TRANS_M and turn it by ROT_DEG "
                             "(random directions, --seed) before building")
    parser.add_argument("--seed", type=int, default=0, help="seed of --pose-noise (default 0)")
    parser.add_argument("--crop-radius", type=float, default=None,
                        help="keep points within this horizontal radius of --crop-center, m")
    parser.add_argument("--crop-center", type=float, nargs=3, default=None,
                        metavar=("X", "Y", "Z"),
                        help="crop centre in the map frame (default for a scene folder: the "
                             "translation in initial.yaml)")
    parser.add_argument("--corridor", type=float, default=None,
                        help="remove dynamic classes only within this distance of the vehicle "
                             "path, m (keeps parked cars; default: everywhere)")
    parser.add_argument("--keep-dynamic", action="store_true",
                        help="do not remove dynamic classes at all")
    parser.add_argument("--first", type=int, default=0, help="index of the first scan to use")
    parser.add_argument("--count", type=int, default=0,
                        help="number of scans to use (default: all from --first)")
    parser.add_argument("--write-poses", type=Path, default=None,
                        help="also write the refined lidar poses (scans/poses.yaml format)")
    parser.add_argument("--kitti-frame", choices=("lidar0", "cam0"), default="lidar0",
                        help="KITTI map frame: lidar of scan 0 (z up, default) or cam0 of "
                             "frame 0 (the frame of poses.txt)")
    parser.set_defaults(func=run)


def _params(args: argparse.Namespace, crop_center_default):
    from semcal_ros.engine.config import apply_flat, load_node_group
    from semcal_ros.mapping import MapBuildParams

    # the node's file: the builder's parameters are its ``mapping.*`` group
    flat = load_node_group(args.config, "map_builder", "mapping") if args.config else {}
    params = apply_flat(MapBuildParams(), flat)
    overrides: dict = {}
    if args.d_max is not None:
        overrides["d_max"] = args.d_max
    if args.voxel is not None:
        overrides["voxel"] = args.voxel
    if args.no_icp:
        overrides["icp"] = False
    if args.keep_dynamic:
        overrides["remove_dynamic"] = False
    if args.corridor is not None:
        overrides["corridor"] = args.corridor
    if args.crop_radius is not None:
        overrides["crop_radius"] = args.crop_radius
        center = args.crop_center if args.crop_center is not None else crop_center_default()
        overrides["crop_center"] = tuple(float(v) for v in center)
    elif args.crop_center is not None:
        raise ValueError("--crop-center needs --crop-radius")
    return apply_flat(params, overrides)


def _open_input(args: argparse.Namespace):
    """(scan ids, stamps, poses, loader(i), reference poses or None, crop centre default)."""
    from semcal_ros.io import kitti, scene_scans
    from semcal_ros.io.files import read_pose

    root = args.input
    if scene_scans.is_scene_folder(root):
        scans = scene_scans.open_scene_scans(root)
        truth = None
        if (root / "scans" / "poses_true.yaml").is_file():
            truth = scene_scans.open_scene_scans(root, true_poses=True).poses
            if truth.shape != scans.poses.shape:
                raise ValueError(f"{root}/scans: poses_true.yaml and poses.yaml differ in length")

        def center():
            if not (root / "initial.yaml").is_file():
                raise ValueError(f"{root} has no initial.yaml: give --crop-center X Y Z")
            return read_pose(root / "initial.yaml").translation

        return ([f.name for f in scans.files], scans.stamps, scans.poses, scans.scan, truth,
                center)
    if kitti.is_kitti_sequence(root):
        seq = kitti.open_sequence(root, frame=args.kitti_frame)

        def no_center():
            raise ValueError("a KITTI sequence has no camera prior: give --crop-center X Y Z")

        return ([p.name for p in seq.scan_paths], seq.stamps, seq.poses, seq.scan, None,
                no_center)
    raise FileNotFoundError(f"{root} is neither a scene folder (scans/poses.yaml) nor a KITTI "
                            "sequence (velodyne/ + poses.txt)")


def _print_corrections(result, reference, noisy_input) -> None:
    import numpy as np

    from semcal_ros.mapping.accuracy import pose_errors, remove_common_transform

    shift, angle = result.pose_changes()
    if len(shift) == 0:
        return
    print(f"pose corrections by ICP over {len(shift)} scans: translation median "
          f"{np.median(shift) * 100:.1f} cm, max {shift.max() * 100:.1f} cm; rotation median "
          f"{np.median(angle):.3f} deg, max {angle.max():.3f} deg")
    if len(shift) <= 20:
        for sid, s, a in zip(result.scan_ids, shift, angle):
            print(f"  {sid}: {s * 100:6.1f} cm  {a:6.3f} deg")
    if reference is None:
        return
    what = "unperturbed poses" if noisy_input else "poses_true.yaml"
    for name, poses in (("given", result.prior_poses), ("refined", result.refined_poses)):
        t, r = pose_errors(poses, reference)
        ta, ra = pose_errors(remove_common_transform(poses, reference), reference)
        print(f"{name} poses vs {what}: median {np.median(t) * 100:.1f} cm / "
              f"{np.median(r):.3f} deg, max {t.max() * 100:.1f} cm / {r.max():.3f} deg; "
              f"without the common offset: median {np.median(ta) * 100:.1f} cm / "
              f"{np.median(ra):.3f} deg")


def run(args: argparse.Namespace) -> int:
    from semcal_ros.io.ply import write_ply
    from semcal_ros.io.scene_scans import write_scan_poses
    from semcal_ros.mapping import ScanInput, build_map
    from semcal_ros.mapping.accuracy import displace_poses

    start = time.perf_counter()
    ids, stamps, poses, loader, reference, crop_center = _open_input(args)
    params = _params(args, crop_center)
    output = args.output or args.input / "map.ply"
    if output.exists() and not args.force:
        raise ValueError(f"{output} exists (use --force to overwrite, or -o)")
    if args.first < 0 or args.count < 0:
        raise ValueError("--first and --count must not be negative")
    stop = len(ids) if args.count == 0 else min(len(ids), args.first + args.count)
    chosen = list(range(args.first, stop))
    if not chosen:
        raise ValueError(f"no scans selected (--first {args.first}, {len(ids)} scans)")
    given = poses[chosen]
    reference = None if reference is None else reference[chosen]
    if args.pose_noise is not None:
        reference = given if reference is None else reference
        given = displace_poses(given, args.pose_noise[0], args.pose_noise[1], args.seed)
        print(f"poses perturbed by {args.pose_noise[0]} m / {args.pose_noise[1]} deg "
              f"(seed {args.seed})")
    items = [ScanInput((lambda i=i: loader(i)), given[k], float(stamps[i]), ids[i])
             for k, i in enumerate(chosen)]
    result = build_map(items, params, progress=True)
    for scan_id, reason in result.skipped:
        print(f"skipped {scan_id}: {reason}")
    n = len(result.scan_ids)
    if n == 0:
        raise ValueError(f"none of the {len(items)} scans could be used; nothing written")
    write_ply(output, result.map)
    t = result.timings
    print(f"{n} scans ({len(result.skipped)} skipped): {result.points_in} points in, "
          f"{result.points_kept} after range filter, voxel grid and dynamic removal; "
          f"map {len(result.map)} points -> {output}")
    stages = ", ".join(f"{k} {t[k]:.1f}" for k in ("load", "deskew", "filter", "grids",
                                                   "covariances", "icp", "merge") if k in t)
    print(f"seconds: total {time.perf_counter() - start:.1f} ({stages})"
          + ("" if params.icp else "; ICP off"))
    if params.icp:
        pairs = result.pairs
        rejected = [p for p in pairs if not p.accepted]
        print(f"ICP pairs: {len(pairs)}, {len(rejected)} rejected"
              + (f" ({rejected[0].reason}, ...)" if rejected else ""))
        _print_corrections(result, reference, args.pose_noise is not None)
    if args.write_poses:
        write_scan_poses(args.write_poses, list(result.scan_ids), result.stamps,
                         result.refined_poses, extra={"source": str(args.input)})
        print(f"refined poses -> {args.write_poses}")
    return 0
