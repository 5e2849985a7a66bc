"""``semcal scene``: generate a synthetic roadside scene folder (docs/scenes.md)."""

from __future__ import annotations

import argparse


def register(subparsers: argparse._SubParsersAction) -> None:
    p = subparsers.add_parser(
        "scene", help="generate a synthetic scene (map, scans, images, bag)",
        description="Generate a procedural roadside scene observed by a ray-cast lidar and "
                    "camera, in the scene folder format of docs/CONTRACTS.md.")
    p.add_argument("--kind", default="junction",
                   help="layout: junction, arterial, highway or roundabout")
    p.add_argument("--seed", type=int, default=0, help="random seed of the world (default 0)")
    p.add_argument("--variant", default="ideal",
                   help="ideal, noisy_labels, dynamic, sparse or pose_noise (default ideal)")
    p.add_argument("--out", help="output folder (must be empty or absent)")
    p.add_argument("--size", default="full",
                   help="full (200 scans), small (50 scans, the test/demo scene) or large "
                        "(maps of 3 M points and more)")
    p.add_argument("--scans", type=int, help="number of scans (overrides --size)")
    p.add_argument("--lines", type=int, help="lidar lines, e.g. 32, 64, 128 (default 128, 32 "
                                             "for sparse)")
    p.add_argument("--horizontal-step", type=float, help="lidar horizontal step, degrees "
                                                         "(default 0.2; large 0.1)")
    p.add_argument("--voxel", type=float, help="map voxel size, metres (default 0.05)")
    p.add_argument("--frame", choices=("layout", "random"),
                   help="map frame: the layout's own (default) or a random one (rotated about z, "
                        "shifted tens of metres)")
    p.add_argument("--mast", choices=("pole", "bracket"),
                   help="the camera's mast in the map: a plain pole (default) or with the "
                        "camera's housing, visor and arm (bracket)")
    p.add_argument("--cameras", type=int,
                   help="N >= 2: N named cameras round one junction (northeast, southeast, "
                        "southwest, northwest, north, east, south, west; at most 8), each in "
                        "cameras/<name>/ with its own bag topics /<name>/labels etc. (default: "
                        "one camera, the single-camera folder)")
    p.add_argument("--lens", choices=("pinhole", "fisheye", "wide"),
                   help="the camera's lens: pinhole (default, 90 deg), fisheye (185 deg "
                        "equidistant) or wide (120 deg rational_polynomial); camera_info.yaml "
                        "carries the model, the label image is ray-cast through it "
                        "(docs/lenses.md)")
    p.add_argument("--catalogue", metavar="NAME",
                   help="a scene of the evaluation table (e.g. roundabout-sparse): sets kind, "
                        "variant, size, lines, frame and mast; --seed still applies")
    p.add_argument("--list", action="store_true",
                   help="print the commands that make every scene of the evaluation table")
    p.add_argument("--no-bag", action="store_true", help="skip the rosbag2 (bag/)")
    p.add_argument("--compressed", action="store_true",
                   help="the bag's camera images as image_transport's <topic>/compressed "
                        "(CompressedImage: JPEG images, PNG labels), as recorders store them")
    p.add_argument("--no-scans", action="store_true",
                   help="skip scans/*.ply (scans/poses.yaml is still written)")
    p.add_argument("--threads", type=int, default=0, help="ray-casting threads (0 = all cores)")
    p.add_argument("--force", action="store_true", help="replace an existing scene in --out")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from dataclasses import replace
    from pathlib import Path

    from semcal_tools.scenes import SIZES, catalogue, generate_scene
    from semcal_tools.scenes.catalogue import find

    if args.list:
        for entry in catalogue(args.seed):
            print(entry.command(args.out or "scenes"))
        return 0
    if not args.out:
        raise ValueError("--out is required (the scene folder to write)")
    kind, variant = args.kind, args.variant
    if args.catalogue:
        entry = find(args.catalogue, args.seed)
        kind, variant = entry.kind, entry.variant
        options = entry.options(bag=not args.no_bag, scans=not args.no_scans)
    else:
        if args.size not in SIZES:
            raise ValueError(f"unknown --size '{args.size}' (choose from {', '.join(SIZES)})")
        options = SIZES[args.size]
    changes = {"write_bag": not args.no_bag, "write_scans": not args.no_scans,
               "threads": args.threads}
    for arg, field in (("scans", "scans"), ("lines", "lines"), ("voxel", "voxel"),
                       ("horizontal_step", "horizontal_step_deg"), ("frame", "map_frame"),
                       ("mast", "mast"), ("cameras", "cameras"), ("lens", "lens")):
        if getattr(args, arg) is not None:
            changes[field] = getattr(args, arg)
    options = replace(options, **changes)
    if args.compressed and args.no_bag:
        raise ValueError("--compressed changes the bag: it cannot go with --no-bag")
    result = generate_scene(args.out, kind, args.seed, variant, options,
                            force=args.force, progress=not args.quiet)
    if args.compressed:
        from semcal_tools.scenes.bag import compress_camera_images

        compress_camera_images(Path(result.out) / "bag")
    s = result.summary
    print(f"{result.out}: {s['kind']}/{s['variant']} seed {s['seed']}, "
          f"{s['counts']['scans']} scans, {s['lidar']['lines']} lines, "
          f"map {s['counts']['map_points']} points, frame {options.map_frame}, "
          f"mast {options.mast}, lens {options.lens}, {s['seconds']['total']:.1f} s"
          + (f", cameras {', '.join(s['cameras'])}" if "cameras" in s else ""))
    return 0
