"""The one place that turns settings into a Zenoh session, for every verb.

``cubeloc run``, ``echo`` and ``demo`` all go through here: the ``[zenoh]`` section of the
config, optionally overridden by ``--mode/--connect/--listen/--no-scouting/--zenoh-config``
on the command line, becomes a ``zenoh.Config``. An optional Zenoh JSON5 file (TLS,
access control, anything else Zenoh offers) is the starting point; the explicit settings
go on top of it. Every problem is a ``ConfigError`` naming the endpoint or file.

Zenoh is imported inside the functions so that ``cubeloc --help`` stays fast.
"""

from __future__ import annotations

import argparse
import ipaddress
import json
import re
from typing import TYPE_CHECKING, Any

import structlog

from cubeloc.daemon.config import ZenohConfig
from cubeloc.errors import ConfigError

if TYPE_CHECKING:  # pragma: no cover
    import zenoh

log = structlog.get_logger()

IP_PROTOCOLS = {"tcp", "udp", "tls", "quic", "ws"}


class ZenohUnreachable(ConfigError):
    """Client mode and no router answers on any ``connect`` endpoint. For a one-shot verb
    this is a user error like any other; the daemon waits for the router instead (it may
    simply not be up yet at boot)."""


def zenoh_error_text(exc: BaseException) -> str:
    """Zenoh's message without the Rust source location, on one line."""
    text = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
    return re.sub(r" at /\S+?\.rs:\d+\.?", "", text)


def check_endpoint(endpoint: str) -> None:
    """Raise ConfigError unless ``endpoint`` looks like PROTOCOL/HOST:PORT (or a socket path).

    Zenoh accepts any string into its config and fails only when opening; checking here
    makes a typo fail at start with the endpoint named.
    """
    protocol, _, rest = endpoint.partition("/")
    address = re.split(r"[?#]", rest, maxsplit=1)[0]  # drop Zenoh's ?config / #metadata
    hint = "expected PROTOCOL/HOST:PORT such as 'tcp/192.168.1.10:7447'"
    if protocol == "unixsock-stream":
        if not address:
            raise ConfigError(f"zenoh endpoint {endpoint!r}: missing socket path")
        return
    if protocol not in IP_PROTOCOLS:
        raise ConfigError(f"zenoh endpoint {endpoint!r}: unknown protocol {protocol!r}; {hint}")
    host, sep, port = address.rpartition(":")
    if not sep or not host or not port.isdigit() or not 0 <= int(port) <= 65535:
        raise ConfigError(f"zenoh endpoint {endpoint!r}: {hint} (port 0-65535)")
    if host.startswith("[") and host.endswith("]"):
        host = host[1:-1]
    try:
        ipaddress.ip_address(host)
    except ValueError:
        # A host name: letters, digits, dots and dashes only.
        if not re.fullmatch(r"[A-Za-z0-9]([A-Za-z0-9.-]*[A-Za-z0-9])?", host) or re.fullmatch(r"[\d.]+", host):
            raise ConfigError(f"zenoh endpoint {endpoint!r}: {host!r} is neither an IP address nor a host name") from None


def add_zenoh_arguments(parser: argparse.ArgumentParser) -> None:
    group = parser.add_argument_group("Zenoh (override the [zenoh] section of the config)")
    group.add_argument("--mode", choices=("peer", "client", "router"), help="Zenoh mode")
    group.add_argument("--connect", action="append", metavar="ENDPOINT", help="endpoint to connect to, e.g. tcp/192.168.1.10:7447 (repeatable)")
    group.add_argument("--listen", action="append", metavar="ENDPOINT", help="endpoint to listen on, e.g. tcp/0.0.0.0:7447 (repeatable)")
    group.add_argument("--no-scouting", action="store_true", help="turn multicast scouting off (only the given endpoints)")
    group.add_argument("--zenoh-config", metavar="JSON5", help="a Zenoh JSON5 config file (TLS, access control); the options above go on top")


def settings_from_arguments(base: ZenohConfig, args: argparse.Namespace) -> ZenohConfig:
    """``base`` with the command-line overrides applied, validated again."""
    update: dict[str, Any] = {}
    if getattr(args, "mode", None):
        update["mode"] = args.mode
    if getattr(args, "connect", None):
        update["connect"] = tuple(args.connect)
    if getattr(args, "listen", None):
        update["listen"] = tuple(args.listen)
    if getattr(args, "no_scouting", False):
        update["multicast_scouting"] = False
    if getattr(args, "zenoh_config", None):
        update["config_file"] = args.zenoh_config
    if not update:
        return base
    document = base.model_dump(exclude_unset=True)
    document.update(update)
    try:
        return ZenohConfig.model_validate(document)
    except ValueError as exc:
        raise ConfigError(f"command line: {str(exc).splitlines()[-1].strip()}") from None


def build_zenoh_config(settings: ZenohConfig, timestamping: bool = False) -> zenoh.Config:
    """The ``zenoh.Config`` for these settings (file first, explicit settings on top);
    ``timestamping`` stamps every sample (the ROS 2 side's cached CameraInfo needs it, as
    rmw_zenoh's default session config has it)."""
    import zenoh

    for endpoint in (*settings.listen, *settings.connect):
        check_endpoint(endpoint)
    explicit = settings.model_fields_set
    if settings.config_file is not None:
        path = settings.config_file
        if not path.is_file():
            raise ConfigError(f"zenoh config file {path}: not found")
        try:
            conf = zenoh.Config.from_file(str(path))
        except zenoh.ZError as exc:
            raise ConfigError(f"zenoh config file {path}: {zenoh_error_text(exc)}") from None
    else:
        conf = zenoh.Config()
    try:
        # Without a file our defaults apply; with one, only what the user set explicitly.
        if settings.config_file is None or "mode" in explicit:
            conf.insert_json5("mode", json.dumps(settings.mode))
        if settings.config_file is None or "multicast_scouting" in explicit:
            conf.insert_json5("scouting/multicast/enabled", json.dumps(settings.multicast_scouting))
        if settings.listen:
            conf.insert_json5("listen/endpoints", json.dumps(list(settings.listen)))
        if settings.connect:
            conf.insert_json5("connect/endpoints", json.dumps(list(settings.connect)))
        if timestamping:
            conf.insert_json5("timestamping/enabled", "true")
    except zenoh.ZError as exc:
        raise ConfigError(f"zenoh settings: {zenoh_error_text(exc)}") from None
    return conf


def effective_settings(conf: zenoh.Config) -> dict[str, Any]:
    """What the session will actually use, for the start-up log line."""
    import zenoh

    out: dict[str, Any] = {}
    for key in ("mode", "listen/endpoints", "connect/endpoints", "scouting/multicast/enabled",
                "access_control/enabled"):
        try:
            out[key] = json.loads(conf.get_json(key))
        except (zenoh.ZError, ValueError):  # a key this Zenoh version lacks is not shown
            continue
    mode = out.get("mode", "peer")
    for key, value in out.items():
        # Zenoh's defaults depend on the mode ({"router": [...], "peer": [...]}): the log
        # shows this mode's (a client listens on nothing, it has no "router" listener)
        if isinstance(value, dict) and set(value) <= {"router", "peer", "client"}:
            out[key] = value.get(mode, [] if key.endswith("endpoints") else None)
    return out


def open_session(settings: ZenohConfig, purpose: str = "daemon", timestamping: bool = False) -> zenoh.Session:
    """Open the session; a Zenoh failure (port in use, bad file, bad TLS) is a ConfigError."""
    import zenoh

    conf = build_zenoh_config(settings, timestamping)
    log.info("zenoh settings", purpose=purpose, **{k.replace("/", "."): v for k, v in effective_settings(conf).items()})
    try:
        session = zenoh.open(conf)
    except zenoh.ZError as exc:
        where = ", ".join((*settings.listen, *settings.connect)) or "default endpoints"
        if settings.mode == "client" and "Unable to connect" in str(exc):
            raise ZenohUnreachable(
                f"no Zenoh router answers on {where}: {zenoh_error_text(exc)}; is the router running?"
            ) from None
        raise ConfigError(
            f"cannot open the Zenoh session ({settings.mode}, {where}): {zenoh_error_text(exc)}; "
            "check the endpoints (is the port in use?) and the Zenoh config file"
        ) from None
    log.info("zenoh session open", purpose=purpose, zid=str(session.zid()))
    return session
