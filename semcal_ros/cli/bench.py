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
    p.add_argument("--calibrations", type=int, default=3, help="calibrations per mode")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    import os

    import numba

    from semcal_ros.bench import run_benchmarks

    sizes = tuple(int(s) for s in args.sizes.split(","))
    log = (lambda msg: print(msg, file=sys.stderr)) if args.json else print
    log(f"{os.cpu_count()} CPUs, numba threads {numba.get_num_threads()}, "
        f"load average {os.getloadavg()[0]:.1f}")
    results = run_benchmarks(sizes, args.repeats, args.calibrations, log)
    if args.json:
        print(json.dumps(results, indent=2))
    return 0
