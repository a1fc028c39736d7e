"""Hostile Zenoh traffic against a running daemon (issue 8, bad input).

The daemon runs in this process on the scripted camera of tests/test_daemon_loop.py (the
cube in view, real target-pose and tracker code, real Zenoh on loopback). A second
session, the intruder, sends the ``reset`` and ``calibration`` queryables garbage
payloads, garbage parameters and attachments, wildcard selectors, a flood of queries it
never waits for, and fake poses on the daemon's own keys. Afterwards the daemon must
still run, publish poses and status, and answer a plain query; and only an exact
``cubeloc/<name>/reset`` may reset it.
"""

from __future__ import annotations

import json
import os
import time

import numpy as np
import pytest
import yaml
from helpers import Listener
from test_daemon_loop import CAMERA_POSITION, Script, make_prepared, start_daemon

from cubeloc.fakes import render_view
from cubeloc.net import free_port
from cubeloc.positioning.geometry import look_at

NAME = "looptest"  # make_prepared's daemon name

GARBAGE_PAYLOADS = [
    b"", b"\x00", bytes(range(256)), os.urandom(4096), b"\xff\xfe" * 500, b'{"reset": "yes", "__proto__": 1}',
    b"[" * 10_000, "ünïcødé \u202e".encode(), os.urandom(1 << 20),  # one megabyte of noise
]
GARBAGE_PARAMETERS = ["a=b", ";;;;", "%ff%fe%00", "x" * 10_000, "reset=true;force", "=", "_time=[..]", "a=" + "b" * 5000]


@pytest.fixture(scope="module")
def cube_image():
    return render_view(look_at(CAMERA_POSITION, np.zeros(3)), room=False)


@pytest.fixture(scope="module")
def daemon_and_intruder(tmp_path_factory, cube_image):
    """One daemon for the module's tests (they run in file order, each leaves it serving)."""
    port = free_port()
    prepared = make_prepared(tmp_path_factory.mktemp("hostile"), port)
    daemon, stop, thread, outcome = start_daemon(prepared, Script(cube_image, [100_000]))
    resets: list[float] = []
    loop_reset = daemon.processor.reset
    daemon.processor.reset = lambda: (resets.append(time.monotonic()), loop_reset())[1]
    listener = Listener(port)  # a well-behaved subscriber
    intruder = Listener(port).session  # a peer on the same network, up to no good
    try:
        assert listener.wait_for(lambda: len(listener.poses) >= 3, 60), listener.status[-1:]
        yield daemon, listener, intruder, resets
    finally:
        stop.set()
        thread.join(5.0)
        intruder.close()
        listener.session.close()
    assert not thread.is_alive() and outcome.get("code") == 0


def replies(session, selector: str, **kwargs) -> list:
    return list(session.get(selector, timeout=3.0, **kwargs))


def still_serving(daemon, listener) -> None:
    """Poses and status keep coming, a plain query is answered, the loop had no error."""
    poses, status = len(listener.poses), len(listener.status)
    assert listener.wait_for(lambda: len(listener.poses) > poses + 3 and len(listener.status) > status, 20)
    assert daemon.capture.is_alive() and daemon.stats.processor_errors == 0
    calibration = yaml.safe_load(listener.query(f"cubeloc/{NAME}/calibration")[0])
    assert calibration["image_width"] == 1280
    pose = listener.poses[-1]
    assert all(np.isfinite(pose["position"])) and np.linalg.norm(np.array(pose["position"]) - CAMERA_POSITION) < 0.01


def test_garbage_queries_do_not_hurt_the_daemon(daemon_and_intruder):
    daemon, listener, session, resets = daemon_and_intruder
    for key in ("calibration", "reset"):
        for payload in GARBAGE_PAYLOADS:
            got = replies(session, f"cubeloc/{NAME}/{key}", payload=payload, attachment=payload[:1000])
            assert len(got) == 1 and got[0].ok is not None, (key, payload[:20])
        for parameters in GARBAGE_PARAMETERS[:: 1 if key == "calibration" else 2]:
            got = replies(session, f"cubeloc/{NAME}/{key}?{parameters}")
            assert len(got) == 1 and got[0].ok is not None, (key, parameters[:20])
    # Whatever came with it, a reset query gets the one well-formed answer.
    answer = replies(session, f"cubeloc/{NAME}/reset", payload=os.urandom(64))[0].ok
    assert str(answer.key_expr) == f"cubeloc/{NAME}/reset"
    assert json.loads(answer.payload.to_bytes()) == {"reset": True}
    still_serving(daemon, listener)


def test_wildcard_selectors_do_not_reset(daemon_and_intruder):
    """A monitoring tool that asks ``cubeloc/**`` (or ``cubeloc/*/*``) for everything
    must not reset every daemon it reaches: only the exact reset key does."""
    daemon, listener, session, resets = daemon_and_intruder
    before = len(resets)
    for selector in ("cubeloc/**", "cubeloc/*/*", f"cubeloc/{NAME}/*", "**", f"cubeloc/{NAME}/res$*", "cubeloc/*/reset"):
        for reply in replies(session, selector):
            if reply.ok is None:
                continue
            key = str(reply.ok.key_expr)
            # Replies name the concrete key of the daemon that answered, never the wildcard.
            assert key in (f"cubeloc/{NAME}/calibration", f"cubeloc/{NAME}/reset"), (selector, key)
            if key.endswith("/reset"):
                assert json.loads(reply.ok.payload.to_bytes())["reset"] is False
    assert len(resets) == before
    replies(session, f"cubeloc/{NAME}/reset")
    assert len(resets) == before + 1
    still_serving(daemon, listener)


def test_query_flood_and_fake_publications(daemon_and_intruder):
    daemon, listener, session, resets = daemon_and_intruder
    # 120 queries fired without waiting for the answers (each gets its own handler).
    pending = [session.get(f"cubeloc/{NAME}/{'reset' if i % 10 == 0 else 'calibration'}",
                           payload=os.urandom(256), timeout=5.0) for i in range(120)]
    # Fake poses and junk on the daemon's own keys: Zenoh lets any peer publish there
    # unless access control says otherwise (tests/test_security_zenoh.py); the daemon
    # itself must simply not care.
    for i in range(120):
        session.put(f"cubeloc/{NAME}/{('pose', 'status', 'reset', 'calibration')[i % 4]}", os.urandom(512))
    for handler in pending:
        for _ in handler:
            pass
    still_serving(daemon, listener)
    assert len(resets) >= 1  # the reset queries were served (coalesced), none wedged the loop
