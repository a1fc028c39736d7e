"""The soak (``cubeloc.daemon.soak``: the daemon on pre-rendered synthetic frames at the
camera's full rate, for long) as a benchmark: ``make soak`` (``python -m bench.soak
--minutes 30``) runs it and writes the result table to docs/soak.md (``--no-write`` to
skip). Exit code 0 when every check passes.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

from cubeloc.daemon.soak import Sample, SoakResult, run_soak

SOAK_DOC = Path(__file__).resolve().parents[1] / "docs" / "soak.md"


def report_markdown(result: SoakResult, command: str) -> str:
    from bench.common import machine_line, markdown_table

    samples = result.samples
    after = [s for s in samples if s.t_s >= result.warmup_s]
    first, warm, end = samples[0], after[0] if after else samples[0], samples[-1]
    rows = [
        ["RSS (MiB)", f"{first.rss_kb / 1024:.1f}", f"{warm.rss_kb / 1024:.1f}", f"{end.rss_kb / 1024:.1f}"],
        ["threads", first.threads, warm.threads, end.threads],
        ["open fds", first.fds, warm.fds, end.fds],
        ["frames processed", first.frames, warm.frames, end.frames],
        ["poses published", first.poses, warm.poses, end.poses],
    ]
    checks = [[name, "pass" if ok else "FAIL", text] for name, (ok, text) in result.checks.items()]
    checks += [[name, "(figure)", text] for name, text in result.info.items()]
    stamp = time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime())
    return (
        "# Soak\n\n"
        "The daemon (capture thread, frame processor, Zenoh publisher, status thread) on the "
        "pre-rendered synthetic camera (`fakes.faulty.CyclingCamera`) at its full frame rate, "
        "a subscriber checking every pose against the ground truth, the cable pulled every "
        "few minutes. Written by `make soak` (`daemon/soak.py`, run by `bench/soak.py`); the same checks (but the "
        "slow-down one) run for 12 s in `make test` (tests/test_soak_short.py).\n\n"
        f"Run: {result.processor}, {result.seconds / 60:.1f} min at {result.fps:g} fps "
        f"({result.frames_delivered} frames from the camera), warm-up {result.warmup_s:.0f} s, "
        f"{result.unplugs} unplugs, {result.reconnects} reconnects; {stamp} on {machine_line()}.\n\n"
        + markdown_table(["", "start", "after warm-up", "end"], rows)
        + "\n"
        + markdown_table(["check", "result", "figures"], checks)
        + f"\nReproduce: `{command}`.\n"
    )


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m bench.soak", description=__doc__.splitlines()[0])
    parser.add_argument("--minutes", type=float, default=30.0, help="how long to run (default 30)")
    parser.add_argument("--fps", type=float, default=10.0, help="the camera's frame rate (default 10)")
    parser.add_argument("--images", type=int, default=24, help="pre-rendered frames to cycle (default 24)")
    parser.add_argument("--sample", type=float, default=10.0, help="seconds between samples (default 10)")
    parser.add_argument("--unplug-every", type=float, default=300.0, help="seconds between cable pulls (0: never)")
    parser.add_argument("--no-write", action="store_true", help="do not write docs/soak.md")
    args = parser.parse_args(argv)
    from cubeloc.atomic import atomic_write_text
    from cubeloc.daemon.logs import configure_logging

    configure_logging("warning", "console")  # the daemon's warnings (camera lost...) only

    def progress(sample: Sample) -> None:
        print(f"{sample.t_s:7.0f} s  RSS {sample.rss_kb / 1024:7.1f} MiB  threads {sample.threads:3d}  "
              f"fds {sample.fds:3d}  frames {sample.frames:6d}  poses {sample.poses:6d}", flush=True)

    result = run_soak(args.minutes * 60, fps=args.fps, images=args.images, sample_s=args.sample,
                      unplug_every_s=args.unplug_every or None, progress=progress)
    for name, (ok, text) in result.checks.items():
        print(f"{'pass' if ok else 'FAIL'}  {name}: {text}")
    for name, text in result.info.items():
        print(f"      {name}: {text}")
    if not args.no_write:
        command = "make soak" if args.minutes == 30 else f"python -m bench.soak --minutes {args.minutes:g}"
        atomic_write_text(SOAK_DOC, report_markdown(result, command))
        print(f"wrote {SOAK_DOC}")
    return 0 if result.ok else 1


if __name__ == "__main__":
    sys.exit(main())
