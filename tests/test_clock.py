"""The device-clock mapping and the frame accounting: pure, on seeded and recorded data."""

from __future__ import annotations

import numpy as np
import pytest

from cubeloc.drivers.base import CaptureStats
from cubeloc.drivers.clock import DeviceClockMapper
from cubeloc.drivers.frame_accounting import FrameAccounting, Verdict

MS = 1_000_000


def test_running_minimum_removes_latency_jitter():
    rng = np.random.default_rng(1)
    device_epoch_to_host = 1_790_000_000_000_000_000 - 5_000 * MS  # host = device + this
    base_latency = 2 * MS
    mapper = DeviceClockMapper(window_ns=10_000 * MS)
    errors = []
    for k in range(600):  # 20 s at 30 Hz
        device_ns = 5_000 * MS + k * 33 * MS
        true_host = device_ns + device_epoch_to_host
        jitter = int(rng.exponential(3 * MS))  # heavy-tailed, like a busy host
        receipt = true_host + base_latency + jitter
        mapping = mapper.map(device_ns, receipt)
        assert mapping.stamp_ns <= receipt
        if k >= 30:  # after a second of samples
            errors.append(mapping.stamp_ns - true_host)
    errors = np.array(errors)
    # The stamp is late by the minimum latency (2 ms) plus the smallest jitter seen in the
    # window: well under the mean jitter (3 ms), and nearly constant frame to frame.
    assert base_latency <= errors.min()
    assert errors.max() < base_latency + 0.5 * MS
    assert np.std(np.diff(errors)) < 0.1 * MS
    naive = np.std(rng.exponential(3 * MS, 500))
    assert np.std(errors) < naive / 20


def test_window_follows_drift():
    mapper = DeviceClockMapper(window_ns=2_000 * MS)
    drift = 50e-6  # device clock 50 ppm slow
    worst = 0
    for k in range(3000):  # 100 s
        device_ns = k * 33 * MS
        true_host = 10**18 + int(device_ns * (1 + drift))
        mapping = mapper.map(device_ns, true_host + MS)
        if k > 100:
            worst = max(worst, abs(mapping.stamp_ns - true_host - MS))
    # Without the window the offset would lag by 50 ppm * 100 s = 5 ms.
    assert worst < 0.2 * MS


def test_device_clock_reset_clears_the_window():
    mapper = DeviceClockMapper()
    for k in range(10):
        mapper.map(1_000 * MS + k * 10 * MS, 10**18 + k * 10 * MS)
    mapping = mapper.map(5 * MS, 10**18 + 200 * MS)  # device rebooted: its clock restarted
    assert mapping.reset and mapper.resets == 1
    assert mapping.stamp_ns == 10**18 + 200 * MS  # the new offset, not the old one


def test_host_clock_step_forward_is_taken_after_a_few_frames():
    mapper = DeviceClockMapper(step_ns=1_000 * MS, step_samples=5)
    for k in range(20):
        mapper.map(k * 10 * MS, 10**18 + k * 10 * MS + MS)
    step = 3_600_000 * MS  # NTP stepped the host clock an hour ahead
    stamps = [mapper.map((20 + k) * 10 * MS, 10**18 + step + (20 + k) * 10 * MS + MS).stamp_ns
              for k in range(6)]
    assert stamps[0] < 10**18 + step  # one late frame is latency, not a step
    assert stamps[-1] == 10**18 + step + 25 * 10 * MS + MS


def test_mapper_rejects_bad_parameters():
    with pytest.raises(ValueError):
        DeviceClockMapper(window_ns=0)


def judge_all(buffers, accounting=None):
    accounting = accounting or FrameAccounting(CaptureStats())
    verdicts = [accounting.judge(ok, frame_id, stamp) for ok, frame_id, stamp in buffers]
    return accounting, verdicts


def test_gigE_16_bit_block_id_wrap_is_not_a_gap():
    ids = [65533, 65534, 65535, 1, 2, 3]  # GigE Vision 1.x: 0 is never used
    accounting, verdicts = judge_all([(True, i, (n + 1) * MS) for n, i in enumerate(ids)])
    assert verdicts == [Verdict.ACCEPT] * 6
    assert accounting.stats.frame_id_gaps == 0 and accounting.stats.delivered == 6


def test_gaps_counted_across_the_wrap_and_64_bit_ids():
    ids = [65530, 65534, 2, 3]  # missing 65531-65533, 65535, 1
    accounting, _ = judge_all([(True, i, (n + 1) * MS) for n, i in enumerate(ids)])
    assert accounting.stats.frame_id_gaps == 3 + 1 + 1
    big = [2**40, 2**40 + 1, 2**40 + 5]  # USB3 Vision / GEV2 64-bit ids
    accounting, _ = judge_all([(True, i, (n + 1) * MS) for n, i in enumerate(big)])
    assert accounting.stats.frame_id_gaps == 3


def test_bad_timestamps_and_status_are_dropped_and_counted():
    buffers = [
        (True, 10, 100 * MS),
        (True, 11, 0),  # zero timestamp
        (True, 12, 90 * MS),  # went backwards
        (True, 13, 100 * MS),  # repeated
        (False, 14, 140 * MS),  # missing packets
        (False, 12, 150 * MS),  # a failed buffer with a stale id: not a reset, not a gap
        (True, 16, 160 * MS),  # 15 never arrived
    ]
    accounting, verdicts = judge_all(buffers)
    assert verdicts == [Verdict.ACCEPT, Verdict.BAD_TIMESTAMP, Verdict.BAD_TIMESTAMP,
                        Verdict.BAD_TIMESTAMP, Verdict.INCOMPLETE, Verdict.INCOMPLETE, Verdict.ACCEPT]
    stats = accounting.stats
    assert (stats.delivered, stats.bad_timestamp, stats.incomplete, stats.frame_id_gaps) == (2, 3, 2, 1)
    assert stats.dropped == 6
    assert accounting.id_resets == 0


def test_counter_reset_is_not_counted_as_loss():
    accounting, _ = judge_all([(True, 500, MS), (True, 501, 2 * MS), (True, 1, 3 * MS), (True, 2, 4 * MS)])
    assert accounting.stats.frame_id_gaps == 0 and accounting.id_resets == 1
    accounting.restart()  # acquisition restarted: the next id starts afresh
    accounting.judge(True, 900, MS)
    assert accounting.stats.frame_id_gaps == 0 and accounting.stats.delivered == 5
