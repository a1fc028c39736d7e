"""Wheel odometry into the running daemon over Zenoh (daemon/odometry_in.py): JSON on
cubeloc/<name>/odometry or nav_msgs/msg/Odometry in CDR on rmw_zenoh's key; good samples
are used, bad ones (NaN, out of order, unreadable) dropped and counted on status (staleness:
test_odometry.py)."""

from __future__ import annotations

import dataclasses
import json
import time

import numpy as np
import pytest
from helpers import free_port
from test_daemon_loop import Script, make_prepared, start_daemon

from daemon.ros2 import typestore
from fakes import render_view
from positioning.geometry import look_at

CAMERA_POSITION = np.array([1.2, -1.0, 0.9])


@pytest.fixture(scope="module")
def cube_image():
    return render_view(look_at(CAMERA_POSITION, np.zeros(3)), room=False)


def _cdr(stamp_ns: int, position, orientation) -> bytes:
    store = typestore("jazzy")
    t = store.types
    header = t["std_msgs/msg/Header"](stamp=t["builtin_interfaces/msg/Time"](sec=stamp_ns // 10**9,
                                                                             nanosec=stamp_ns % 10**9),
                                      frame_id="odom")
    pose = t["geometry_msgs/msg/Pose"](position=t["geometry_msgs/msg/Point"](x=position[0], y=position[1], z=position[2]),
                                       orientation=t["geometry_msgs/msg/Quaternion"](x=orientation[0], y=orientation[1],
                                                                                    z=orientation[2], w=orientation[3]))
    zero = t["geometry_msgs/msg/Vector3"](x=0.0, y=0.0, z=0.0)
    message = t["nav_msgs/msg/Odometry"](
        header=header, child_frame_id="base_link",
        pose=t["geometry_msgs/msg/PoseWithCovariance"](pose=pose, covariance=np.zeros(36)),
        twist=t["geometry_msgs/msg/TwistWithCovariance"](twist=t["geometry_msgs/msg/Twist"](linear=zero, angular=zero),
                                                          covariance=np.zeros(36)))
    return bytes(store.serialize_cdr(message, "nav_msgs/msg/Odometry"))


@pytest.mark.parametrize("source", ["json", "ros2"])
def test_odometry_samples_are_used_and_bad_ones_counted_on_status(tmp_path, cube_image, listeners, source):
    port = free_port()
    prepared = make_prepared(tmp_path, port)
    # stale_s at its most: the samples below are stamped a little before they are sent, and
    # on a busy machine their delivery may take longer than the default 0.5 s (the staleness
    # rule has its own test in test_odometry.py)
    config = prepared.config.model_copy(update={"odometry": prepared.config.odometry.model_validate(
        {"enabled": True, "source": source, "stale_s": 60})})
    prepared = dataclasses.replace(prepared, config=config)
    _, stop, thread, _ = start_daemon(prepared, Script(cube_image, [10_000]))
    listener = listeners(port)
    try:
        assert listener.wait_for(lambda: len(listener.poses) >= 1)
        if source == "json":
            key = "cubeloc/looptest/odometry"

            def send(stamp, position, orientation):
                listener.session.put(key, json.dumps({"schema": "cubeloc.odometry/1", "stamp_ns": stamp,
                                                      "position": position, "orientation": orientation}))

            def send_garbage():
                listener.session.put(key, b"{not json")
        else:
            key = "0/odom/nav_msgs::msg::dds_::Odometry_/RIHS01_0000"  # any hash: the daemon takes them all

            def send(stamp, position, orientation):
                listener.session.put(key, _cdr(stamp, position, orientation))

            def send_garbage():
                listener.session.put(key, b"\x00\x01\x00\x00 too short")

        now = time.time_ns()
        for k in range(5):  # 50 Hz, 1 cm a sample
            send(now - 10**8 + k * 20_000_000, [0.01 * k, 0.0, 0.0], [0.0, 0.0, 0.0, 1.0])
        send(now - 10**8 + 10_000_000, [0.0, 0.0, 0.0], [0.0, 0.0, 0.0, 1.0])  # out of order
        send(now + 10**8, [float("nan"), 0.0, 0.0], [0.0, 0.0, 0.0, 1.0])  # not finite
        send(now - 5 * 10**9, [0.0, 0.0, 0.0], [0.0, 0.0, 0.0, 1.0])  # 5 s old: out of order
        send_garbage()

        def counted():
            odometry = listener.status[-1]["extra"].get("odometry") if listener.status else None
            return odometry if odometry and odometry["received"] >= 9 else None

        assert listener.wait_for(counted, 10), listener.status[-1:]
        odometry = counted()
        assert odometry["dropped"] == {"out_of_order": 2, "nan": 1, "malformed": 1}, odometry
        assert odometry["used"] == 5 and odometry["newest_stamp_ns"] == now - 10**8 + 4 * 20_000_000
        before = len(listener.poses)
        assert listener.wait_for(lambda: len(listener.poses) > before + 2)  # and on it goes
    finally:
        stop.set()
        thread.join(5.0)
