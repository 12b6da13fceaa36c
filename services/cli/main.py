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

from services.cli.provenance import run_recorded
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
    "services.cli.results",
    "services.cli.publish",
    "services.cli.derive",
]

#: The commands each of :data:`COMMAND_MODULES` registers (a test keeps the two in step). A
#: command line naming one of them builds only its module's parsers: importing every command
#: module cost each command 0.04 s of CPU (a sixth of the start-up ``graylight tiles`` has
#: left besides numpy and numba). Any other command line (``--help``, a typo) gets them all.
COMMANDS = {
    "scan": "services.cli.scan", "patterns": "services.cli.scan", "import-sequence": "services.cli.scan",
    "simulate": "services.cli.simulate",
    "serve": "services.cli.jobs", "worker": "services.cli.jobs", "beat": "services.cli.jobs",
    "submit": "services.cli.jobs", "jobs": "services.cli.jobs", "batch": "services.cli.jobs",
    "keys": "services.cli.jobs",
    "tiles": "services.cli.render", "preview": "services.cli.render",
    "calibrate": "services.cli.calibrate",
    "export": "services.cli.export",
    "rig": "services.cli.rig",
    "compress": "services.cli.compress", "decompress": "services.cli.compress",
    "merge": "services.cli.merge",
    "job": "services.cli.results", "rerender": "services.cli.results", "view": "services.cli.results",
    "publish": "services.cli.publish", "rerun": "services.cli.publish",
    "derivatives": "services.cli.derive",
}  # fmt: skip


def _command_word(argv: list[str]) -> str | None:
    """The command a command line names: its first word that is not an option (the top-level
    options take no value), or None."""
    return next((a for a in argv if not a.startswith("-")), None)


def build_parser(argv: list[str] | None = None) -> argparse.ArgumentParser:
    """The ``graylight`` parser: every command's, or with ``argv`` naming a command of
    :data:`COMMANDS`, that command's module's alone (the same parse of that command line)."""
    parser = argparse.ArgumentParser(prog="graylight", description="Structured-light 3D scanning.")
    parser.add_argument("-v", "--verbose", action="store_true", help="log progress details")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", required=True)
    command = _command_word(argv) if argv is not None else None
    for name in [COMMANDS[command]] if command in COMMANDS else COMMAND_MODULES:
        importlib.import_module(name).register(sub)
    return parser


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    parser = build_parser(argv)
    args = parser.parse_args(argv)
    logging.basicConfig(
        level=logging.INFO if args.verbose else logging.WARNING,
        format="%(levelname)s %(name)s: %(message)s",
    )
    try:
        # Commands that write outputs leave their paradata beside them (services/cli/provenance.py).
        return int(run_recorded(args, argv, args.func) or 0)
    except GraylightError as exc:
        print(f"graylight {args.command}: error: {exc}", file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        print(f"graylight {args.command}: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
