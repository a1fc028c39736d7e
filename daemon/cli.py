"""The ``cubeloc`` command line: one entry point, one module per verb.

Each verb lives in ``daemon/commands/<verb>.py`` with ``register(subparsers)`` that adds
its parser and sets ``func`` to a function taking the parsed arguments and returning an
exit code. Verb modules import heavy libraries (OpenCV, Zenoh, PyGObject) inside their
functions, so ``cubeloc --help`` stays fast.

This is the one place where errors become messages: a ``CubelocError`` is printed as one
line on stderr with exit code 2; anything else is a bug and keeps its traceback.
"""

from __future__ import annotations

import argparse
import importlib
import os
import sys

from cubeloc import __version__
from cubeloc.errors import CubelocError

# The verbs, in the order ``--help`` lists them.
VERB_MODULES = (
    "cubeloc.daemon.commands.run",
    "cubeloc.daemon.commands.devices",
    "cubeloc.daemon.commands.record",
    "cubeloc.daemon.commands.demo",
    "cubeloc.daemon.commands.echo",
    "cubeloc.daemon.commands.simulate",
    "cubeloc.daemon.commands.pose",
    "cubeloc.daemon.commands.track",
    "cubeloc.daemon.commands.generate",
    "cubeloc.daemon.commands.calibrate",
    "cubeloc.daemon.commands.calibrate_target",
    "cubeloc.daemon.commands.calibrate_mount",
    "cubeloc.daemon.commands.doctor",
    "cubeloc.daemon.commands.map",
)


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="cubeloc",
        description="Metric 6-DoF camera pose from a cube of AprilTags and a monocular tracker, over Zenoh.",
    )
    parser.add_argument("--version", action="version", version=f"cubeloc {__version__}")
    subparsers = parser.add_subparsers(dest="verb", metavar="VERB", required=True)
    for module_name in VERB_MODULES:
        importlib.import_module(module_name).register(subparsers)
    return parser


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    try:
        code = int(args.func(args) or 0)
        sys.stdout.flush()  # here, where a closed pipe is caught, not at the interpreter's exit
        return code
    except CubelocError as exc:
        print(f"cubeloc {args.verb}: error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(f"cubeloc {args.verb}: interrupted", file=sys.stderr)
        return 130
    except BrokenPipeError:
        # The reader went away (`cubeloc pose ... | head -1`): what it wanted it got. No
        # traceback, and none at exit either: stdout goes to /dev/null for the final flush.
        devnull = os.open(os.devnull, os.O_WRONLY)
        os.dup2(devnull, sys.stdout.fileno())
        os.close(devnull)
        return 0


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
