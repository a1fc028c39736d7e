"""``cubeloc simulate``: write a synthetic sequence with exact ground truth."""

from __future__ import annotations

import signal
import sys
import threading
import time

# fakes.trajectories.TRAJECTORIES, spelled out so that --help needs no numpy import
TRAJECTORY_NAMES = ("static", "orbit", "paper", "room_walk", "spin", "turn_after_init", "spin_in_place",
                    "spin_in_place_fast", "spin_brisk", "spin_on_axis", "agile", "passers_by", "blank_wall", "long_lap", "laps")


def register(subparsers) -> None:
    parser = subparsers.add_parser(
        "simulate",
        help="write a synthetic sequence (EuRoC layout, ground truth, camera_info, target file)",
        description=(
            "Render the cube in a textured room along a camera trajectory and write it as a "
            "sequence directory: mav0/cam0 (EuRoC layout), groundtruth.tum, camera.yaml, target.yaml."
        ),
    )
    which = parser.add_mutually_exclusive_group(required=True)
    which.add_argument("--trajectory", choices=TRAJECTORY_NAMES,
                       help="camera path; the robot-motion scenarios (turn_after_init ... laps) bring "
                            "their own passers-by, exposure steps and exposure-long motion blur")
    which.add_argument("--family", type=int, metavar="SEED",
                       help="a member of the randomized family (fakes/family.py): scene, lens, robot, motion "
                            "and disturbances all drawn from SEED; writes family.json beside the frames "
                            "(--seconds, --fps, --calib, --target and the render options do not apply)")
    parser.add_argument("--resolution", choices=("half", "full"), default="half",
                        help="with --family: 640x512 (default) or 1280x1024, the same lens")
    parser.add_argument("--out", required=True, help="sequence directory to create (must not exist or be empty)")
    from cubeloc.fakes.trajectories import DEFAULT_FPS, DEFAULT_FPS_OF, DEFAULT_SECONDS

    lengths = ", ".join(f"{name} {seconds:g}" for name, seconds in DEFAULT_SECONDS.items())
    fast = ", ".join(f"{name} {fps:g}" for name, fps in DEFAULT_FPS_OF.items() if fps != DEFAULT_FPS)
    parser.add_argument("--seconds", type=float, help=f"length in seconds (default per trajectory: {lengths})")
    parser.add_argument("--fps", type=float, help=f"frame rate (default {DEFAULT_FPS:g}; {fast})")
    parser.add_argument("--seed", type=int, default=0, help="sensor-noise seed (default 0)")
    parser.add_argument("--noise", type=float, default=2.0, help="read noise, DN (default 2)")
    parser.add_argument("--blur", type=float, default=0.0, help="defocus blur sigma, px (default 0)")
    parser.add_argument("--hide", type=int, nargs="*", default=[], metavar="ID", help="tags to paint over")
    parser.add_argument("--glare", type=int, metavar="ID", help="over-expose the face of this tag")
    parser.add_argument("--calib", help="camera_info YAML to render with (default: the paper's camera)")
    parser.add_argument("--target", help="target file (default: the 18 cm cube, ids 0-5)")
    parser.set_defaults(func=run)


def run(args) -> int:
    from cubeloc.daemon.logs import configure_logging

    configure_logging("warning", stream=sys.stderr)  # stdout is for the one-line summary
    started = time.monotonic()
    interactive = sys.stderr.isatty()

    stop = threading.Event()

    def progress(done: int, total: int) -> None:
        # a signal stops the render between two frames, as a KeyboardInterrupt, which removes
        # the half-written sequence (raised inside a compiled kernel's call by the handler, it
        # would come out as a SystemError)
        if stop.is_set():
            raise KeyboardInterrupt
        if interactive and (done % 10 == 0 or done == total):
            print(f"\rrendered {done}/{total} frames", end="" if done < total else "\n", file=sys.stderr, flush=True)

    # SIGTERM as Ctrl-C, each at the end of the frame being rendered
    previous = {sig: signal.signal(sig, lambda *_: stop.set()) for sig in (signal.SIGINT, signal.SIGTERM)}
    try:
        summary = _simulate(args, progress)
    finally:
        for sig, handler in previous.items():
            signal.signal(sig, handler)
    elapsed = time.monotonic() - started
    print(
        f"wrote {summary.frames} frames ({summary.seconds:.1f} s of {summary.trajectory}) to {summary.path} "
        f"in {elapsed:.1f} s ({1000 * elapsed / summary.frames:.0f} ms/frame)"
    )
    return 0


def _simulate(args, progress):
    if args.family is not None:
        from cubeloc.fakes.family import make_case, render_case

        return render_case(make_case(args.family, args.resolution), args.out, progress)
    from cubeloc.calib.camera_info import read_camera_info
    from cubeloc.fakes.camera import RenderOptions
    from cubeloc.fakes.sequence import write_synthetic_sequence
    from cubeloc.positioning.target import load_target

    return write_synthetic_sequence(
        args.out,
        args.trajectory,
        seconds=args.seconds,
        fps=args.fps,
        seed=args.seed,
        calibration=read_camera_info(args.calib) if args.calib else None,
        target=load_target(args.target) if args.target else None,
        options=RenderOptions(
            noise_sigma=args.noise, blur_sigma_px=args.blur, hidden_tags=tuple(args.hide), glare_tag=args.glare
        ),
        progress=progress,
    )
