"""The robot-motion scenarios of the synthetic camera (fakes/scenarios.py): each does what
its name promises (rates, lever arm, time out of view), and the effects reach the pixels
(motion blur integrated over the exposure, exposure steps, passers-by)."""

from __future__ import annotations

import numpy as np
import pytest
from helpers import half_resolution

from cubeloc.calib.camera_info import paper_camera
from cubeloc.fakes.camera import SyntheticCamera
from cubeloc.fakes.scenarios import TIMING, scenario_effects
from cubeloc.fakes.trajectories import make_trajectory
from cubeloc.positioning.target import make_cube

CUBE = np.concatenate([tag.corners for tag in make_cube().tags])


def kinematics(name: str, **kwargs):
    poses = make_trajectory(name, **kwargs)
    times = (np.array([p.stamp_ns for p in poses]) - poses[0].stamp_ns) / 1e9
    T = [p.T_world_camera for p in poses]
    dt = np.diff(times)
    rate = np.array([np.degrees(a.rotation_angle_to(b)) for a, b in zip(T, T[1:], strict=False)]) / dt
    speed = np.array([np.linalg.norm(b.translation - a.translation) for a, b in zip(T, T[1:], strict=False)]) / dt
    k = paper_camera().camera_matrix
    in_view = []
    for pose in T:
        c = pose.inverse().apply(CUBE)
        u = c[:, 0] / c[:, 2] * k[0, 0] + k[0, 2]
        v = c[:, 1] / c[:, 2] * k[1, 1] + k[1, 2]
        in_view.append(bool(np.all(c[:, 2] > 0) and np.all((u > 0) & (u < 1280) & (v > 0) & (v < 1024))))
    return times, T, rate, speed, np.array(in_view)


def longest_run(flags: np.ndarray) -> int:
    best = run = 0
    for f in flags:
        run = run + 1 if f else 0
        best = max(best, run)
    return best


def test_turn_after_init_turns_away_briskly_driving_then_laps_the_room_and_returns():
    times, T, rate, speed, in_view = kinematics("turn_after_init")
    assert in_view[:30].all() and in_view[-10:].all()  # initialises on the cube, comes back to it
    turn = (times[1:] > 3.0) & (times[1:] < 6.5)
    assert 30 <= rate[turn].max() <= 60  # deg/s
    headings = [np.degrees(np.arctan2(pose.rotation[1, 2], pose.rotation[0, 2])) for pose in (T[30], T[60])]
    assert 90 <= (headings[0] - headings[1]) % 360 <= 120  # turned right by that much
    assert np.median(speed[turn]) >= 0.1 and speed[turn].max() <= 0.3
    assert longest_run(~in_view) / 10.0 >= 60  # a lap of the room without the cube


@pytest.mark.parametrize("name, lever_m, rate_deg_s", [("spin_in_place", 0.2, 45), ("spin_in_place_fast", 0.2, 90),
                                                        ("spin_brisk", 0.2, 120), ("spin_on_axis", 0.0, 45)])
def test_spins_turn_on_the_spot_about_an_axis_behind_the_camera(name, lever_m, rate_deg_s):
    times, T, rate, _, in_view = kinematics(name)
    spinning = rate > 0.98 * rate_deg_s
    assert spinning.sum() > 5 and rate.max() <= rate_deg_s * 1.01
    assert times[np.argmax(spinning)] <= 3.5  # right after initialisation (2.5 s)
    centres = np.array([pose.translation for pose, s in zip(T, spinning, strict=False) if s])
    forward = np.array([pose.rotation[:, 2] for pose, s in zip(T, spinning, strict=False) if s])
    forward[:, 2] = 0
    forward /= np.linalg.norm(forward, axis=1)[:, None]
    axis = centres - lever_m * forward  # the same point for every pose: the robot's axis
    assert np.ptp(axis, axis=0).max() < 1e-6
    turned = sum(np.degrees(a.rotation_angle_to(b)) for a, b in zip(T, T[1:], strict=False))
    assert turned > 700  # two turns
    assert in_view[:20].all() and in_view[-5:].all()


def test_agile_swings_the_cube_in_and_out_of_view_at_30_fps():
    times, T, rate, _, in_view = kinematics("agile")
    assert np.allclose(np.diff(times), 1 / 30, atol=1e-6)
    assert 60 <= np.percentile(rate, 99) <= 90
    changes = np.count_nonzero(np.diff(in_view.astype(int)))
    assert changes >= 6  # in and out of view, again and again
    effects = scenario_effects("agile", make_trajectory("agile"))
    gains = [g for _, g in effects.gain_steps]
    assert effects.exposure_s == pytest.approx(0.004) and len(gains) >= 5
    assert min(gains) >= 0.7 and max(gains) <= 1.35


def test_long_lap_keeps_the_cube_out_of_view_for_80_s():
    times, _, _, speed, in_view = kinematics("long_lap")
    assert times[-1] >= 100 and longest_run(~in_view) / 10.0 >= 80
    assert in_view[:30].all() and in_view[-10:].all() and speed.max() < 0.5


def test_a_passer_by_crosses_over_the_cube_during_initialisation_and_the_others_at_half_a_metre_to_2_m():
    poses = make_trajectory("passers_by")
    effects = scenario_effects("passers_by", poses)
    camera = SyntheticCamera(poses, name="passers_by", calibration=half_resolution(), effects=effects)
    clear = SyntheticCamera(poses, name="passers_by", calibration=half_resolution())
    # 1.2 s in: the walker stands between the camera and the cube, hiding it
    frame = 12
    covered, bare = camera.render(frame), clear.render(frame)
    k = half_resolution().camera_matrix
    c = poses[frame].T_world_camera.inverse().apply(np.zeros((1, 3)))[0]
    u, v = int(c[0] / c[2] * k[0, 0] + k[0, 2]), int(c[1] / c[2] * k[1, 1] + k[1, 2])
    patch = (slice(v - 20, v + 20), slice(u - 20, u + 20))
    assert np.abs(covered[patch].astype(float) - bare[patch]).mean() > 20
    distances = []
    for walker in effects.walkers:
        t = (walker.t0 + walker.t1) / 2
        i = int(round(t * 10))
        centre = np.array([*walker.start, 0.0]) + np.array([*walker.velocity, 0.0]) * (t - walker.t0)
        distances.append(np.linalg.norm((centre - poses[i].T_world_camera.translation)[:2]))
    assert len(distances) == 3 and min(distances) >= 0.5 and max(distances) <= 2.0


def test_motion_blur_is_integrated_over_the_exposure_and_gain_steps_change_the_brightness():
    poses = make_trajectory("agile")
    effects = scenario_effects("agile", poses)
    camera = SyntheticCamera(poses, name="agile", calibration=half_resolution(), effects=effects, seed=1)
    still = SyntheticCamera(poses, name="agile", calibration=half_resolution(), seed=1)
    rate = [np.degrees(a.T_world_camera.rotation_angle_to(b.T_world_camera)) * 30 for a, b in zip(poses, poses[1:],
                                                                                                     strict=False)]
    fast = int(np.argmax(rate[:150]))
    sub = camera._exposure_poses(fast)
    assert len(sub) >= 4  # ~60 deg/s over 4 ms at fx 833: ~3.5 px of smear
    spread = np.degrees(sub[0].rotation_angle_to(sub[-1]))
    assert spread == pytest.approx(rate[fast] * 0.004 * (len(sub) - 1) / len(sub), rel=0.2)
    blurred, sharp = camera.render(fast).astype(float), still.render(fast).astype(float)
    gain = effects.gain_at((poses[fast].stamp_ns - poses[0].stamp_ns) / 1e9)

    def energy(image):
        return np.mean(np.abs(np.diff(image, axis=1)))

    assert energy(blurred) < 0.85 * energy(sharp) * gain
    assert blurred.mean() == pytest.approx(sharp.mean() * gain, rel=0.05)


def test_scenarios_refuse_too_short_a_run():
    from cubeloc.fakes.trajectories import TrajectoryError

    for name, (_, _, minimum) in TIMING.items():
        with pytest.raises(TrajectoryError, match=name):
            make_trajectory(name, seconds=minimum - 1)
