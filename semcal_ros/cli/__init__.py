"""The ``semcal`` command: one module per subcommand, discovered here.

Each ``semcal_ros/cli/<name>.py`` defines ``register(subparsers)`` that adds its parser and sets
``func``; modules import their heavy dependencies inside ``run`` so ``semcal --help`` stays fast.
Errors the user can fix (bad files, bad values) are raised as ``ValueError``/``FileNotFoundError``
and printed as one line with a non-zero exit code.
"""

from __future__ import annotations

import argparse
import importlib
import pkgutil
import sys

EXIT_USAGE = 2
EXIT_INPUT = 1


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="semcal",
        description="Target-free camera extrinsic calibration against a labelled lidar map.",
    )
    subparsers = parser.add_subparsers(dest="command", metavar="COMMAND", required=True)
    for info in sorted(pkgutil.iter_modules(__path__), key=lambda m: m.name):
        if info.name.startswith("_"):
            continue
        module = importlib.import_module(f"{__name__}.{info.name}")
        if hasattr(module, "register"):
            module.register(subparsers)
    return parser


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    try:
        return int(args.func(args) or 0)
    except (ValueError, FileNotFoundError, OSError) as exc:
        print(f"semcal {args.command}: error: {exc}", file=sys.stderr)
        return EXIT_INPUT
    except KeyboardInterrupt:
        print(f"semcal {args.command}: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
