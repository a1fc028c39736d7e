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
from test_daemon_loop import Script, make_prepared, start_daemon

from cubeloc.daemon.ros2 import typestore
from cubeloc.fakes import render_view
from cubeloc.net import free_port
from cubeloc.positioning.geometry import look_at

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


def test_a_tf_consumer_composes_map_to_odom_with_the_robots_odometry_into_the_base_pose(tmp_path, cube_image,
                                                                                        listeners):
    """REP 105 and tf2 as a ROS consumer reads them: the robot's odometry publishes
    odom -> base_link (here: driving 0.2 m/s along its x, its heading 25 deg, as wheels that
    have drifted from the map would say); cubeloc publishes map -> odom on /tf and
    cubeloc/<name>/map_odom. Composed at the same stamp they give the base pose cubeloc
    publishes on base_pose within 1 mm, and no frame has two parents."""
    import threading

    from ros2_msgs import decode

    from cubeloc.positioning.geometry import Transform

    port = free_port()
    mount = {"xyz": [0.3, 0.0, 1.1], "rpy_deg": [-90, 0, -90]}
    prepared = make_prepared(tmp_path, port, frames={"base_from_camera": mount},
                             ros2={"enabled": True, "publish_tf": True})
    config = prepared.config.model_copy(update={"odometry": prepared.config.odometry.model_validate(
        {"enabled": True, "source": "json", "stale_s": 60})})
    prepared = dataclasses.replace(prepared, config=config)
    start_ns = time.time_ns()
    yaw = np.radians(25.0)
    quaternion = np.array([0.0, 0.0, np.sin(yaw / 2), np.cos(yaw / 2)])

    def odom_base(stamp_ns: int) -> Transform:  # what the wheels say at any time
        return Transform.from_quaternion(np.array([1.0 + 0.2 * (stamp_ns - start_ns) / 1e9, -2.0, 0.0]), quaternion)

    listener = listeners(port)
    tf_messages, map_odom = [], []
    listener.session.declare_subscriber("0/tf/tf2_msgs::msg::dds_::TFMessage_/*",
                                        lambda s: tf_messages.append(decode(s.payload.to_bytes(), "tf")))
    listener.session.declare_subscriber("cubeloc/looptest/map_odom",
                                        lambda s: map_odom.append(json.loads(s.payload.to_bytes())))
    sending = threading.Event()

    def wheels():  # 50 Hz, stamped as measured
        while not sending.wait(0.02):
            stamp = time.time_ns()
            pose = odom_base(stamp)
            listener.session.put("cubeloc/looptest/odometry", json.dumps({
                "schema": "cubeloc.odometry/1", "stamp_ns": stamp, "frame_id": "odom", "child_frame_id": "base_link",
                "position": pose.translation.tolist(), "orientation": pose.quaternion().tolist()}))

    sender = threading.Thread(target=wheels, daemon=True)
    sender.start()
    _, stop, thread, _ = start_daemon(prepared, Script(cube_image, [10_000]))
    try:
        def counted():  # a status that has counted them (the last one may go out as the session closes)
            return any(s["extra"].get("map_odom", {}).get("published", 0) >= 5 for s in listener.status)

        assert listener.wait_for(lambda: len(tf_messages) >= 5 and len(map_odom) >= 5 and listener.base_poses
                                 and counted(), 30), (len(tf_messages), len(map_odom), listener.status[-1:])
    finally:
        stop.set()
        thread.join(5.0)
        sending.set()
        sender.join(2.0)
    parents = {}
    for message in tf_messages:
        for transform in message.transforms:
            parents.setdefault(transform.child_frame_id, set()).add(transform.header.frame_id)
    parents.setdefault("base_link", set()).add("odom")  # the robot's own odom -> base_link
    assert parents == {"odom": {"map"}, "base_link": {"odom"}}  # one parent each
    base_by_stamp = {b["stamp_ns"]: b for b in listener.base_poses}
    compared = 0
    for message in tf_messages:
        (transform,) = message.transforms
        stamp = transform.header.stamp.sec * 10**9 + transform.header.stamp.nanosec
        t, q = transform.transform.translation, transform.transform.rotation
        T_map_odom = Transform.from_quaternion(np.array([t.x, t.y, t.z]), np.array([q.x, q.y, q.z, q.w]))
        T_map_base = T_map_odom @ odom_base(stamp)  # tf2: lookupTransform(map, base_link, stamp)
        base = base_by_stamp.get(stamp)
        if base is not None:
            assert np.linalg.norm(T_map_base.translation - np.array(base["position"])) < 0.001
            compared += 1
    assert compared >= 1
    for document in map_odom:  # the same transform as JSON, with the pose's state and source
        assert document["schema"] == "cubeloc.map_odom/1" and document["child_frame_id"] == "odom"
        T_map_base = Transform.from_quaternion(np.array(document["position"]),
                                               np.array(document["orientation"])) @ odom_base(document["stamp_ns"])
        base = base_by_stamp.get(document["stamp_ns"])
        if base is not None:
            assert np.linalg.norm(T_map_base.translation - np.array(base["position"])) < 0.001
    assert counted()
