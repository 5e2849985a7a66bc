"""The ``semcal`` command: one module per subcommand, discovered here.

Each ``semcal_ros/cli/<name>.py`` (and each ``semcal_tools/cli/<name>.py``: the test and demo
tooling's commands scene, bench, evaluate, demo) defines ``register(subparsers)`` that adds its
parser and sets ``func``; modules import their heavy dependencies inside ``run`` so
``semcal --help`` stays fast.
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
COMMAND_PACKAGES = ("semcal_ros.cli", "semcal_tools.cli")


def _command_modules():
    """Every sub-command module of the product and of the tooling, sorted by name."""
    found = []
    for package_name in COMMAND_PACKAGES:
        try:
            package = importlib.import_module(package_name)
        except ImportError:  # the tooling is optional in an installation without it
            continue
        found += [(info.name, f"{package_name}.{info.name}")
                  for info in pkgutil.iter_modules(package.__path__) if not info.name.startswith("_")]
    return sorted(found)


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="semcal",
        description="Target-free camera extrinsic calibration against a labelled lidar map.",
    )
    subparsers = parser.add_subparsers(dest="command", metavar="COMMAND", required=True)
    for _name, module_name in _command_modules():
        module = importlib.import_module(module_name)
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
