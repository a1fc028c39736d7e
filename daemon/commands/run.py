"""``cubeloc run [--config FILE]``: the daemon (capture, positioning, Zenoh).

Everything is checked before anything starts (daemon/preflight.py): a bad config, file or
endpoint is one line on stderr and exit code 2. SIGTERM and SIGINT only set the stop
event; the daemon then shuts down in order (daemon/service.py).
"""

from __future__ import annotations

import signal
import threading


def register(subparsers) -> None:
    from cubeloc.daemon.zenoh_session import add_zenoh_arguments

    parser = subparsers.add_parser(
        "run",
        help="the daemon: capture, positioning, publish poses over Zenoh",
        description="Run the positioning daemon. Config: --config FILE, else $CUBELOC_CONFIG, "
        "else /etc/cubeloc/cubeloc.toml, else built-in defaults; CUBELOC_<SECTION>__<FIELD> "
        "environment variables override single values.",
    )
    parser.add_argument("--config", metavar="FILE", help="TOML config file (see systemd/cubeloc.toml)")
    parser.add_argument("--name", help="override the config's name (the key is cubeloc/<name>/...)")
    parser.add_argument("--source", metavar="SOURCE", help="override camera.source, e.g. aravis:SERIAL, replay:DIR, synthetic:paper")
    parser.add_argument("--foxglove", metavar="HOST:PORT",
                        help="serve the Foxglove viewer there (sets [foxglove] listen); 127.0.0.1:8765 for "
                             "this machine only, 0.0.0.0:8765 to admit other hosts (docs/security.md)")
    parser.add_argument("--check", action="store_true", help="check the config and its files, then exit (0 if all is well)")
    add_zenoh_arguments(parser)
    parser.set_defaults(func=run)


def load_for_command_line(args):
    """The config from ``--config`` (or the defaults), with the command-line overrides."""
    from pydantic import ValidationError

    from cubeloc.daemon.config import Config, load_config
    from cubeloc.daemon.zenoh_session import settings_from_arguments
    from cubeloc.errors import ConfigError

    config = load_config(getattr(args, "config", None))
    # exclude_unset keeps "what the user set" apart from defaults (the Zenoh JSON5 file
    # wins over defaults but not over explicit settings).
    document = config.model_dump(exclude_unset=True)
    document["zenoh"] = settings_from_arguments(config.zenoh, args).model_dump(exclude_unset=True)
    if getattr(args, "name", None):
        document["name"] = args.name
    if getattr(args, "foxglove", None):
        document.setdefault("foxglove", {})["listen"] = args.foxglove
    if getattr(args, "source", None):
        document.setdefault("camera", {})["source"] = args.source
    try:
        return Config.model_validate(document)
    except ValidationError as exc:
        error = exc.errors()[0]
        field = ".".join(str(part) for part in error["loc"])
        raise ConfigError(f"command line: {field} = {error.get('input')!r}: {error['msg']}") from None


def run(args) -> int:
    import structlog

    from cubeloc.daemon.logs import configure_logging
    from cubeloc.daemon.preflight import prepare
    from cubeloc.daemon.service import Daemon

    config = load_for_command_line(args)
    configure_logging(config.logging.level, config.logging.format)
    prepared = prepare(config)
    if args.check:
        print(f"cubeloc run: config OK (name {config.name}, camera {config.camera.source}, "
              f"calibration {config.positioning.calibration}, target {config.positioning.target})")
        return 0
    stop = threading.Event()

    def request_stop(signum, _frame) -> None:
        # Only set the event: the loop notices within a fraction of a second and shuts
        # everything down in order, outside the signal handler.
        stop.set()

    reload = threading.Event()

    def request_reload(signum, _frame) -> None:
        reload.set()  # SIGHUP (systemctl reload): the status thread reads the files again

    previous = {sig: signal.signal(sig, request_stop) for sig in (signal.SIGTERM, signal.SIGINT)}
    previous[signal.SIGHUP] = signal.signal(signal.SIGHUP, request_reload)
    try:
        daemon = Daemon(prepared, stop, reload=reload)
        return daemon.run()
    finally:
        for sig, handler in previous.items():
            signal.signal(sig, handler)
        structlog.get_logger().info("exiting")
