"""Laser logs: CARMEN files (FLASER, ROBOTLASER1, ODOM; plain or gzipped) and TUM trajectories;
the real logs in ../shared."""

import gzip
import math
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from taichi_match._errors import InvalidOptionError, LogFileError, LogFormatError
from taichi_match.logs import LaserLog, read_carmen, read_tum, write_tum

SHARED_LOGS = Path(__file__).resolve().parents[2] / "shared" / "logs"


def flaser(ranges, pose, timestamp, odom=(9.0, 9.0, 9.0)):
    """A FLASER line: n r_1 .. r_n x y theta odom_x odom_y odom_theta timestamp host logger_timestamp."""
    numbers = [len(ranges), *ranges, *pose, *odom, timestamp]
    return "FLASER " + " ".join(str(v) for v in numbers) + f" robot {timestamp + 0.5}"


def robotlaser(start, step, max_range, ranges, laser_pose, timestamp, remissions=()):
    """A ROBOTLASER1 line: type start fov step max_range accuracy remission_mode n r.. m rem..
    laser pose, robot pose, tv rv forward_safety side_safety turn_axis timestamp host logger_timestamp."""
    numbers = [0, start, step * (len(ranges) - 1), step, max_range, 0.01, 0, len(ranges), *ranges,
               len(remissions), *remissions, *laser_pose, 7.0, 7.0, 7.0, 0.1, 0.2, 0.3, 0.4, 0.5, timestamp]
    return "ROBOTLASER1 " + " ".join(str(v) for v in numbers) + f" robot {timestamp + 0.5}"


def write(path, lines, gzipped=False):
    text = "\n".join(lines) + "\n"
    if gzipped:
        with gzip.open(path, "wt", encoding="utf-8") as f:
            f.write(text)
    else:
        path.write_text(text, encoding="utf-8")
    return path


LOG_LINES = [
    "# a CARMEN log",
    "PARAM robot_front_laser_max 8.0",
    "ODOM 0.5 -0.25 0.1 0.3 0.0 0.0 100.25 robot 100.3",
    flaser([1.0, 2.5, 8.0, 3.25, 0.5], (0.5, -0.25, 0.1), 100.5),
    "",
    "SYNC some thing",
    "ODOM 0.75 -0.25 0.2 0.3 0.0 0.0 101.0 robot 101.1",
    flaser([7.5, 2.0, 1.5, float("nan"), 4.0], (0.75, -0.25, 0.2), 101.5),
]


@pytest.mark.parametrize("name, gzipped", [("run.log", False), ("run.clf", False), ("run.log.gz", True),
                                           ("run.clf", True), ("run.log", True), ("run.gz", False)])
def test_flaser_and_odom_lines(tmp_path, name, gzipped):
    log = read_carmen(write(tmp_path / name, LOG_LINES, gzipped))
    assert isinstance(log, LaserLog) and len(log) == 2
    first, second = log.scans
    np.testing.assert_array_equal(first.ranges, [1.0, 2.5, 8.0, 3.25, 0.5])
    np.testing.assert_array_equal(second.ranges, [7.5, 2.0, 1.5, np.nan, 4.0])
    # 5 beams (odd): evenly over 180 degrees, the first at -90 (the robot's right)
    for scan in log.scans:
        np.testing.assert_allclose(scan.angles, np.radians([-90.0, -45.0, 0.0, 45.0, 90.0]), rtol=0, atol=1e-15)
        assert scan.max_range == 8.0                  # the largest reading in the log
        assert not scan.ranges.flags.writeable and not scan.pose.flags.writeable
    np.testing.assert_array_equal(log.poses, [[0.5, -0.25, 0.1], [0.75, -0.25, 0.2]])   # (x, y, theta)
    np.testing.assert_array_equal(log.timestamps, [100.5, 101.5])
    assert first.timestamp == 100.5
    np.testing.assert_array_equal(log.odometry, [[100.25, 0.5, -0.25, 0.1], [101.0, 0.75, -0.25, 0.2]])


def test_flaser_beam_counts_and_max_range(tmp_path):
    # the SICK scanners' steps from -90 degrees: an odd count spans 180 degrees (181 beams 1 degree
    # apart, 361 beams 0.5), an even count stops one step short of +90 (180 beams 1 degree apart)
    counts = [181, 361, 180, 360, 3, 4]
    lines = [flaser([2.0] * n, (0.0, 0.0, 0.0), float(i)) for i, n in enumerate(counts)]
    lines += [flaser([3.0, 4.0, float("inf")], (1.0, 2.0, 3.0), t) for t in (9.0, 10.0)]
    path = write(tmp_path / "a.log", lines)
    log = read_carmen(path)
    want = [np.arange(-90.0, 90.5, 1.0), np.arange(-90.0, 90.25, 0.5), np.arange(-90.0, 89.5, 1.0),
            np.arange(-90.0, 89.75, 0.5), [-90.0, 0.0, 90.0], [-90.0, -45.0, 0.0, 45.0]]
    for scan, degrees in zip(log.scans, want):
        np.testing.assert_allclose(np.degrees(scan.angles), degrees, rtol=0, atol=1e-12)
    assert [s.max_range for s in log.scans] == [4.0] * 8          # infinite readings left out
    assert log.odometry.shape == (0, 4)
    assert [s.max_range for s in read_carmen(path, max_range=30.0).scans] == [30.0] * 8
    for bad in (0.0, -1.0, math.nan, math.inf, "8"):
        with pytest.raises(InvalidOptionError, match="max_range"):
            read_carmen(path, max_range=bad)


def test_a_lone_larger_reading_is_not_the_sensors_maximum(tmp_path):
    """Readings saturated at 4 m in most scans and one glitch of 65.5 m: the maximum is 4 m (a
    glitch taken for it made every 4 m reading a wall); with no value repeated, the largest."""
    lines = [flaser([1.0, 4.0, 2.5], (0.0, 0.0, 0.0), float(t)) for t in range(5)]
    lines.append(flaser([1.0, 65.535, 2.5], (0.0, 0.0, 0.0), 5.0))
    assert {s.max_range for s in read_carmen(write(tmp_path / "a.log", lines)).scans} == {4.0}
    lines = [flaser([1.0, 3.0 + t, 2.5], (0.0, 0.0, 0.0), float(t)) for t in range(3)]
    assert {s.max_range for s in read_carmen(write(tmp_path / "b.log", lines)).scans} == {5.0}


def test_a_corrupt_gzip_body_is_a_log_file_error_naming_the_file(tmp_path):
    data = bytearray(gzip.compress(("\n".join(LOG_LINES) + "\n").encode() * 50))
    data[40:60] = bytes(20)
    (tmp_path / "bad.log.gz").write_bytes(bytes(data))
    with pytest.raises(LogFileError, match="bad.log.gz"):
        read_carmen(tmp_path / "bad.log.gz")


def test_robotlaser_lines(tmp_path):
    lines = [
        robotlaser(-1.5, 0.75, 30.0, [1.0, 2.0, 30.0, 4.0, 5.0], (1.5, -2.0, 0.25), 10.0, remissions=[0.5, 0.7]),
        robotlaser(-0.5, 0.25, 12.0, [6.0, 7.0], (2.5, -1.0, -0.5), 11.0),
        flaser([1.0, 3.0], (0.0, 0.0, 0.0), 12.0),
    ]
    log = read_carmen(write(tmp_path / "r.clf", lines))
    assert len(log) == 3
    a, b, c = log.scans
    np.testing.assert_array_equal(a.ranges, [1.0, 2.0, 30.0, 4.0, 5.0])
    np.testing.assert_allclose(a.angles, -1.5 + 0.75 * np.arange(5), rtol=0, atol=1e-15)
    np.testing.assert_array_equal(a.pose, [1.5, -2.0, 0.25])           # the laser's pose, not the robot's
    assert (a.timestamp, a.max_range) == (10.0, 30.0)
    np.testing.assert_array_equal(b.ranges, [6.0, 7.0])
    np.testing.assert_allclose(b.angles, [-0.5, -0.25], rtol=0, atol=1e-15)
    assert (b.timestamp, b.max_range) == (11.0, 12.0)
    np.testing.assert_array_equal(c.ranges, [1.0, 3.0])
    assert c.timestamp == 12.0


@pytest.mark.parametrize("line, message", [
    ("FLASER", "number of beams"),
    ("FLASER 5 1.0 2.0 3.0 0 0 0 0 0 0 5.0", "has 12 to 14 fields"),
    ("FLASER 3 1.0 abc 2.0 0 0 0 0 0 0 5.0 robot 5.0", "expected numbers"),
    ("FLASER 3 1.0 2.0 3.0 0 0 zero 0 0 0 5.0 robot 5.0", "expected numbers"),
    ("FLASER 1000000000 1.0 2.0 3.0 0 0 0 0 0 0 5.0 robot 5.0", "number of beams"),
    ("FLASER 0 0 0 0 0 0 0 5.0 robot 5.0", "number of beams"),
    ("FLASER -2 1.0 2.0 0 0 0 0 0 0 5.0 robot 5.0", "number of beams"),
    ("FLASER 2.5 1.0 2.0 0 0 0 0 0 0 5.0 robot 5.0", "not an integer"),
    ("FLASER 2 1.0 2.0 0 0 0 0 0 0 nan robot 5.0", "not finite"),
    ("FLASER 2 1.0 2.0 0 inf 0 0 0 0 5.0 robot 5.0", "not finite"),
    ("ODOM 1.0 2.0 3.0", "ODOM needs"),
    ("ODOM 1.0 2.0 x 0 0 0 5.0 robot 5.0", "expected numbers"),
    ("ROBOTLASER1 0 -1.57 3.14", "too short"),
    ("ROBOTLASER1 0 -1.57 3.14 1.57 30 0.01 0 3 1.0 2.0", "truncated"),
    ("ROBOTLASER1 0 -1.57 3.14 1.57 30 0.01 0 3 1.0 2.0 3.0 0 1 2 3 4 5 6 7 8", "truncated"),
    ("ROBOTLASER1 0 -1.57 3.14 1.57 30 0.01 0 2000000 1.0", "number of beams"),
])
def test_malformed_lines_raise_naming_file_and_line(tmp_path, line, message):
    good = flaser([1.0, 2.0], (0.0, 0.0, 0.0), 1.0)
    path = write(tmp_path / "bad.log", ["# header", good, line, good])
    with pytest.raises(LogFormatError, match=message) as info:
        read_carmen(path)
    assert "bad.log:3" in str(info.value)


def test_logs_without_scans_and_overlong_lines(tmp_path):
    with pytest.raises(LogFormatError, match="no FLASER or ROBOTLASER1"):
        read_carmen(write(tmp_path / "odom.log", ["ODOM 0 0 0 0 0 0 1.0 robot 1.0"]))
    with pytest.raises(LogFormatError, match="no FLASER or ROBOTLASER1"):
        read_carmen(write(tmp_path / "empty.log", []))
    long_line = "FLASER 300000 " + "1.5 " * 300000 + "0 0 0 0 0 0 1.0 robot 1.0"
    with pytest.raises(LogFormatError, match="longer than"):
        read_carmen(write(tmp_path / "long.log.gz", [long_line], gzipped=True))


def test_a_gzip_of_newlines_is_refused_at_the_line_limit(tmp_path, monkeypatch):
    """A gzip that unpacks to nothing but newlines (a thousand times its size) is refused once it
    passes ``MAX_LINES`` lines, not read to its end."""
    import taichi_match.logs as logs

    monkeypatch.setattr(logs, "MAX_LINES", 1000)
    (tmp_path / "bomb.log.gz").write_bytes(gzip.compress(b"\n" * 100_000))
    with pytest.raises(LogFormatError, match="more than 1000 lines"):
        read_carmen(tmp_path / "bomb.log.gz")
    (tmp_path / "fine.log").write_text("\n".join(LOG_LINES) + "\n")       # fewer lines: read
    assert len(read_carmen(tmp_path / "fine.log")) > 0


def test_unreadable_files_raise_log_file_error(tmp_path):
    for reader in (read_carmen, read_tum):
        with pytest.raises(LogFileError, match="not a regular file"):
            reader(tmp_path / "missing.log")
        with pytest.raises(LogFileError, match="not a regular file"):
            reader(tmp_path)
    good = write(tmp_path / "good.log.gz", LOG_LINES * 50, gzipped=True).read_bytes()
    (tmp_path / "truncated.log").write_bytes(good[:len(good) // 2])
    (tmp_path / "corrupt.log").write_bytes(b"\x1f\x8b" + b"not really gzip" * 10)
    for name in ("truncated.log", "corrupt.log"):
        with pytest.raises(LogFileError, match="cannot read"):
            read_carmen(tmp_path / name)
    assert issubclass(LogFileError, OSError) and issubclass(LogFormatError, ValueError)


# --- TUM trajectories ------------------------------------------------------------------------------

def test_tum_round_trip(tmp_path):
    rng = np.random.default_rng(0)
    timestamps = np.sort(rng.uniform(0.0, 1e4, 40))
    poses = np.column_stack([rng.uniform(-50.0, 50.0, (40, 2)), rng.uniform(-3 * np.pi, 3 * np.pi, 40)])
    poses[:4, 2] = [0.0, np.pi, -np.pi / 2, 2 * np.pi]
    write_tum(tmp_path / "t.tum", timestamps, poses)
    lines = (tmp_path / "t.tum").read_text().splitlines()
    assert lines[0].startswith("#") and len(lines) == 41
    assert all(line.split()[3:6] == ["0", "0", "0"] for line in lines[1:])       # z, qx, qy
    t, back = read_tum(tmp_path / "t.tum")
    np.testing.assert_allclose(t, timestamps, rtol=0, atol=6e-7)
    np.testing.assert_allclose(back[:, :2], poses[:, :2], rtol=0, atol=6e-7)
    turn = np.angle(np.exp(1j * (back[:, 2] - poses[:, 2])))                      # the same angle mod 2 pi
    np.testing.assert_allclose(turn, 0.0, rtol=0, atol=1e-8)
    assert np.all(np.abs(back[:, 2]) <= np.pi)
    with pytest.raises(ValueError):
        write_tum(tmp_path / "u.tum", timestamps[:3], poses[:4])


def test_tum_yaw_from_quaternions(tmp_path):
    # pure yaw rotations, the same with -q, and rotations with some roll and pitch: the yaw of
    # the intrinsic z-y'-x'' angles, from scipy
    rng = np.random.default_rng(1)
    quats = [(0.0, 0.0, 0.0, 1.0), (0.0, 0.0, math.sqrt(0.5), math.sqrt(0.5)), (0.0, 0.0, 1.0, 0.0),
             (0.0, 0.0, -math.sqrt(0.5), -math.sqrt(0.5)), (0.0, 0.0, -0.6, 0.8)]
    hand_yaws = [0.0, math.pi / 2, math.pi, math.pi / 2, 2 * math.atan2(-0.6, 0.8)]
    tilted = Rotation.from_euler("ZYX", np.column_stack([rng.uniform(-np.pi, np.pi, 20), rng.uniform(-0.2, 0.2, 20),
                                                         rng.uniform(-0.2, 0.2, 20)]))
    quats += [tuple(q) for q in tilted.as_quat()]          # scalar last, as TUM
    lines = ["# timestamp x y z qx qy qz qw"]
    lines += [f"{i}.5 {i} {-i} 0.25 " + " ".join(repr(float(c)) for c in q) for i, q in enumerate(quats)]
    t, poses = read_tum(write(tmp_path / "q.tum", lines))
    np.testing.assert_array_equal(t, np.arange(len(quats)) + 0.5)
    np.testing.assert_array_equal(poses[:, :2], np.column_stack([np.arange(len(quats)), -np.arange(len(quats))]))
    want = hand_yaws + list(Rotation.from_quat(quats[5:]).as_euler("ZYX")[:, 0])
    np.testing.assert_allclose(np.angle(np.exp(1j * (poses[:, 2] - want))), 0.0, rtol=0, atol=1e-12)
    np.testing.assert_allclose(poses[1:4, 2], [math.pi / 2, math.pi, math.pi / 2], rtol=0, atol=1e-15)


@pytest.mark.parametrize("line, message", [
    ("1.0 2.0 3.0 0 0 0 0", "8 fields"),
    ("1.0 2.0 3.0 0 0 0 0 1 9", "8 fields"),
    ("1.0 2.0 x 0 0 0 0 1", "expected numbers"),
    ("1.0 nan 3.0 0 0 0 0 1", "not finite"),
])
def test_malformed_tum_lines(tmp_path, line, message):
    with pytest.raises(LogFormatError, match=message):
        read_tum(write(tmp_path / "bad.tum", ["# header", "0.5 0 0 0 0 0 0 1", line]))


def test_tum_without_poses(tmp_path):
    with pytest.raises(LogFormatError, match="no pose"):
        read_tum(write(tmp_path / "empty.tum", ["# only a comment", ""]))


# --- the real logs ---------------------------------------------------------------------------------

def test_shared_logs_have_one_reference_pose_per_scan():
    if not SHARED_LOGS.is_dir():
        pytest.skip(f"no shared logs at {SHARED_LOGS}")
    names = sorted(p.name for p in SHARED_LOGS.iterdir() if (p / f"{p.name}.log.gz").is_file())
    if not names:
        pytest.skip(f"no NAME/NAME.log.gz in {SHARED_LOGS}")
    for name in names:
        log = read_carmen(SHARED_LOGS / name / f"{name}.log.gz")
        reference = SHARED_LOGS / name / f"{name}.reference.tum"
        lines = [line for line in reference.read_text().splitlines() if line.strip() and not line.startswith("#")]
        assert len(log) == len(lines) > 100, name
        t, poses = read_tum(reference)
        np.testing.assert_allclose(log.timestamps, t, rtol=0, atol=1e-6, err_msg=name)
        assert np.all(np.diff(log.timestamps) > 0), name
        # every scan of a log has the same beams, from -90 degrees 1 or 0.5 degree apart, and the
        # log's saturation value
        beams = {len(s.ranges) for s in log.scans}
        assert len(beams) == 1 and beams <= {180, 181, 360, 361}, (name, beams)
        step = 1.0 if beams <= {180, 181} else 0.5
        for s in log.scans:
            np.testing.assert_allclose(np.degrees(s.angles), -90.0 + step * np.arange(len(s.angles)),
                                       rtol=0, atol=1e-9, err_msg=name)
        max_range = max(float(np.nanmax(s.ranges)) for s in log.scans)
        assert all(s.max_range == max_range for s in log.scans), name
        assert len(log.odometry) == len(log), name


def test_a_beam_count_that_disagrees_with_the_line_is_refused(tmp_path):
    # a FLASER line one beam longer than its count says, without host and logger timestamp: the last
    # beam would be read as x, x as y, y as theta and the odometry's heading as the timestamp; the
    # number where the host's name stands gives it away
    ranges = [1.0, 2.0, 3.0]
    line = "FLASER 2 " + " ".join(str(v) for v in [*ranges, 0.5, 0.6, 0.1, 9.0, 9.0, 9.0, 10.0])
    with pytest.raises(LogFormatError, match="host's name"):
        read_carmen(write(tmp_path / "shifted.log", [line]))
    # the same fields with the right count and a host's name are read as written
    log = read_carmen(write(tmp_path / "right.log", [flaser(ranges, (0.5, 0.6, 0.1), 10.0)]))
    np.testing.assert_array_equal(log.scans[0].ranges, ranges)
    np.testing.assert_array_equal(log.scans[0].pose, (0.5, 0.6, 0.1))


@pytest.mark.parametrize("value", ["nan", "inf", "0.0", "-1.0"])
def test_a_log_without_a_usable_range_says_so(tmp_path, value):
    lines = [flaser([value] * 4, (0.1 * k, 0.0, 0.0), 10.0 + k) for k in range(3)]
    with pytest.raises(LogFormatError, match="no usable beam"):
        read_carmen(write(tmp_path / "none.log", lines))


def test_tum_keeps_timestamps_closer_than_a_microsecond_apart(tmp_path):
    # six decimals where they hold the timestamp (the usual case, written as before); in full where
    # they would merge scans 10 ns apart into one stamp
    timestamps = np.array([1000.0, 1000.00000001, 1000.00000002, 1000.5])
    poses = np.zeros((4, 3))
    write_tum(tmp_path / "t.tum", timestamps, poses)
    lines = (tmp_path / "t.tum").read_text().splitlines()
    assert lines[1].startswith("1000.000000 ") and lines[4].startswith("1000.500000 ")
    back, _ = read_tum(tmp_path / "t.tum")
    np.testing.assert_array_equal(back, timestamps)
