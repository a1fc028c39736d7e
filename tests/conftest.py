"""Shared fixtures. Test data is made by helpers in one call, on real files in tmp_path."""

from __future__ import annotations

import os
import socket
import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
SHARED = REPO.parent / "shared"


def real_photographs(name: str) -> Path:
    """``../shared/data/NAME``, the real photographs beside the repository. Missing: under
    CI (``CI`` set) the test fails, so that a green run always includes them; elsewhere it
    is skipped with the reason, and the session's summary says so in capitals."""
    path = SHARED / "data" / name
    if not path.is_dir():
        message = f"REAL PHOTOGRAPHS NOT FOUND: {path} (the tests read ../shared beside the repository)"
        if os.environ.get("CI"):
            pytest.fail(message, pytrace=False)
        MISSING_PHOTOGRAPHS.add(str(path))
        pytest.skip(message)
    return path


MISSING_PHOTOGRAPHS: set[str] = set()


def pytest_terminal_summary(terminalreporter):
    for path in sorted(MISSING_PHOTOGRAPHS):
        terminalreporter.write_line(f"WARNING: tests on real photographs were SKIPPED: {path} not found", red=True,
                                    bold=True)


def run_cli(*args: str, timeout: float = 120, **kwargs) -> subprocess.CompletedProcess:
    """Run ``cubeloc ARGS`` in a fresh interpreter, as a user would."""
    return subprocess.run(
        [sys.executable, "-m", "cubeloc.daemon.cli", *args],
        capture_output=True,
        text=True,
        timeout=timeout,
        **kwargs,
    )


@pytest.fixture
def cli():
    return run_cli


# Aravis' GigE Vision fake camera must own 127.0.0.1:3956 (GVCP), so at most one may run
# on the machine. Every test of a module that starts one is marked ``gv_fake``: ``make
# test`` runs the rest on both cores (pytest-xdist) and, alongside them in a network
# namespace of its own, these one at a time.
# (xdist's own ``--dist loadgroup`` does not group with pytest 9.2: it renames
# ``item._nodeid``, which pytest no longer reads.)
GV_FAKE_MARKERS = ("gv_fake", "GvFake")


def _starts_gv_fake(path: Path, cache: dict[Path, bool] = {}) -> bool:  # noqa: B006 - a per-session memo
    if path not in cache:
        text = path.read_text(encoding="utf-8") if path.suffix == ".py" else ""
        cache[path] = any(marker in text for marker in GV_FAKE_MARKERS)
    return cache[path]


def _touches_aravis(path: Path, cache: dict[Path, bool] = {}) -> bool:  # noqa: B006 - a per-session memo
    if path not in cache:
        text = path.read_text(encoding="utf-8") if path.suffix == ".py" else ""
        # the backend by name, or the verbs that run Aravis' discovery
        cache[path] = any(word in text for word in ("aravis", "Aravis", '"doctor"', '"devices"', *GV_FAKE_MARKERS))
    return cache[path]


def non_loopback_interfaces() -> list[str]:
    return [name for _, name in socket.if_nameindex() if name != "lo"]


# The tests ``make test-fast`` leaves out (measured, see the file's header).
SLOW_TESTS = frozenset(line.strip() for line in (Path(__file__).parent / "slow_tests.txt").read_text().splitlines()
                       if line.strip() and not line.startswith("#"))


def pytest_collection_modifyitems(config, items):
    for item in items:
        path = Path(str(item.fspath))
        if item.nodeid.split("[")[0] in SLOW_TESTS:
            item.add_marker(pytest.mark.slow)
        if _starts_gv_fake(path):
            item.add_marker(pytest.mark.gv_fake)
        if _touches_aravis(path):
            item.add_marker(pytest.mark.loopback_only)


@pytest.fixture(autouse=True)
def _loopback_only(request):
    """Aravis' discovery broadcasts on every interface: a test of a module that touches
    Aravis runs only where loopback is the one interface (``make test`` sees to it)."""
    if request.node.get_closest_marker("loopback_only") is not None:
        others = non_loopback_interfaces()
        if others:
            pytest.fail(f"this test touches Aravis, whose discovery broadcasts on {', '.join(others)}: run it "
                        "in a loopback-only network namespace (make test, or scripts/loopback-only "
                        ".venv/bin/python -m pytest ...)", pytrace=False)


@pytest.fixture
def listeners():
    """Listener sessions, always closed (an open Zenoh session keeps the interpreter alive)."""
    from helpers import Listener

    made = []
    yield lambda port: made.append(Listener(port)) or made[-1]
    for listener in made:
        listener.session.close()
