"""``cubeloc demo``, as the README's first command runs it (shortened)."""

from __future__ import annotations

import re


def test_demo_prints_poses_live_and_an_accuracy_summary(cli):
    result = cli("demo", "--seconds", "4", timeout=240)
    assert result.returncode == 0, result.stderr[-2000:]
    out = result.stdout
    pose_lines = [line for line in out.splitlines() if line.startswith("demo  pose  seq")]
    assert len(pose_lines) >= 3, out
    assert "cubeloc demo: summary" in out
    rms = re.search(r"position error vs ground truth: RMS ([\d.]+) mm, median ([\d.]+) mm, max ([\d.]+) mm over (\d+) poses", out)
    assert rms, out
    rms_mm, median_mm, _, count = float(rms[1]), float(rms[2]), float(rms[3]), int(rms[4])
    # The start of the paper's path: the cube ~2.3 m away, three faces in view.
    assert count == len(pose_lines) and median_mm < 2.0 and rms_mm < 10.0, out
    assert re.search(r"rate:\s+[\d.]+ frames/s processed", out)
    assert "Traceback" not in result.stderr
