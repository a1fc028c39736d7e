"""Run the benchmarks: ``python -m bench [NAME ...]`` (all of them by default)."""

from __future__ import annotations

import importlib
import sys
import time

from bench.common import update_section

# Module names under bench/, in the order they appear in docs/benchmarks.md.
BENCHMARKS: tuple[str, ...] = ("grab", "render", "pose", "range", "target_nees", "e2e", "calibrate", "tracker", "scenarios", "odometry", "mount",
                               "foxglove", "boot", "seeds", "intrinsics", "turns", "family", "laps", "planar", "boards")


def main(argv: list[str]) -> int:
    names = argv or list(BENCHMARKS)
    unknown = [n for n in names if n not in BENCHMARKS]
    if unknown:
        print(f"unknown benchmark(s) {unknown}; known: {', '.join(BENCHMARKS)}", file=sys.stderr)
        return 2
    for name in names:
        module = importlib.import_module(f"bench.{name}")
        started = time.perf_counter()
        print(f"bench {name}: {module.TITLE} ...", flush=True)
        body = module.run()
        update_section(name, module.TITLE, body)
        print(body)
        print(f"bench {name}: done in {time.perf_counter() - started:.1f} s\n", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
