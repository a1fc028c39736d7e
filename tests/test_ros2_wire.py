"""The ROS 2 side checked against what it must match, with nothing of daemon/ros2.py's own
machinery on the checking side: the key and token formats against rmw_zenoh's design
document (its examples verbatim), the type hashes against a second hasher
(ros2-pyterfaces), every payload decoded by a second CDR implementation (pycdr2, with the
message layouts written here from the .msg definitions), the attachment byte by byte as
the design document lays it out."""

from __future__ import annotations

import struct
import time

import numpy as np
import pytest
from ros2_msgs import decode

from cubeloc.calib.camera_info import paper_camera
from cubeloc.daemon.config import Ros2Config
from cubeloc.daemon.messages import CameraStatus, StatusReport
from cubeloc.daemon.ros2 import (
    CAMERA_INFO_TYPE,
    DIAGNOSTICS_TYPE,
    ODOMETRY_TYPE,
    POSE_TYPE,
    TF_TYPE,
    UNKNOWN_TWIST_VARIANCE,
    Ros2Publisher,
    node_token,
    ros_topic,
    typestore,
)
from cubeloc.positioning.estimator import PoseEstimate, PoseState
from cubeloc.positioning.frames import RobotFrames
from cubeloc.positioning.geometry import Transform, look_at

# rmw_zenoh docs/design.md (commit 99a6a2b), "Topic and Service name mapping" and "Graph Cache"
DOC_CHATTER_KEY = "0/chatter/std_msgs::msg::dds_::String_/RIHS01_df668c740482bbd48fb39d76a70dfd4bd59db1288021743503259e948f6b1a18"
DOC_NAMESPACED_KEY = "0/robot1/chatter/std_msgs::msg::dds_::String_/RIHS01_df668c740482bbd48fb39d76a70dfd4bd59db1288021743503259e948f6b1a18"
DOC_LISTENER_NODE = "@ros2_lv/2/aac3178e146ba6f1fc6e6a4085e77f21/0/0/NN/%/%/listener"
DOC_TALKER_PUBLISHER = ("@ros2_lv/2/8b20917502ee955ac4476e0266340d5c/0/10/MP/%/%/talker/%chatter/"
                        "std_msgs::msg::dds_::String_/RIHS01_df668c740482bbd48fb39d76a70dfd4bd59db1288021743503259e948f6b1a18/"
                        "::,7:,:,:,,")


def test_keys_and_tokens_are_the_design_documents_examples():
    string_hash = typestore("jazzy").hash_rihs01("std_msgs/msg/String")  # computed, and it is the doc's
    chatter = ros_topic("std_msgs/msg/String", "/chatter", string_hash, 0, "z", 0, 1, "", "talker", 10)
    assert chatter.key == DOC_CHATTER_KEY
    namespaced = ros_topic("std_msgs/msg/String", "/robot1/chatter", string_hash, 0, "z", 0, 1, "/robot1", "talker", 10)
    assert namespaced.key == DOC_NAMESPACED_KEY
    talker = ros_topic("std_msgs/msg/String", "/chatter", string_hash, 2, "8b20917502ee955ac4476e0266340d5c", 0, 10,
                       "", "talker", 7)
    assert talker.token == DOC_TALKER_PUBLISHER
    assert node_token(2, "aac3178e146ba6f1fc6e6a4085e77f21", 0, "", "listener") == DOC_LISTENER_NODE
    # a namespace is mangled, a latched topic says TRANSIENT_LOCAL (1) with depth 1
    latched = ros_topic(CAMERA_INFO_TYPE, "/robot7/cubeloc/camera_info", "H", 0, "z", 0, 3, "/robot7", "cubeloc", 1, True)
    assert latched.token.endswith("/MP/%/%robot7/cubeloc/%robot7%cubeloc%camera_info/"
                                  "sensor_msgs::msg::dds_::CameraInfo_/H/:1:,1:,:,:,,")


def _pyterfaces_schemas():
    from ros2_pyterfaces.core.diagnostic_msgs.msg import DiagnosticArray
    from ros2_pyterfaces.core.geometry_msgs.msg import PoseWithCovarianceStamped, TransformStamped
    from ros2_pyterfaces.core.nav_msgs.msg import Odometry
    from ros2_pyterfaces.core.sensor_msgs.msg import CameraInfo
    from ros2_pyterfaces.core.types import Sequence

    tf = {"__typename": TF_TYPE, "transforms": Sequence(TransformStamped)}  # tf2_msgs is not in it
    return {POSE_TYPE: PoseWithCovarianceStamped, ODOMETRY_TYPE: Odometry, CAMERA_INFO_TYPE: CameraInfo, TF_TYPE: tf,
            DIAGNOSTICS_TYPE: DiagnosticArray}


@pytest.mark.parametrize("distro", ["jazzy", "kilted", "rolling"])
def test_type_hashes_agree_with_a_second_hasher(distro):
    from ros2_pyterfaces.core.description import hash_rihs01

    store = typestore(distro)
    for typename, schema in _pyterfaces_schemas().items():
        assert store.hash_rihs01(typename) == hash_rihs01(schema), typename


class FakeSession:
    """Records what the publisher would put, for decoding without a network."""

    class _Info:
        @staticmethod
        def zid():
            return "0123456789abcdef0123456789abcdef"

    class _Entity:
        def __init__(self, log, key):
            self.log, self.key = log, key

        def put(self, payload, attachment=None):
            self.log.append((self.key, bytes(payload), bytes(attachment)))

        def undeclare(self):
            pass

    def __init__(self):
        self.info, self.sent, self.tokens = self._Info(), [], []

    def declare_publisher(self, key, **_):
        return self._Entity(self.sent, key)

    def liveliness(self):
        session = self

        class _Liveliness:
            @staticmethod
            def declare_token(key):
                session.tokens.append(key)
                return FakeSession._Entity([], key)

        return _Liveliness()


def test_every_payload_decodes_with_a_second_cdr_implementation_and_says_what_was_measured(monkeypatch):
    import zenoh.ext

    session = FakeSession()
    monkeypatch.setattr(zenoh.ext, "declare_advanced_publisher",
                        lambda s, key, **_: FakeSession._Entity(session.sent, key))
    mount = Transform(np.array([[0, 0, 1], [-1, 0, 0], [0, -1, 0]], float), [0.3, 0.0, 1.1])
    frames = RobotFrames(mount, Transform(np.eye(3), [5.0, 2.0, 0.0]), "map", "robot7/base_link", "robot7/camera")
    camera = paper_camera()
    config = Ros2Config(enabled=True, namespace="/robot7", publish_tf=True)
    publisher = Ros2Publisher(session, config, frames, camera)
    T = look_at(np.array([1.5, -1.2, 0.8]), np.zeros(3))
    covariance = np.diag([1e-6, 2e-6, 3e-6, 1e-5, 2e-5, 3e-5])
    estimate = PoseEstimate(T, PoseState.TARGET, 3, (0, 1, 4), 0.1, covariance)
    stamp_ns = 1_790_000_000_123_456_789
    before = time.time_ns()
    publisher.publish(7, stamp_ns, estimate)
    publisher.publish(8, stamp_ns + 100_000_000, estimate)
    expected, expected_cov = frames.base_in_map(T, covariance)
    by_key = {topic.key: role for role, topic in publisher.topics.items()}
    seen = {}
    for key, payload, attachment in session.sent:
        role = by_key[key]
        message = decode(payload, role)
        # the attachment, as design.md lays it out: int64 LE sequence, int64 LE time, 16, GID
        sequence, source_ns, gid_length, gid = struct.unpack("<qqB16s", attachment)
        assert len(attachment) == 33 and gid_length == 16 and gid == publisher.topics[role].gid
        assert before - 10**9 <= source_ns <= time.time_ns() + 10**9 or role == "camera_info"
        seen.setdefault(role, []).append((sequence, message))
    assert sorted(seen) == ["camera_info", "odometry", "pose", "tf"]  # diagnostics come with status
    assert [s for s, _ in seen["pose"]] == [1, 2] and [s for s, _ in seen["camera_info"]] == [1]
    pose = seen["pose"][0][1]
    assert (pose.header.frame_id, pose.header.stamp.sec, pose.header.stamp.nanosec) == ("map", 1_790_000_000, 123_456_789)
    position = pose.pose.pose.position
    np.testing.assert_allclose([position.x, position.y, position.z], expected.translation, atol=1e-12)
    q = pose.pose.pose.orientation
    assert abs(abs(np.dot([q.x, q.y, q.z, q.w], expected.quaternion())) - 1) < 1e-12
    np.testing.assert_allclose(np.reshape(pose.pose.covariance, (6, 6)), expected_cov, rtol=1e-12, atol=1e-18)
    odometry = seen["odometry"][0][1]
    assert odometry.child_frame_id == "robot7/base_link" and odometry.pose == pose.pose
    assert odometry.twist.covariance[0] == UNKNOWN_TWIST_VARIANCE and odometry.twist.twist.linear.x == 0.0
    (transform,) = seen["tf"][0][1].transforms
    assert (transform.header.frame_id, transform.child_frame_id) == ("map", "robot7/base_link")
    assert transform.transform.translation.x == position.x and transform.transform.rotation == q
    info = seen["camera_info"][0][1]
    assert (info.width, info.height, info.header.frame_id) == (1280, 1024, "robot7/camera")
    np.testing.assert_allclose(np.reshape(info.k, (3, 3)), camera.camera_matrix)
    np.testing.assert_allclose(info.d, np.ravel(camera.distortion))
    assert info.distortion_model == "plumb_bob" and np.reshape(info.p, (3, 4))[0, 3] == 0.0
    # the graph: one node token, one token per publisher, each with its topic's type and hash
    assert session.tokens[0] == "@ros2_lv/0/0123456789abcdef0123456789abcdef/0/0/NN/%/%robot7/cubeloc"
    assert set(session.tokens[1:]) == {topic.token for topic in publisher.topics.values()}
    assert publisher.topics["pose"].key.startswith("0/robot7/cubeloc/pose/geometry_msgs::msg::dds_::"
                                                   "PoseWithCovarianceStamped_/RIHS01_")
    assert publisher.topics["tf"].key.startswith("0/robot7/tf/tf2_msgs::msg::dds_::TFMessage_/RIHS01_")


def _report(camera_state="streaming", state="tracking", detail="", source="map", lost_now_s=0.0):
    camera = CameraStatus("aravis:MV-CA013", camera_state, "" if camera_state == "streaming" else "cable pulled",
                          "MV-CA013-20UM", "K12345")
    return StatusReport("robot7", state, detail, 1_790_000_000_500_000_000, 29.8, 1200, 1190, 3, 0,
                        {"p50": 21.0, "p99": 35.5}, camera, 60.0, "0.1.0",
                        extra={"source": source, "lost_now_s": lost_now_s, "held_frames": 12})


@pytest.mark.parametrize("report, level, says", [
    (_report(), 0, "pose from the map"),
    (_report(state="target", source="target"), 0, "pose from the target"),
    (_report(detail="held: orientation from rays", source="held"), 1, "pose held (held: orientation from rays)"),
    (_report(state="bridged", source="odometry"), 1, "pose odometry"),
    (_report(state="initialising", detail="waiting for the target", source=None), 1, "no pose yet (initialising"),
    (_report(state="lost", detail="3 map points agree", source=None, lost_now_s=2.5), 2, "no pose for 2.5 s (lost"),
    (_report(camera_state="reconnecting", source=None), 2, "camera reconnecting: cable pulled"),
])
def test_status_goes_to_diagnostics_ok_warn_or_error_and_decodes_with_a_second_cdr_implementation(
        monkeypatch, report, level, says):
    import zenoh.ext

    session = FakeSession()
    monkeypatch.setattr(zenoh.ext, "declare_advanced_publisher",
                        lambda s, key, **_: FakeSession._Entity(session.sent, key))
    frames = RobotFrames(Transform(np.eye(3), np.zeros(3)), Transform(np.eye(3), np.zeros(3)), "map", "base_link",
                         "camera")
    publisher = Ros2Publisher(session, Ros2Config(enabled=True, namespace="/robot7"), frames, paper_camera())
    assert publisher.topics["diagnostics"].key.startswith(
        "0/diagnostics/diagnostic_msgs::msg::dds_::DiagnosticArray_/RIHS01_")  # absolute: not namespaced
    publisher.publish_diagnostics(report)
    key, payload, _ = session.sent[-1]
    assert key == publisher.topics["diagnostics"].key
    message = decode(payload, "diagnostics")
    assert (message.header.stamp.sec, message.header.stamp.nanosec) == (1_790_000_000, 500_000_000)
    (status,) = message.status
    assert status.level == level and status.message.startswith(says), status.message
    assert status.name == "cubeloc: pose" and status.hardware_id == "MV-CA013-20UM K12345"
    values = {kv.key: kv.value for kv in status.values}
    assert values["source"] == (report.extra["source"] or "") and values["latency_p99_ms"] == "35.5"
    publisher.close()
    publisher.publish_diagnostics(report)  # closed: nothing more goes out
    assert session.sent[-1][0] == key and len([s for s in session.sent if s[0] == key]) == 1



def test_with_wheel_odometry_tf_carries_map_to_odom_and_never_a_second_parent_for_base_link(monkeypatch):
    """REP 105: the robot's odometry publishes odom -> base_link, so cubeloc's tf says
    map -> odom (what it is given, stamped as given) and the poses carry no tf of their own."""
    import zenoh.ext

    session = FakeSession()
    monkeypatch.setattr(zenoh.ext, "declare_advanced_publisher",
                        lambda s, key, **_: FakeSession._Entity(session.sent, key))
    mount = Transform(np.array([[0, 0, 1], [-1, 0, 0], [0, -1, 0]], float), [0.3, 0.0, 1.1])
    frames = RobotFrames(mount, Transform(np.eye(3), [5.0, 2.0, 0.0]), "map", "base_link", "camera", "odom")
    publisher = Ros2Publisher(session, Ros2Config(enabled=True, publish_tf=True), frames, paper_camera(),
                              map_odom=True)
    T = look_at(np.array([1.5, -1.2, 0.8]), np.zeros(3))
    estimate = PoseEstimate(T, PoseState.TARGET, 3, (0, 1, 4), 0.1, np.eye(6) * 1e-6)
    stamp_ns = 1_790_000_000_000_000_000
    publisher.publish(1, stamp_ns, estimate)
    T_map_odom = frames.odom_in_map(T, None, Transform(np.eye(3), [1.025, -2.0, 0.0]))[0]
    publisher.publish_map_odom(stamp_ns, T_map_odom)
    by_key = {topic.key: role for role, topic in publisher.topics.items()}
    sent = [(by_key[key], decode(payload, by_key[key])) for key, payload, _ in session.sent]
    tfs = [message for role, message in sent if role == "tf"]
    assert len(tfs) == 1 and [role for role, _ in sent].count("pose") == 1
    (transform,) = tfs[0].transforms
    assert (transform.header.frame_id, transform.child_frame_id) == ("map", "odom")
    assert transform.header.stamp.sec * 10**9 + transform.header.stamp.nanosec == stamp_ns
    t = transform.transform.translation
    np.testing.assert_allclose([t.x, t.y, t.z], T_map_odom.translation, atol=1e-12)


def test_the_robot_localization_example_reads_the_topics_and_frames_cubeloc_publishes():
    """examples/ekf.yaml (docs/robot_localization.md): its pose input is the topic cubeloc
    publishes under the namespace it assumes, in the frames cubeloc's defaults name, fused
    absolute (x, y, yaw), and it keeps more history than a pose's latency."""
    from pathlib import Path

    import yaml

    from cubeloc.daemon.config import FramesConfig

    example = yaml.safe_load((Path(__file__).parents[1] / "examples" / "ekf.yaml").read_text())
    ros2, frames = Ros2Config(enabled=True, namespace="/robot7"), FramesConfig()
    local, global_ = example["ekf_odom"]["ros__parameters"], example["ekf_map"]["ros__parameters"]
    assert global_["pose0"] == ros2.topic(ros2.topics.pose)
    assert (global_["map_frame"], global_["odom_frame"], global_["base_link_frame"], global_["world_frame"]) == \
        (frames.map_frame, frames.odom_frame, frames.base_frame, frames.map_frame)
    assert (local["world_frame"], local["base_link_frame"]) == (frames.odom_frame, frames.base_frame)
    assert [i for i, used in enumerate(global_["pose0_config"]) if used] == [0, 1, 5]  # x, y, yaw
    assert global_["pose0_differential"] is False and len(global_["odom0_config"]) == 15
    assert global_["smooth_lagged_data"] is True and global_["history_length"] >= 0.2
