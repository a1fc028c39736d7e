"""Process faults: ``kill -9`` at random moments (seeded) while a calibration is saved and while
a sequence is recorded, and SIGTERM while ``cubeloc calibrate`` writes its results.

The kills use a forked child running the real writers (``calib.camera_info.write_camera_info``,
``drivers.sequence.SequenceWriter``) in a loop, so that a few dozen kills take a second or
two instead of a few dozen interpreter start-ups; the child says when its first write is
done (a pipe), so every kill lands in a writing loop. (SIGTERM during ``record``, and
SIGTERM and ``kill -9`` at three moments of a calibration save, are in
test_replay_record.py and test_calib_files.py; this file adds the random moments.)
"""

from __future__ import annotations

import os
import random
import select
import signal
import subprocess
import sys
import time

import numpy as np
import pytest

from cubeloc.calib.boards import parse_board
from cubeloc.calib.camera_info import (
    CameraCalibration,
    read_camera_info,
    to_yaml,
    write_camera_info,
)
from cubeloc.drivers.sequence import SequenceWriter, read_image, read_sequence_index
from cubeloc.fakes.board_views import board_views, synthetic_board_camera
from tests.conftest import REPO

KILLS = 20
SEED = 8


def calibration(version: int) -> CameraCalibration:
    k = np.array([[800.0 + version, 0, 320], [0, 801.0 + version, 240], [0, 0, 1]])
    metadata = {"version": version, "per_view_rms_px": {f"view_{j:03d}.png": 0.1 + version for j in range(300)}}
    return CameraCalibration(640, 480, k, [0.01 * version, 0, 0, 0, 0], metadata=metadata)


def kill_child_at_random(body, rng: random.Random, max_delay_s: float) -> None:
    """Fork; the child runs ``body(ready)`` (it calls ``ready()`` after its first write and
    then writes on forever); kill -9 it a random time after that."""
    read_end, write_end = os.pipe()
    pid = os.fork()
    if pid == 0:  # the child: never returns into pytest
        try:
            os.close(read_end)
            body(lambda: os.write(write_end, b"1"))
        finally:
            os._exit(0)
    os.close(write_end)
    try:
        ready, _, _ = select.select([read_end], [], [], 30)
        assert ready and os.read(read_end, 1) == b"1", "the writer did not start"
        time.sleep(rng.uniform(0.0, max_delay_s))  # where in its loop the kill lands
        os.kill(pid, signal.SIGKILL)
        _, status = os.waitpid(pid, 0)
        assert os.WIFSIGNALED(status) and os.WTERMSIG(status) == signal.SIGKILL
    finally:
        os.close(read_end)


def test_kill_9_at_random_moments_during_calibration_save_leaves_the_old_or_the_new_file(tmp_path):
    path = tmp_path / "camera.yaml"
    versions = {v: to_yaml(calibration(v)) for v in (1, 2)}
    write_camera_info(path, calibration(1))
    rng = random.Random(SEED)
    seen = set()

    def save_forever(ready) -> None:
        version = 2
        while True:
            write_camera_info(path, calibration(version))
            ready()
            version = 3 - version  # 2, 1, 2, ...: every save replaces the file with the other

    for _ in range(KILLS):
        kill_child_at_random(save_forever, rng, max_delay_s=0.06)  # a few saves
        text = path.read_text()
        assert text in versions.values(), "a broken calibration file after kill -9"
        loaded = read_camera_info(path)  # and the reader agrees
        seen.add(loaded.metadata["version"])
        assert loaded.fx == 800.0 + loaded.metadata["version"]
    assert seen == {1, 2}  # the kills landed at different points of the loop
    leftovers = [p.name for p in tmp_path.iterdir() if p.name != "camera.yaml"]
    assert all(name.startswith(".camera.yaml.") and name.endswith(".tmp") for name in leftovers), leftovers


def test_kill_9_at_random_moments_during_record_leaves_a_readable_sequence(tmp_path):
    rng = random.Random(SEED + 1)
    images = [np.random.default_rng(i).integers(0, 255, (96, 128), dtype=np.uint8) for i in range(4)]
    for attempt in range(20):
        out = tmp_path / f"seq{attempt}"

        def record_forever(ready, out=out) -> None:
            with SequenceWriter(out) as writer:
                k = 0
                while True:
                    k += 1
                    writer.write(1_000_000_000 + k * 50_000_000, images[k % len(images)])
                    if k == 1:
                        ready()

        kill_child_at_random(record_forever, rng, max_delay_s=0.05)
        entries = read_sequence_index(out)  # the CSV names only whole frames
        assert len(entries) >= 1
        for index, entry in enumerate(entries, start=1):
            assert entry.stamp_ns == 1_000_000_000 + index * 50_000_000
            np.testing.assert_array_equal(read_image(entry.path), images[index % len(images)])


@pytest.fixture(scope="module")
def board_sequence(tmp_path_factory):
    sequence = tmp_path_factory.mktemp("boards") / "seq"
    board = "chessboard:9x6:0.025"  # renders in a fraction of the time a ChArUco board takes
    # supersample 1: the ray grid of a finer one alone takes seconds to build
    views = board_views(parse_board(board), synthetic_board_camera(480, 384), 8, seed=6, supersample=1)
    with SequenceWriter(sequence) as writer:
        for index, view in enumerate(views, start=1):
            writer.write(1_700_000_000_000_000_000 + index * 100_000_000, view.image)
    return sequence, board


def test_sigterm_while_calibrate_writes_finishes_the_writes(board_sequence, tmp_path):
    sequence, board = board_sequence
    out = tmp_path / "live.yaml"
    process = subprocess.Popen(
        [sys.executable, "-m", "cubeloc.daemon.cli", "calibrate", "--camera", f"replay:{sequence}",
         "--board", board, "--out", str(out), "--min-views", "6", "--max-views", "8"],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, cwd=REPO,
    )
    try:
        for line in process.stdout:
            if line.startswith("capture ended"):  # next: solve, then write views, report, calibration
                process.send_signal(signal.SIGTERM)
                break
        stdout, stderr = process.communicate(timeout=120)
    finally:
        if process.poll() is None:
            process.kill()
    assert process.returncode == 0, f"exit {process.returncode}: {stderr[-2000:]}"
    assert "wrote" in stdout and "Traceback" not in stderr
    calibration_written = read_camera_info(out)
    views = out.with_name("live.views")
    images = sorted(p.name for p in views.glob("view_*.png"))
    assert len(images) == calibration_written.metadata["views"] + len(calibration_written.metadata["dropped"])
    assert out.with_name("live.report.png").stat().st_size > 0
    assert not [p.name for p in tmp_path.iterdir() if p.name.startswith(".")]  # no staging left behind
