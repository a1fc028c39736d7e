"""``cubeloc demo``: arrives with the daemon (issue 5)."""

from __future__ import annotations

import sys


def register(subparsers) -> None:
    parser = subparsers.add_parser("demo", help="the daemon on the synthetic camera (not there yet)")
    parser.set_defaults(func=run)


def run(args) -> int:
    print("cubeloc demo: not there yet: the daemon arrives with issue 5", file=sys.stderr)
    return 1
