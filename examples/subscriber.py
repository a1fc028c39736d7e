#!/usr/bin/env python3
"""Read a cubeloc daemon's poses over Zenoh: a robot integrator's first five minutes.

Needs only Zenoh (``pip install eclipse-zenoh``), not cubeloc::

    python3 subscriber.py                                   # find daemons by multicast
    python3 subscriber.py --connect tcp/192.168.1.50:7447   # the robot's address
    python3 subscriber.py --connect tcp/192.168.1.50:7447 > run.tum   # evo_traj tum run.tum
    python3 subscriber.py --zenoh-config zenoh-operator.json5 --connect tcp/192.168.1.50:7447
                           # a Zenoh file: the login or TLS set-ups of examples/zenoh-*.json5

With nothing heard from any daemon within ``--wait`` seconds (default 10) it says so on
stderr and exits 1.

Every pose is printed as one TUM line, ``timestamp tx ty tz qx qy qz qw``: the capture
time of the frame in seconds, the camera centre in the world (target) frame in metres,
and the camera's orientation (rotation world <- camera, x right, y down, z forward) as a
unit quaternion. Status changes of the daemon go to stderr.

The payload (JSON, schema ``cubeloc.pose/3``)::

    {"schema": "cubeloc.pose/3", "seq": 42, "stamp_ns": 1790000000000000000,
     "frame_id": "world", "child_frame_id": "camera",
     "position": [x, y, z], "orientation": [qx, qy, qz, qw],
     "state": "target", "source": "target", "planes": 3, "reproj_rms_px": 0.21,
     "covariance": [36 numbers], "latency_ns": 31250000}

``source`` says what measured the pose (target, map, held, odometry, relocalised: the
README's "Reading a pose"); this example reads only the fields every schema version has.
"""

import argparse
import json
import queue
import sys
import time

import zenoh


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--connect", action="append", default=[], help="endpoint of the daemon, e.g. tcp/192.168.1.50:7447")
    parser.add_argument("--name", default="*", help="the daemon's name (default: every daemon)")
    parser.add_argument("--count", type=int, default=0, help="stop after this many poses (default: run until Ctrl-C)")
    parser.add_argument("--timeout", type=float, default=0.0, help="stop after this many seconds (default: never)")
    parser.add_argument("--wait", type=float, default=10.0,
                        help="exit 1 when no daemon has been heard within this many seconds (default 10)")
    parser.add_argument("--zenoh-config", metavar="FILE",
                        help="a Zenoh config file (JSON5): TLS, user/password, mode; --connect goes on top")
    args = parser.parse_args()

    try:
        config = zenoh.Config.from_file(args.zenoh_config) if args.zenoh_config else zenoh.Config()
    except zenoh.ZError as exc:
        print(f"subscriber.py: {args.zenoh_config}: not a usable Zenoh config ({exc})", file=sys.stderr)
        return 2
    if args.connect:  # a known address: no need for multicast discovery
        config.insert_json5("connect/endpoints", json.dumps(args.connect))
        config.insert_json5("scouting/multicast/enabled", "false")
    where = ", ".join(args.connect) or (f"the endpoints of {args.zenoh_config}" if args.zenoh_config
                                        else "multicast scouting")

    # Zenoh calls these from its own threads; hand the samples to the main thread.
    inbox = queue.Queue()
    try:
        session = zenoh.open(config)
    except zenoh.ZError as exc:  # a client whose router does not answer, a TLS failure
        print(f"subscriber.py: no cubeloc daemon reachable on {where} ({exc})", file=sys.stderr)
        return 1
    with session:
        session.declare_subscriber(f"cubeloc/{args.name}/pose", lambda sample: inbox.put(("pose", sample)))
        session.declare_subscriber(f"cubeloc/{args.name}/status", lambda sample: inbox.put(("status", sample)))
        poses, last_state, heard = 0, {}, False
        started = time.monotonic()
        deadline = started + args.timeout if args.timeout else None
        try:
            while not args.count or poses < args.count:
                if deadline is not None and time.monotonic() > deadline:
                    break
                try:
                    kind, sample = inbox.get(timeout=0.2)
                except queue.Empty:
                    if not heard and time.monotonic() - started > args.wait:
                        print(f"subscriber.py: no cubeloc daemon seen on {where} within {args.wait:g} s",
                              file=sys.stderr)
                        return 1
                    continue
                heard = True
                message = json.loads(sample.payload.to_bytes())
                if kind == "status":
                    # Say when a daemon's state changes (target, no_target, reconnecting...).
                    key = str(sample.key_expr)
                    if last_state.get(key) != message["state"]:
                        last_state[key] = message["state"]
                        print(f"{key}: {message['state']} {message.get('detail', '')}", file=sys.stderr, flush=True)
                    continue
                stamp = message["stamp_ns"]
                x, y, z = message["position"]
                qx, qy, qz, qw = message["orientation"]
                print(f"{stamp // 10**9}.{stamp % 10**9:09d} {x:.6f} {y:.6f} {z:.6f} "
                      f"{qx:.6f} {qy:.6f} {qz:.6f} {qw:.6f}", flush=True)
                poses += 1
        except KeyboardInterrupt:
            pass
    return 0


if __name__ == "__main__":
    sys.exit(main())
