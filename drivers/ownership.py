"""One process owns a camera: an flock'ed lock file per camera.

A GigE Vision camera grants control to one host application at a time and a USB3 Vision
interface can be claimed once; a second opener would otherwise fail later with a register
write timeout or a libusb "busy" that says nothing about who holds the camera. So each
opener takes an exclusive ``flock`` on ``<lock dir>/cubeloc-camera-<id>.lock`` first and
writes its pid and command line into it; the second opener reads them back and says who
to stop. The kernel releases an flock when its holder dies, so a crash never leaves a
stale lock (the file stays; its content is only informative).

Lock directory: ``$CUBELOC_LOCK_DIR``, else ``/run/lock`` (shared by every user and
service on the machine), else a directory in the system temp dir when ``/run/lock`` is
not writable.
"""

from __future__ import annotations

import contextlib
import fcntl
import os
import re
import tempfile
from pathlib import Path

import structlog

from cubeloc.drivers.base import CameraBusy

log = structlog.get_logger()

LOCK_DIR_ENV = "CUBELOC_LOCK_DIR"
SYSTEM_LOCK_DIR = Path("/run/lock")


def lock_dir() -> Path:
    """The directory holding camera lock files (created if needed)."""
    configured = os.environ.get(LOCK_DIR_ENV)
    if configured:
        path = Path(configured)
        path.mkdir(parents=True, exist_ok=True)
        return path
    if SYSTEM_LOCK_DIR.is_dir() and os.access(SYSTEM_LOCK_DIR, os.W_OK | os.X_OK):
        return SYSTEM_LOCK_DIR
    path = Path(tempfile.gettempdir()) / "cubeloc-locks"
    path.mkdir(mode=0o1777, exist_ok=True)
    return path


def lock_path(camera_key: str) -> Path:
    safe = re.sub(r"[^A-Za-z0-9._-]", "_", camera_key) or "_"
    return lock_dir() / f"cubeloc-camera-{safe}.lock"


def _holder_of(path: Path) -> tuple[int | None, str]:
    try:
        lines = path.read_text(encoding="utf-8", errors="replace").splitlines()
    except OSError:
        return None, ""
    pid = int(lines[0]) if lines and lines[0].strip().isdigit() else None
    return pid, lines[1].strip() if len(lines) > 1 else ""


def _own_command_line() -> str:
    try:
        raw = Path(f"/proc/{os.getpid()}/cmdline").read_bytes()
        return " ".join(part.decode(errors="replace") for part in raw.split(b"\0") if part)
    except OSError:
        return ""


def busy_message(camera_key: str, pid: int | None, command: str) -> str:
    if pid is None:
        return (f"camera {camera_key} is held by another process (lock {lock_path(camera_key)}); "
                "stop it with 'systemctl stop cubeloc' or find it with 'fuser -v' on that file")
    what = f" ({_short(command)})" if command else ""
    return (f"camera {camera_key} is held by pid {pid}{what}; "
            f"stop it with 'systemctl stop cubeloc' or 'kill {pid}'")


def _short(command: str) -> str:
    """'cubeloc run' rather than '/usr/bin/python3 /opt/venv/bin/cubeloc run --config ...'."""
    words = command.split()
    for index, word in enumerate(words):
        name = os.path.basename(word)
        from_module = name == "-m" and words[index + 1:index + 2] == ["cubeloc.daemon.cli"]
        if name == "cubeloc" or from_module:
            rest = words[index + 2:] if from_module else words[index + 1:]
            verb = next((w for w in rest if not w.startswith("-")), "")
            return f"cubeloc {verb}".strip()
    return command if len(command) <= 60 else command[:57] + "..."


class CameraLock:
    """An exclusive, non-blocking lock on one camera, held until ``release()``."""

    def __init__(self, camera_key: str) -> None:
        self.camera_key = camera_key
        self.path = lock_path(camera_key)
        self._fd: int | None = None

    @property
    def held(self) -> bool:
        return self._fd is not None

    def acquire(self) -> None:
        """Take the lock or raise CameraBusy naming the holder."""
        if self._fd is not None:
            return
        try:
            fd = os.open(self.path, os.O_RDWR | os.O_CREAT | os.O_CLOEXEC, 0o664)
            writable = True
        except PermissionError:
            # Another user's lock file in a shared directory: flock works on a read-only fd.
            fd = os.open(self.path, os.O_RDONLY | os.O_CLOEXEC)
            writable = False
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            os.close(fd)
            raise CameraBusy(busy_message(self.camera_key, *_holder_of(self.path))) from None
        if writable:
            os.ftruncate(fd, 0)
            os.pwrite(fd, f"{os.getpid()}\n{_own_command_line()}\n".encode(), 0)
        self._fd = fd
        log.debug("camera lock taken", camera=self.camera_key, path=str(self.path))

    def release(self) -> None:
        """Release the lock. Safe to call twice."""
        if self._fd is None:
            return
        fd, self._fd = self._fd, None
        with contextlib.suppress(OSError):
            os.ftruncate(fd, 0)  # no stale pid for the next reader
        os.close(fd)  # closing the last fd releases the flock

    def __enter__(self) -> CameraLock:
        self.acquire()
        return self

    def __exit__(self, *exc: object) -> None:
        self.release()
