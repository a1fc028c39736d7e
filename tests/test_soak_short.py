"""The soak's checks (``cubeloc.daemon.soak``, ``make soak`` runs them for 30 minutes) on a short run:
the daemon on pre-rendered frames at the camera's full rate with the cable pulled twice,
every pose checked against the ground truth, RSS, threads and fds sampled. A leak fast
enough to show in 12 seconds, a reconnect that leaves a thread or a socket behind, or a
wrong pose fails here; slower leaks are for the long run."""

from __future__ import annotations

from cubeloc.daemon.soak import run_soak


def test_short_soak_no_leak_steady_rate_no_wrong_pose():
    result = run_soak(12.0, fps=10.0, images=6, sample_s=1.0, warmup_s=3.0, unplug_every_s=4.0, room=False)
    report = "\n".join(f"{'pass' if ok else 'FAIL'} {name}: {text}" for name, (ok, text) in result.checks.items())
    assert result.unplugs >= 2, report
    assert result.ok, report
    assert result.poses_received >= 30, report  # poses flowed all along (120 frames from the camera)
