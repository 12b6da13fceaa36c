"""Entry point of the ``graylight`` command.

Each command group lives in its own module with a ``register(subparsers)`` function;
``COMMAND_MODULES`` lists them. A :class:`~shared.core.errors.GraylightError` ends the
command with its one-line message on stderr and exit status 1.
"""

from __future__ import annotations

import argparse
import importlib
import logging
import sys

from shared.core.errors import GraylightError

COMMAND_MODULES = [
    "services.cli.scan",
    "services.cli.simulate",
    "services.cli.jobs",
    "services.cli.render",
    "services.cli.calibrate",
    "services.cli.export",
    "services.cli.rig",
    "services.cli.compress",
    "services.cli.merge",
]


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="graylight", description="Structured-light 3D scanning.")
    parser.add_argument("-v", "--verbose", action="store_true", help="log progress details")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", required=True)
    for name in COMMAND_MODULES:
        importlib.import_module(name).register(sub)
    return parser


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    logging.basicConfig(
        level=logging.INFO if args.verbose else logging.WARNING,
        format="%(levelname)s %(name)s: %(message)s",
    )
    try:
        return int(args.func(args) or 0)
    except GraylightError as exc:
        print(f"graylight {args.command}: error: {exc}", file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        print(f"graylight {args.command}: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
