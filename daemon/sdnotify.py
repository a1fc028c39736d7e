"""systemd notifications (``Type=notify``) over the documented datagram socket protocol.

``sd_notify(3)``: send newline-separated ``KEY=VALUE`` assignments in one datagram to the
AF_UNIX socket named by ``$NOTIFY_SOCKET`` (a leading ``@`` means the abstract namespace).
Without ``NOTIFY_SOCKET`` (not under systemd) every call does nothing.

Who calls what (see daemon/pipeline.py): READY=1 once the camera streams, the Zenoh session
is open and a first frame went through; WATCHDOG=1 (before READY: EXTEND_TIMEOUT_USEC=)
only from the processing loop when it made progress, never from a timer thread, so a hung
loop gets the service restarted.
"""

from __future__ import annotations

import os
import socket
import time

import structlog

log = structlog.get_logger()

# Before READY, each sign of progress moves the start deadline this far into the future.
EXTEND_START_TIMEOUT_US = 30_000_000


class SystemdNotifier:
    def __init__(self, environ: dict[str, str] | None = None) -> None:
        environ = dict(os.environ if environ is None else environ)
        address = environ.get("NOTIFY_SOCKET", "")
        self._address: str | bytes | None = None
        if address.startswith("@"):
            self._address = b"\0" + address[1:].encode()
        elif address.startswith("/"):
            self._address = address
        self._socket: socket.socket | None = None
        if self._address is not None:
            self._socket = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM | socket.SOCK_CLOEXEC)
            # Never block the loop on a full socket (a datagram queue holds only ~10 by
            # default): a message that does not fit is dropped; READY is retried.
            self._socket.setblocking(False)
        # The watchdog applies to us only if WATCHDOG_PID is unset or names this process.
        watchdog_pid = environ.get("WATCHDOG_PID")
        usec = environ.get("WATCHDOG_USEC", "")
        self.watchdog_interval_s: float | None = None
        if usec.isdigit() and int(usec) > 0 and (not watchdog_pid or watchdog_pid == str(os.getpid())):
            self.watchdog_interval_s = int(usec) / 1e6
        self._last_watchdog = float("-inf")
        self._last_status = ""
        self.ready_sent = False

    @property
    def enabled(self) -> bool:
        return self._socket is not None

    def notify(self, **assignments: str | int) -> bool:
        """Send ``KEY=VALUE`` lines (keyword names are upper-cased). True if sent."""
        if self._socket is None:
            return False
        message = "\n".join(f"{key.upper()}={value}" for key, value in assignments.items())
        try:
            self._socket.sendto(message.encode("utf-8"), self._address)
        except BlockingIOError:
            log.debug("sd_notify dropped: the socket is full", message=message)
            return False
        except OSError as exc:
            # systemd gone or socket not writable: the daemon itself keeps working.
            log.warning("sd_notify failed", error=str(exc))
            return False
        return True

    def ready(self, status: str) -> None:
        if not self.ready_sent:
            self.ready_sent = self.notify(ready=1, status=status) or not self.enabled
            self._last_status = status

    def status(self, text: str) -> None:
        if text != self._last_status:
            self._last_status = text
            self.notify(status=text)

    def watchdog(self) -> None:
        """Say the loop made progress; rate-limited to a quarter of the interval (or 1 s).

        After READY it is WATCHDOG=1. Before READY (no camera yet: systemd's watchdog is
        not armed until start-up completes) it extends the start timeout instead, so a
        daemon waiting for its camera stays up while a hung one still hits TimeoutStartSec.
        """
        if self._socket is None:
            return
        now = time.monotonic()
        period = self.watchdog_interval_s / 4 if self.watchdog_interval_s else 1.0
        if now - self._last_watchdog >= period:
            self._last_watchdog = now
            if self.ready_sent:
                self.notify(watchdog=1)
            else:
                self.notify(extend_timeout_usec=EXTEND_START_TIMEOUT_US)

    def stopping(self) -> None:
        self.notify(stopping=1, status="stopping")

    def close(self) -> None:
        if self._socket is not None:
            self._socket.close()
            self._socket = None
