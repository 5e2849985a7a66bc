"""``semcal bench``: render, loss and calibration timings of the engine."""

from __future__ import annotations

import argparse
import json
import sys


def register(subparsers: argparse._SubParsersAction) -> None:
    p = subparsers.add_parser("bench", help="time the renderer, the loss and calibrations")
    p.add_argument("--json", action="store_true", help="print the figures as JSON")
    p.add_argument("--sizes", default="100000,1000000,3000000", help="point counts to render")
    p.add_argument("--repeats", type=int, default=15)
    p.add_argument("--calibrations", type=int, default=3, help="calibrations per mode and size")
    p.add_argument("--calibration-sizes", default="1000000,3500000",
                   help="map sizes (points) to calibrate on")
    p.add_argument("--compare", action="store_true",
                   help="after the figures above: the default procedure against one plain paper "
                        "run (paper render settings, 1/4 then full resolution, one start, no "
                        "verification, no quality report) from the same starts on the same map, "
                        "alternating, with the ratio")
    p.add_argument("--compare-sizes", default="1000000,3500000",
                   help="map sizes (points) of --compare")
    p.add_argument("--compare-scenes", nargs="+", metavar="DIR", default=(),
                   help="--compare on scene folders (map.ply, labels.png, camera_info.yaml, "
                        "ground_truth.yaml: the catalogue's), from the evaluation protocol's "
                        "first --calibrations starts (with --sizes '' --calibration-sizes '': only this)")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    import os

    import numba

    from semcal_tools.bench import run_benchmarks

    sizes = tuple(int(s) for s in args.sizes.split(",") if s)
    log = (lambda msg: print(msg, file=sys.stderr)) if args.json else print
    log(f"{os.cpu_count()} CPUs, numba threads {numba.get_num_threads()}, "
        f"load average {os.getloadavg()[0]:.1f}")
    cal_sizes = tuple(int(s) for s in args.calibration_sizes.split(",") if s)
    sizes = tuple(s for s in sizes if s)
    results = (run_benchmarks(sizes, args.repeats, args.calibrations, cal_sizes, log)
               if sizes or cal_sizes else {})
    if args.compare:
        from semcal_tools.bench import run_compare

        cmp_sizes = tuple(int(s) for s in args.compare_sizes.split(",") if s)
        results["compare"] = run_compare(cmp_sizes, args.calibrations, log)
    if args.compare_scenes:
        from semcal_tools.bench import run_compare_scenes

        results["compare_scenes"] = run_compare_scenes(list(args.compare_scenes),
                                                       args.calibrations, log)
    if args.json:
        print(json.dumps(results, indent=2))
    return 0
