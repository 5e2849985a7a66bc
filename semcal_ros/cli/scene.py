"""``semcal scene``: generate a synthetic roadside scene folder (docs/scenes.md)."""

from __future__ import annotations

import argparse


def register(subparsers: argparse._SubParsersAction) -> None:
    p = subparsers.add_parser(
        "scene", help="generate a synthetic scene (map, scans, images, bag)",
        description="Generate a procedural roadside scene observed by a ray-cast lidar and "
                    "camera, in the scene folder format of docs/CONTRACTS.md.")
    p.add_argument("--kind", default="junction", help="layout: junction, arterial or highway")
    p.add_argument("--seed", type=int, default=0, help="random seed of the world (default 0)")
    p.add_argument("--variant", default="ideal",
                   help="ideal, noisy_labels, dynamic, sparse or pose_noise (default ideal)")
    p.add_argument("--out", required=True, help="output folder (must be empty or absent)")
    p.add_argument("--size", default="full",
                   help="full (200 scans) or small (50 scans, the test/demo scene)")
    p.add_argument("--scans", type=int, help="number of scans (overrides --size)")
    p.add_argument("--lines", type=int, help="lidar lines (default 128, 32 for sparse)")
    p.add_argument("--no-bag", action="store_true", help="skip the rosbag2 (bag/)")
    p.add_argument("--no-scans", action="store_true",
                   help="skip scans/*.ply (scans/poses.yaml is still written)")
    p.add_argument("--threads", type=int, default=0, help="ray-casting threads (0 = all cores)")
    p.add_argument("--force", action="store_true", help="replace an existing scene in --out")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from dataclasses import replace

    from semcal_ros.scenes import SIZES, generate_scene

    if args.size not in SIZES:
        raise ValueError(f"unknown --size '{args.size}' (choose from {', '.join(SIZES)})")
    options = SIZES[args.size]
    changes = {"write_bag": not args.no_bag, "write_scans": not args.no_scans,
               "threads": args.threads}
    if args.scans is not None:
        changes["scans"] = args.scans
    if args.lines is not None:
        changes["lines"] = args.lines
    options = replace(options, **changes)
    result = generate_scene(args.out, args.kind, args.seed, args.variant, options,
                            force=args.force, progress=not args.quiet)
    s = result.summary
    print(f"{result.out}: {s['kind']}/{s['variant']} seed {s['seed']}, "
          f"{s['counts']['scans']} scans, map {s['counts']['map_points']} points, "
          f"{s['seconds']['total']:.1f} s")
    return 0
