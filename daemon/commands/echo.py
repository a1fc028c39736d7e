"""``cubeloc echo``: print the poses and status of every cubeloc daemon on the network.

One line per pose (with the rate per daemon), one per status, a line when a daemon
appears or disappears (its ``alive`` token); ``--json`` prints the raw payloads, one JSON
object per line, for scripts. By default it finds daemons by multicast scouting; give
``--connect tcp/ROBOT:7447`` where multicast does not pass.
"""

from __future__ import annotations

import collections
import json
import queue
import sys
import time
from datetime import datetime, timezone

RATE_WINDOW_S = 2.0
WAIT_S = 10.0  # nothing from any daemon this long: say so and exit 1
NOTHING_HEARD = 1  # the exit code then


def register(subparsers) -> None:
    from cubeloc.daemon.zenoh_session import add_zenoh_arguments

    parser = subparsers.add_parser("echo", help="print the poses and status of the cubeloc daemons on the network")
    parser.add_argument("--name", dest="daemon_name", default="*", help="only this daemon (default: all, '*')")
    parser.add_argument("--json", action="store_true", help="raw JSON payloads, one per line")
    parser.add_argument("--no-status", action="store_true", help="poses only")
    parser.add_argument("--count", type=int, metavar="N", help="exit after N poses")
    parser.add_argument("--duration", type=float, metavar="S", help="exit after S seconds")
    parser.add_argument("--wait", type=float, default=WAIT_S, metavar="S",
                        help=f"exit 1 when no daemon has been heard within S seconds (default {WAIT_S:g})")
    parser.add_argument("--config", metavar="FILE", help="take the Zenoh settings from this daemon config (TOML)")
    add_zenoh_arguments(parser)
    parser.set_defaults(func=run)


def _daemon_name(key: str) -> str:
    parts = key.split("/")
    return parts[1] if len(parts) >= 3 else key


def format_pose(name: str, doc: dict, rate_hz: float | None) -> str:
    stamp = datetime.fromtimestamp(doc["stamp_ns"] / 1e9, tz=timezone.utc).strftime("%H:%M:%S.%f")[:-3]
    x, y, z = doc["position"]
    qx, qy, qz, qw = doc["orientation"]
    rate = f"{rate_hz:5.1f} Hz" if rate_hz is not None else "    - Hz"  # one pose has no rate yet
    from cubeloc.daemon.messages import pose_label

    state = pose_label(doc["state"], doc.get("source"))
    return (
        f"{name}  pose  seq {doc['seq']:>6}  {stamp}  "
        f"xyz [{x:+8.4f} {y:+8.4f} {z:+8.4f}] m  q [{qx:+.4f} {qy:+.4f} {qz:+.4f} {qw:+.4f}]  "
        f"{state} {doc['planes']} faces  rms {doc['reproj_rms_px']:.2f} px  {rate}"
    )


def format_status(name: str, doc: dict) -> str:
    latency = doc.get("latency_ms") or {}
    p50, p99 = latency.get("p50"), latency.get("p99")
    lat = f"latency p50 {p50:.1f} p99 {p99:.1f} ms" if p50 is not None and p99 is not None else "latency -"
    camera = doc.get("camera") or {}
    model = f" ({camera['model']})" if camera.get("model") else ""
    detail = f" ({doc['detail']})" if doc.get("detail") else ""
    return (
        f"{name}  status  {doc.get('state')}{detail}  {doc.get('fps', 0):.1f} fps  "
        f"poses {doc.get('poses')}  dropped {doc.get('dropped_frames')}  {lat}  "
        f"camera {camera.get('state')}{model}  up {doc.get('uptime_s', 0):.0f} s"
    )


def run(args) -> int:
    import zenoh

    from cubeloc.daemon.commands.run import load_for_command_line
    from cubeloc.daemon.logs import configure_logging
    from cubeloc.daemon.zenoh_session import open_session
    from cubeloc.errors import ConfigError

    if not 0 < args.wait <= 3600:
        raise ConfigError(f"--wait {args.wait:g}: give 0 < S <= 3600 seconds")
    config = load_for_command_line(args)
    # stdout is for the poses; logs (Zenoh settings, problems) go to stderr.
    configure_logging("warning", "console", stream=sys.stderr)
    inbox: queue.Queue = queue.Queue()
    prefix = f"cubeloc/{args.daemon_name}"
    with open_session(config.zenoh, purpose="echo") as session:
        handlers = [session.declare_subscriber(f"{prefix}/pose", lambda s: inbox.put(("pose", s)))]
        if not args.no_status:
            handlers.append(session.declare_subscriber(f"{prefix}/status", lambda s: inbox.put(("status", s))))
            handlers.append(session.liveliness().declare_subscriber(f"{prefix}/alive", lambda s: inbox.put(("alive", s)), history=True))
        code = _print_loop(inbox, args, zenoh.SampleKind.DELETE)
    if code == NOTHING_HEARD:
        where = ", ".join(config.zenoh.connect) or "multicast scouting"
        waited = min(args.wait, args.duration) if args.duration else args.wait
        print(f"cubeloc echo: no cubeloc daemon seen on {where} within {waited:g} s "
              "(is it running? the address, TLS or credentials right?)", file=sys.stderr)
    return code



def _print_loop(inbox: queue.Queue, args, delete_kind) -> int:
    arrivals: dict[str, collections.deque] = collections.defaultdict(collections.deque)
    poses = 0
    started = time.monotonic()
    heard = False
    deadline = started + args.duration if args.duration else None
    while args.count is None or poses < args.count:
        timeout = 0.2 if deadline is None else min(0.2, deadline - time.monotonic())
        if timeout <= 0:
            break
        try:
            kind, sample = inbox.get(timeout=timeout)
        except queue.Empty:
            if not heard and time.monotonic() - started > args.wait:
                return NOTHING_HEARD
            continue
        heard = True
        key = str(sample.key_expr)
        name = _daemon_name(key)
        if kind == "alive":
            gone = sample.kind == delete_kind
            if args.json:
                print(json.dumps({"key": key, "alive": not gone}), flush=True)
            else:
                print(f"{name}  {'gone' if gone else 'alive'}", flush=True)
            continue
        text = sample.payload.to_bytes().decode("utf-8", "replace")
        if args.json:
            print(text, flush=True)
            poses += kind == "pose"
            continue
        try:
            doc = json.loads(text)
        except ValueError:
            print(f"{name}  {kind}  (not JSON: {text[:80]!r})", flush=True)
            continue
        if kind == "pose":
            now = time.monotonic()
            window = arrivals[name]
            window.append(now)
            while window and now - window[0] > RATE_WINDOW_S:
                window.popleft()
            rate = (len(window) - 1) / (window[-1] - window[0]) if len(window) > 1 and window[-1] > window[0] else None
            print(format_pose(name, doc, rate), flush=True)
            poses += 1
        else:
            print(format_status(name, doc), flush=True)
    return 0 if heard else NOTHING_HEARD
