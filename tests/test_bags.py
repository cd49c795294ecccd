"""ROS bags in (taichi_match.bags): small ROS 1 and ROS 2 bags written here with rosbags."""

import math

import numpy as np
import pytest

from taichi_match import LogFileError, LogFormatError
from taichi_match.simulate import simulate_log

pytest.importorskip("rosbags")
from rosbags.typesys import Stores, get_typestore  # noqa: E402

from taichi_match.bags import read_rosbag  # noqa: E402

STORE = get_typestore(Stores.ROS2_HUMBLE)
T = STORE.types


def header(t, frame):
    sec = int(math.floor(t))
    stamp = T["builtin_interfaces/msg/Time"](sec=sec, nanosec=int(round((t - sec) * 1e9)))
    return T["std_msgs/msg/Header"](stamp=stamp,
                                    frame_id=frame)


def scan_msg(scan):
    n = len(scan.ranges)
    step = (scan.angles[-1] - scan.angles[0]) / (n - 1)
    return T["sensor_msgs/msg/LaserScan"](
        header=header(scan.timestamp + 0.25, "laser"),
        angle_min=float(scan.angles[0]), angle_max=float(scan.angles[-1]),
        angle_increment=float(step), time_increment=0.0, scan_time=0.0, range_min=0.05,
        range_max=float(scan.max_range), ranges=np.asarray(scan.ranges, dtype=np.float32),
        intensities=np.zeros(0, dtype=np.float32))




def odom(t, x, y, yaw, scale=1.0):
    geometry = {k: T[f"geometry_msgs/msg/{k}"] for k in ("Point", "Quaternion", "Pose", "PoseWithCovariance",
                                                         "Vector3", "Twist", "TwistWithCovariance")}
    pose = geometry["Pose"](position=geometry["Point"](x=x, y=y, z=0.0),
                            orientation=geometry["Quaternion"](x=0.0, y=0.0, z=scale * math.sin(yaw / 2),
                                                               w=scale * math.cos(yaw / 2)))
    zero = geometry["Vector3"](x=0.0, y=0.0, z=0.0)
    return T["nav_msgs/msg/Odometry"](
        header=header(t, "odom"), child_frame_id="base_link",
        pose=geometry["PoseWithCovariance"](pose=pose, covariance=np.zeros(36)),
        twist=geometry["TwistWithCovariance"](twist=geometry["Twist"](linear=zero, angular=zero),
                                              covariance=np.zeros(36)))


def write_bag(path, log, *, ros1=False, scans=True, odometry=True, scale=1.0):
    """Odometry at each scan's time and half-way between scans; scans stamped 0.25 s after their
    odometry pose's time (``simulate_log``'s scans are 1 s apart)."""
    if ros1:
        from rosbags.rosbag1 import Writer
        writer, serialize = Writer(path), STORE.serialize_ros1
    else:
        from rosbags.rosbag2 import Writer
        writer, serialize = Writer(path, version=9), STORE.serialize_cdr
    with writer:
        c_scan = writer.add_connection("/scan", "sensor_msgs/msg/LaserScan", typestore=STORE)
        c_odom = writer.add_connection("/odom", "nav_msgs/msg/Odometry", typestore=STORE)
        poses = log.poses
        for k, scan in enumerate(log.scans):
            if odometry:
                stops = [(scan.timestamp, poses[k])]
                if k + 1 < len(log):
                    stops.append((scan.timestamp + 0.5, 0.5 * (poses[k] + poses[k + 1])))
                for t, p in stops:
                    writer.write(c_odom, int(t * 1e9), serialize(odom(t, *p, scale), "nav_msgs/msg/Odometry"))
            if scans:
                writer.write(c_scan, int((scan.timestamp + 0.25) * 1e9),
                             serialize(scan_msg(scan), "sensor_msgs/msg/LaserScan"))


@pytest.fixture(scope="module")
def run():
    return simulate_log(2, laps=0.3)


@pytest.mark.parametrize("ros1", [False, True])
def test_bag_round_trip(run, tmp_path, ros1):
    path = tmp_path / ("run.bag" if ros1 else "run")
    write_bag(path, run.log, ros1=ros1)
    log, left_out = read_rosbag(path)
    assert left_out == 1                               # the last scan lies after the last odometry
    assert len(log) == len(run.log) - 1
    for got, sent, k in zip(log.scans, run.log.scans, range(len(log))):
        assert got.timestamp == pytest.approx(sent.timestamp + 0.25)
        np.testing.assert_allclose(got.angles, sent.angles, atol=1e-6)
        np.testing.assert_allclose(got.ranges, sent.ranges, atol=1e-5)
        # interpolated a quarter of the way from pose k to pose k + 1 (heading unwrapped)
        a, b = run.log.poses[k], run.log.poses[k + 1]
        expected = a + 0.25 * np.array([b[0] - a[0], b[1] - a[1], math.remainder(b[2] - a[2], 2 * math.pi)])
        np.testing.assert_allclose(got.pose[:2], expected[:2], atol=1e-9)
        assert math.remainder(got.pose[2] - expected[2], 2 * math.pi) == pytest.approx(0.0, abs=1e-9)


def test_bag_without_odometry_or_scans(run, tmp_path):
    write_bag(tmp_path / "no_odom", run.log, odometry=False)
    with pytest.raises(LogFormatError, match="without odometry"):
        read_rosbag(tmp_path / "no_odom")
    write_bag(tmp_path / "empty", run.log, scans=False)
    with pytest.raises(LogFormatError, match="LaserScan"):
        read_rosbag(tmp_path / "empty")


@pytest.mark.parametrize("scale", [0.0, 0.5, 2.0])
def test_odometry_orientations_must_be_unit_quaternions(run, tmp_path, scale):
    """All-zero or non-unit orientations would give headings from a rotation nobody sent."""
    write_bag(tmp_path / "bad", run.log, scale=scale)
    with pytest.raises(LogFormatError, match="unit quaternion"):
        read_rosbag(tmp_path / "bad")


def test_unreadable_bag(tmp_path):
    path = tmp_path / "broken.bag"
    path.write_bytes(b"#ROSBAG V2.0\n" + b"\x00" * 64)
    with pytest.raises((LogFileError, LogFormatError)):
        read_rosbag(path)
    with pytest.raises((LogFileError, LogFormatError)):
        read_rosbag(tmp_path / "missing")


def test_slam_reads_a_bag(run, tmp_path):
    pytest.importorskip("gtsam")
    from taichi_match.cli import main

    write_bag(tmp_path / "run", run.log)
    assert main(["slam", str(tmp_path / "run"), "--out", str(tmp_path / "out")]) == 0
    assert (tmp_path / "out" / "trajectory.tum").exists()


def test_bag_scan_geometry_is_checked(run, tmp_path):
    import dataclasses

    from taichi_match.logs import LaserLog

    flat = tuple(dataclasses.replace(s, angles=np.full(len(s.angles), 0.1)) for s in run.log.scans)
    write_bag(tmp_path / "flat", LaserLog(flat, run.log.odometry))            # angle_increment 0
    with pytest.raises(LogFormatError, match="angle_increment"):
        read_rosbag(tmp_path / "flat")


def test_live_laserscans_feed_the_mapping_loop(run):
    """Messages as a ROS node's subscription delivers them (``scan_msg``, no bag) through
    ``scan_from_laserscan`` at each scan's odometry pose, into ``Slam.add``: the ranges as the
    module docstring says (below range_min or -inf invalid, at or beyond range_max or +inf no
    return), the angles from angle_min by angle_increment, and a map within the ATE target of the
    simulated truth; a message without a usable geometry raises LogFormatError."""
    pytest.importorskip("gtsam")
    from taichi_match.bags import scan_from_laserscan
    from taichi_match.evaluation import trajectory_errors
    from taichi_match.slam import Slam

    sent = run.log.scans[0]
    msg = scan_msg(sent)
    raw = np.asarray(msg.ranges, dtype=np.float64)
    raw[:4] = [0.01, -np.inf, np.inf, sent.max_range + 1.0]
    msg.ranges = raw.astype(np.float32)
    got = scan_from_laserscan(msg, sent.pose)
    assert np.isnan(got.ranges[:2]).all() and np.all(got.ranges[2:4] == np.float32(sent.max_range))
    np.testing.assert_allclose(got.ranges[4:], np.asarray(sent.ranges[4:], dtype=np.float32), rtol=0, atol=0)
    np.testing.assert_allclose(got.angles, sent.angles, atol=1e-6)
    assert got.timestamp == pytest.approx(sent.timestamp + 0.25) and np.array_equal(got.pose, sent.pose)
    mapper = Slam()
    for scan in run.log.scans:
        mapper.add(scan_from_laserscan(scan_msg(scan), scan.pose))
    errors = trajectory_errors(mapper.finish().poses, run.truth)
    assert errors["ate_m"] <= 0.10, errors
    msg.angle_increment = 0.0
    with pytest.raises(LogFormatError, match="angle_increment"):
        scan_from_laserscan(msg, sent.pose)


def test_odometry_stamped_twice(run, tmp_path):
    # two Odometry messages with one stamp: the same pose is one message (read as without the copy),
    # two poses cannot be interpolated between (np.interp needs increasing times: silently wrong)
    import dataclasses

    from rosbags.rosbag2 import Writer

    def bag(path, second):
        with Writer(path, version=9) as writer:
            c_scan = writer.add_connection("/scan", "sensor_msgs/msg/LaserScan", typestore=STORE)
            c_odom = writer.add_connection("/odom", "nav_msgs/msg/Odometry", typestore=STORE)
            for t, p in [(0.0, (0.0, 0.0, 0.0)), (1.0, (1.0, 0.0, 0.0)), (1.0, second), (2.0, (2.0, 0.0, 0.0))]:
                writer.write(c_odom, int(t * 1e9), STORE.serialize_cdr(odom(t, *p), "nav_msgs/msg/Odometry"))
            for t in (0.5, 1.5):                        # (scan_msg stamps a scan 0.25 s after its own time)
                msg = scan_msg(dataclasses.replace(run.log.scans[0], timestamp=t - 0.25))
                writer.write(c_scan, int(t * 1e9), STORE.serialize_cdr(msg, "sensor_msgs/msg/LaserScan"))

    bag(tmp_path / "copy", (1.0, 0.0, 0.0))
    log, _ = read_rosbag(tmp_path / "copy")
    np.testing.assert_allclose([s.pose[0] for s in log.scans], [0.5, 1.5], atol=1e-12)
    bag(tmp_path / "two", (1.3, 0.0, 0.0))
    with pytest.raises(LogFormatError, match="stamped 1.0 s with different poses"):
        read_rosbag(tmp_path / "two")
