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


def scan_msg(scan, frame="laser"):
    n = len(scan.ranges)
    step = (scan.angles[-1] - scan.angles[0]) / (n - 1)
    return T["sensor_msgs/msg/LaserScan"](
        header=header(scan.timestamp + 0.25, frame),
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


def tf_message(parent, child, translation, rotation):
    geometry = {k: T[f"geometry_msgs/msg/{k}"] for k in ("Vector3", "Quaternion", "Transform", "TransformStamped")}
    stamped = geometry["TransformStamped"](
        header=header(0.0, parent), child_frame_id=child,
        transform=geometry["Transform"](translation=geometry["Vector3"](x=translation[0], y=translation[1],
                                                                        z=translation[2]),
                                        rotation=geometry["Quaternion"](x=rotation[0], y=rotation[1], z=rotation[2],
                                                                        w=rotation[3])))
    return T["tf2_msgs/msg/TFMessage"](transforms=[stamped])


IDENTITY = [("base_link", "laser", (0.0, 0.0, 0.0), (0.0, 0.0, 0.0, 1.0))]


def write_bag(path, log, *, ros1=False, scans=True, odometry=True, scale=1.0, static=IDENTITY, scan=None):
    """Odometry at each scan's time and half-way between scans; scans stamped 0.25 s after their
    odometry pose's time (``simulate_log``'s scans are 1 s apart); ``static``: /tf_static's
    transforms (parent, child, translation, quaternion), the laser at the base by default;
    ``scan``: the messages' maker (``scan_msg``)."""
    if ros1:
        from rosbags.rosbag1 import Writer
        writer, serialize = Writer(path), STORE.serialize_ros1
    else:
        from rosbags.rosbag2 import Writer
        writer, serialize = Writer(path, version=9), STORE.serialize_cdr
    with writer:
        c_scan = writer.add_connection("/scan", "sensor_msgs/msg/LaserScan", typestore=STORE)
        c_odom = writer.add_connection("/odom", "nav_msgs/msg/Odometry", typestore=STORE)
        if static:
            c_tf = writer.add_connection("/tf_static", "tf2_msgs/msg/TFMessage", typestore=STORE)
            for k, transform in enumerate(static):
                writer.write(c_tf, k, serialize(tf_message(*transform), "tf2_msgs/msg/TFMessage"))
        poses = log.poses
        for k, item in enumerate(log.scans):
            if odometry:
                stops = [(item.timestamp, poses[k])]
                if k + 1 < len(log):
                    stops.append((item.timestamp + 0.5, 0.5 * (poses[k] + poses[k + 1])))
                for t, p in stops:
                    writer.write(c_odom, int(t * 1e9), serialize(odom(t, *p, scale), "nav_msgs/msg/Odometry"))
            if scans:
                writer.write(c_scan, int((item.timestamp + 0.25) * 1e9),
                             serialize((scan or scan_msg)(item), "sensor_msgs/msg/LaserScan"))


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
                msg = scan_msg(dataclasses.replace(run.log.scans[0], timestamp=t - 0.25), "base_link")
                writer.write(c_scan, int(t * 1e9), STORE.serialize_cdr(msg, "sensor_msgs/msg/LaserScan"))

    bag(tmp_path / "copy", (1.0, 0.0, 0.0))
    log, _ = read_rosbag(tmp_path / "copy")
    np.testing.assert_allclose([s.pose[0] for s in log.scans], [0.5, 1.5], atol=1e-12)
    bag(tmp_path / "two", (1.3, 0.0, 0.0))
    with pytest.raises(LogFormatError, match="stamped 1.0 s with different poses"):
        read_rosbag(tmp_path / "two")


def _pose2(a, b):
    """a (+) b for (x, y, theta), written out here (the test's own SE(2))."""
    c, s = math.cos(a[2]), math.sin(a[2])
    return np.array([a[0] + c * b[0] - s * b[1], a[1] + s * b[0] + c * b[1], a[2] + b[2]])


def _inverse2(a):
    c, s = math.cos(a[2]), math.sin(a[2])
    return np.array([-c * a[0] - s * a[1], s * a[0] - c * a[1], -a[2]])


def _yaw_quaternion(yaw):
    return (0.0, 0.0, math.sin(yaw / 2), math.cos(yaw / 2))


def _base_run(run, mount):
    """The run's scans with the odometry of a base the laser sits on at ``mount``: the log's poses
    are the laser's, so the base's are laser (+) mount^-1."""
    import dataclasses

    from taichi_match.logs import LaserLog

    base = np.array([_pose2(p, _inverse2(mount)) for p in run.log.poses])
    scans = tuple(dataclasses.replace(s, pose=b) for s, b in zip(run.log.scans, base))
    return LaserLog(scans, run.log.odometry)


def _expected_laser_poses(log, mount):
    """Each read scan's expected pose: the base's odometry interpolated a quarter of the way to the
    next (as ``test_bag_round_trip``), then the mount."""
    out = []
    for k in range(len(log.scans) - 1):
        a, b = log.poses[k], log.poses[k + 1]
        base = a + 0.25 * np.array([b[0] - a[0], b[1] - a[1], math.remainder(b[2] - a[2], 2 * math.pi)])
        out.append(_pose2(base, mount))
    return np.array(out)


@pytest.mark.parametrize("ros1", [False, True])
def test_a_laser_off_the_base_is_placed_by_tf_static(run, tmp_path, ros1):
    # a chain base_link -> mast -> laser in /tf_static (the heights and a small roll do not count);
    # each scan then sits at the base's odometry (+) the laser's mounting on the floor plane
    mast, on_mast = (0.1, 0.0, 0.1), (0.2, -0.1, 0.25)
    mount = _pose2(mast, on_mast)
    roll = math.radians(2.0)                      # level within the tolerance: a roll about the laser's x
    q_mast = _yaw_quaternion(mast[2])
    q_laser = (math.sin(roll / 2) * math.cos(on_mast[2] / 2), math.sin(roll / 2) * math.sin(on_mast[2] / 2),
               math.cos(roll / 2) * math.sin(on_mast[2] / 2), math.cos(roll / 2) * math.cos(on_mast[2] / 2))
    static = [("base_link", "mast", (mast[0], mast[1], 0.4), q_mast),
              ("mast", "laser", (on_mast[0], on_mast[1], 0.3), q_laser)]
    log = _base_run(run, mount)
    path = tmp_path / ("run.bag" if ros1 else "run")
    write_bag(path, log, ros1=ros1, static=static)
    got, _ = read_rosbag(path)
    want = _expected_laser_poses(log, mount)
    poses = np.array([s.pose for s in got.scans])
    np.testing.assert_allclose(poses[:, :2], want[:, :2], atol=1e-9)
    np.testing.assert_allclose(np.remainder(poses[:, 2] - want[:, 2] + math.pi, 2 * math.pi) - math.pi, 0.0,
                               atol=1e-9)
    # and against the simulated truth: the laser's own poses, to the interpolation's error
    assert np.abs(poses[:, :2] - run.log.poses[:-1, :2]).max() < 0.3
    # the same mounting given instead of read (a bag without /tf_static)
    write_bag(tmp_path / "bare", log, static=None)
    given, _ = read_rosbag(tmp_path / "bare", laser_pose=mount)
    np.testing.assert_allclose([s.pose for s in given.scans], [s.pose for s in got.scans], atol=1e-12)
    # the log says where the laser sits and how that was found (for report.md)
    words = f"x {mount[0]:.4g} m, y {mount[1]:.4g} m, theta {mount[2]:.4g} rad"
    assert got.laser_mount == f"{words} (the bag's /tf_static from 'base_link' to 'laser')"
    assert given.laser_mount == f"{words} (as given: laser_pose)"


def test_an_upside_down_laser_has_its_angles_negated(run, tmp_path):
    # a laser mounted upside down (rolled half a turn) at a heading: its scans, as it sends them,
    # sweep the other way; read, they are the upright laser's again
    mount = (0.15, 0.05, 0.4)
    static = [("base_link", "laser", (mount[0], mount[1], 0.2), (math.cos(mount[2] / 2), math.sin(mount[2] / 2),
                                                                   0.0, 0.0))]

    def mirrored(item):
        msg = scan_msg(item)
        msg.angle_min, msg.angle_max, msg.angle_increment = -msg.angle_min, -msg.angle_max, -msg.angle_increment
        return msg

    log = _base_run(run, mount)
    write_bag(tmp_path / "run", log, static=static, scan=mirrored)
    got, _ = read_rosbag(tmp_path / "run")
    for read, sent in zip(got.scans, run.log.scans):
        np.testing.assert_allclose(read.angles, sent.angles, atol=1e-6)
        np.testing.assert_allclose(read.ranges, sent.ranges, atol=1e-5)
    want = _expected_laser_poses(log, mount)
    np.testing.assert_allclose([s.pose[:2] for s in got.scans], want[:, :2], atol=1e-9)
    assert ", upside down (the bag's /tf_static" in got.laser_mount
    # the same mounting given instead (a bag without /tf_static): the same scans; given level
    # against the bag's upside-down transform: a warning
    import warnings

    from taichi_match.bags import LaserMountWarning

    write_bag(tmp_path / "bare", log, static=None, scan=mirrored)
    given, _ = read_rosbag(tmp_path / "bare", laser_pose=mount, upside_down=True)
    for a, b in zip(given.scans, got.scans):
        assert np.array_equal(a.angles, b.angles) and np.array_equal(a.ranges, b.ranges)
        np.testing.assert_allclose(a.pose, b.pose, atol=1e-12)
    assert given.laser_mount.endswith(", upside down (as given: laser_pose)")
    with warnings.catch_warnings():
        warnings.simplefilter("error", LaserMountWarning)
        read_rosbag(tmp_path / "run", laser_pose=mount, upside_down=True)      # as the bag says: no warning
    with pytest.warns(LaserMountWarning, match=r"\), level, differs from the bag.*\), upside down; laser_pose is used"):
        read_rosbag(tmp_path / "run", laser_pose=mount)


def test_a_tilted_laser_or_an_unknown_mount(run, tmp_path):
    from taichi_match import InvalidOptionError
    from taichi_match.bags import LaserMountWarning

    pitch = math.radians(20.0)                    # the beams would sweep a cone, not the floor
    write_bag(tmp_path / "tilted", run.log, static=[("base_link", "laser", (0.0, 0.0, 0.0),
                                                     (0.0, math.sin(pitch / 2), 0.0, math.cos(pitch / 2)))])
    with pytest.raises(LogFormatError, match="tilted 20.00 degrees"):
        read_rosbag(tmp_path / "tilted")
    write_bag(tmp_path / "zero", run.log, static=[("base_link", "laser", (0.0, 0.0, 0.0), (0.0, 0.0, 0.0, 0.0))])
    with pytest.raises(LogFormatError, match="unit quaternion"):
        read_rosbag(tmp_path / "zero")
    write_bag(tmp_path / "unknown", run.log, static=None)    # frames "base_link" and "laser", no transform
    with pytest.warns(LaserMountWarning, match="'laser'"):
        unknown, _ = read_rosbag(tmp_path / "unknown")
    plain, _ = read_rosbag(tmp_path / "unknown", laser_pose=(0.0, 0.0, 0.0))
    assert all(np.array_equal(a.pose, b.pose) for a, b in zip(unknown.scans, plain.scans))
    for bad in [(0.0, 0.0), (0.0, float("nan"), 0.0), (500.0, 0.0, 0.0), "abc", (0.0, 0.0, 1e300), (0, 0, 90),
                (True, False, True), (10**400, 0, 0)]:
        with pytest.raises(InvalidOptionError, match="laser_pose"):
            read_rosbag(tmp_path / "unknown", laser_pose=bad)
    with pytest.raises(InvalidOptionError, match="upside_down goes with laser_pose"):
        read_rosbag(tmp_path / "unknown", upside_down=True)
    with pytest.raises(InvalidOptionError, match="upside_down must be True or False"):
        read_rosbag(tmp_path / "unknown", laser_pose=(0.0, 0.0, 0.0), upside_down="yes")


def test_cli_slam_laser_pose(run, tmp_path, capsys):
    # a bag that does not say where its laser sits: one warning line, the run goes on; --laser-pose
    # says it (no warning); on a CARMEN log the flag is refused (its scans carry the laser's pose)
    pytest.importorskip("gtsam")
    from taichi_match.cli import main
    from taichi_match.logs import write_carmen

    write_bag(tmp_path / "bare", run.log, static=None)
    capsys.readouterr()
    assert main(["slam", str(tmp_path / "bare"), "--out", str(tmp_path / "a")]) == 0
    err = capsys.readouterr().err
    assert err.count("taichi-match: warning: ") == 1 and "'laser'" in err and "Traceback" not in err
    assert ("- the laser on the robot: x 0 m, y 0 m, theta 0 rad (taken to sit at the robot's base: no transform "
            "found)") in (tmp_path / "a" / "report.md").read_text()
    assert main(["slam", str(tmp_path / "bare"), "--out", str(tmp_path / "b"), "--laser-pose", "0", "0", "0"]) == 0
    assert "warning" not in capsys.readouterr().err
    assert "(as given: laser_pose)" in (tmp_path / "b" / "report.md").read_text()
    assert ((tmp_path / "a" / "trajectory.tum").read_text() == (tmp_path / "b" / "trajectory.tum").read_text())
    assert main(["slam", str(tmp_path / "bare"), "--out", str(tmp_path / "d"), "--laser-pose", "0", "0", "90"]) == 2
    assert "taichi-match: error: --laser-pose must be three numbers" in capsys.readouterr().err   # radians
    # numbers in exponent form, negative (argparse before Python 3.13 took them for options)
    assert main(["slam", str(tmp_path / "bare"), "--out", str(tmp_path / "f"), "--laser-pose", "-1e-3", "0",
                 "-.5e-2"]) == 0
    assert "x -0.001 m, y 0 m, theta -0.005 rad (as given" in (tmp_path / "f" / "report.md").read_text()
    assert main(["slam", str(tmp_path / "bare"), "--out", str(tmp_path / "g"), "--laser-upside-down"]) == 2
    assert "error: --laser-upside-down goes with --laser-pose" in capsys.readouterr().err
    write_carmen(tmp_path / "run.log", run.log)
    assert main(["slam", str(tmp_path / "run.log"), "--out", str(tmp_path / "c"), "--laser-pose", "0", "0", "0"]) == 2
    assert "--laser-pose applies to ROS bags only" in capsys.readouterr().err
    assert main(["slam", str(tmp_path / "run.log"), "--out", str(tmp_path / "c"), "--laser-upside-down"]) == 2
    assert "--laser-upside-down applies to ROS bags only" in capsys.readouterr().err
    assert main(["slam", str(tmp_path / "run.log"), "--out", str(tmp_path / "e")]) == 0
    assert "the laser on the robot" not in (tmp_path / "e" / "report.md").read_text()   # CARMEN: its own poses


def test_the_mount_through_a_common_ancestor_and_its_limits(run, tmp_path):
    # the transforms need not run from the base down to the laser: the laser may be the base's
    # parent, or both hang under a third frame; a mounting in millimetres (300 "m") is refused, an
    # unnamed frame warned, and a laser_pose that contradicts the bag warned too
    from taichi_match.bags import LaserMountWarning

    mount = (0.3, -0.1, 0.25)
    log = _base_run(run, mount)
    footprint = (0.05, 0.02, -0.2)                 # base_footprint -> base_link
    laser_in_footprint = _pose2(footprint, mount)
    inverse = _inverse2(mount)                     # laser -> base_link
    layouts = {
        "parent": [("laser", "base_link", (inverse[0], inverse[1], -0.2), _yaw_quaternion(inverse[2]))],
        "siblings": [("base_footprint", "base_link", (footprint[0], footprint[1], 0.1), _yaw_quaternion(footprint[2])),
                     ("base_footprint", "laser", (laser_in_footprint[0], laser_in_footprint[1], 0.3),
                      _yaw_quaternion(laser_in_footprint[2]))],
    }
    want = _expected_laser_poses(log, mount)
    for name, static in layouts.items():
        write_bag(tmp_path / name, log, static=static)
        got, _ = read_rosbag(tmp_path / name)
        np.testing.assert_allclose([s.pose[:2] for s in got.scans], want[:, :2], atol=1e-9, err_msg=name)
    write_bag(tmp_path / "mm", log, static=[("base_link", "laser", (300.0, -100.0, 0.0), _yaw_quaternion(0.25))])
    with pytest.raises(LogFormatError, match="within 100 m"):
        read_rosbag(tmp_path / "mm")
    write_bag(tmp_path / "given", log, static=layouts["parent"])
    with pytest.warns(LaserMountWarning, match="differs from the bag"):
        read_rosbag(tmp_path / "given", laser_pose=(0.0, 0.0, 0.0))
    import warnings

    with warnings.catch_warnings():
        warnings.simplefilter("error", LaserMountWarning)
        read_rosbag(tmp_path / "given", laser_pose=mount)        # the same mounting: no warning

    def unnamed(item):
        msg = scan_msg(item)
        msg.header.frame_id = ""
        return msg

    write_bag(tmp_path / "unnamed", log, static=layouts["parent"], scan=unnamed)
    with pytest.warns(LaserMountWarning, match="unnamed"):
        read_rosbag(tmp_path / "unnamed")
