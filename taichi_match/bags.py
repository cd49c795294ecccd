"""ROS 1 and ROS 2 bags in: ``sensor_msgs/LaserScan`` with ``nav_msgs/Odometry``, as a ``LaserLog``.

Apart from the core; ``read_rosbag`` needs ``rosbags`` (the ``slam`` extra), which reads both bag
formats without a ROS installation. ``scan_from_laserscan`` turns one message, from a bag or from a
live subscription, into a ``Scan`` for ``slam.Slam.add`` (no ROS package needed: it reads the
message's fields). Conventions, beyond those of ``logs``:

- Each scan's angles are ``angle_min + i * angle_increment``; a reading below ``range_min`` or not
  finite and negative is invalid (NaN), one at or above ``range_max`` (or +inf) is no return.
- Each scan's pose is the odometry pose at the scan's header stamp, interpolated linearly between
  the two odometry messages around it (headings unwrapped). The laser is taken to sit at the
  odometry's child frame: no TF is read. Scans before the first or after the last odometry
  message are left out, and so counted in ``read_rosbag``'s second return value.
- A bag with several LaserScan (or Odometry) topics needs the topic named.
"""

import math
from pathlib import Path

import numpy as np

from ._errors import LogFileError, LogFormatError
from .logs import _MAX_BEAMS as MAX_BEAMS
from .logs import MAX_ANGLE, MAX_COORDINATE, LaserLog, Scan, yaw_of_quaternion

__all__ = ["read_rosbag", "scan_from_laserscan"]

SCAN_TYPE = "sensor_msgs/msg/LaserScan"
ODOMETRY_TYPE = "nav_msgs/msg/Odometry"


def _stamp(header):
    return header.stamp.sec + 1e-9 * header.stamp.nanosec


def _topic(connections, msgtype, name, path):
    topics = sorted({c.topic for c in connections if c.msgtype == msgtype})
    if name is not None:
        if name not in topics:
            raise LogFormatError(f"{path}: no {msgtype} topic {name!r}; the bag has {topics}")
        return name
    if not topics:
        raise LogFormatError(f"{path}: no {msgtype} message" + (
            " (a log without odometry cannot be mapped)" if msgtype == ODOMETRY_TYPE else ""))
    if len(topics) > 1:
        raise LogFormatError(f"{path}: several {msgtype} topics {topics}; name one")
    return topics[0]


def scan_from_laserscan(msg, pose) -> Scan:
    """A ``sensor_msgs/LaserScan`` message (ROS 1 or 2, from a bag or a live subscription: any
    object with its fields) as a ``Scan`` at ``pose``, the laser's (x, y, theta) in the odometry
    frame at the message's stamp (the caller's odometry or TF lookup), for ``slam.Slam.add``.
    Ranges as the module docstring says; a message with more than ``logs`` allows of beams, or
    without a finite ``range_max`` > 0, a finite ``angle_min`` and a non-zero ``angle_increment``
    keeping every beam within one turn, raises LogFormatError."""
    t = _stamp(msg.header)
    n = len(msg.ranges)
    if n > MAX_BEAMS:
        raise LogFormatError(f"a LaserScan at t={t} has {n} ranges; at most {MAX_BEAMS}")
    r = np.asarray(msg.ranges, dtype=np.float64).copy()
    max_range = float(msg.range_max)
    step = float(msg.angle_increment)
    if not (np.isfinite(max_range) and max_range > 0 and np.isfinite(msg.angle_min) and np.isfinite(step)
            and step != 0.0 and abs(step) * max(n - 1, 0) <= 2 * np.pi + 1e-6):
        raise LogFormatError(f"a LaserScan at t={t} needs a finite range_max > 0, a finite angle_min and a non-zero "
                             f"angle_increment with all beams within one turn")
    with np.errstate(invalid="ignore"):
        r[(r < msg.range_min) | (np.isinf(r) & (r < 0))] = np.nan
        r[(r >= max_range) | np.isposinf(r)] = max_range
    angles = msg.angle_min + np.arange(len(r)) * msg.angle_increment
    pose = np.array(pose, dtype=np.float64)
    for array in (r, angles, pose):
        array.setflags(write=False)
    return Scan(float(t), r, angles, pose, max_range)


def read_rosbag(path, *, scan_topic: str = None, odometry_topic: str = None):
    """Read a ROS 1 (``.bag``) or ROS 2 (folder or ``.db3``/``.mcap``) bag.

    Returns
    -------
    (LaserLog, int)
        The scans with their interpolated odometry poses, and how many scans were left out for
        lying outside the odometry's time span.
    """
    try:
        from rosbags.highlevel import AnyReader
        from rosbags.typesys import Stores, get_typestore
    except ImportError as exc:                    # pragma: no cover - depends on the installation
        raise ImportError("reading bags needs rosbags: pip install 'taichi-match[slam]'") from exc
    path = Path(path)
    bag = path.parent if path.suffix in (".db3", ".mcap") else path
    scans, odometry = [], []
    try:
        with AnyReader([bag], default_typestore=get_typestore(Stores.ROS2_HUMBLE)) as reader:
            scan_name = _topic(reader.connections, SCAN_TYPE, scan_topic, path)
            odom_name = _topic(reader.connections, ODOMETRY_TYPE, odometry_topic, path)
            wanted = [c for c in reader.connections if c.topic in (scan_name, odom_name)]
            for connection, _, raw in reader.messages(connections=wanted):
                msg = reader.deserialize(raw, connection.msgtype)
                if connection.topic == odom_name:
                    p, q = msg.pose.pose.position, msg.pose.pose.orientation
                    if not abs(math.sqrt(q.x * q.x + q.y * q.y + q.z * q.z + q.w * q.w) - 1.0) <= 1e-3:
                        raise LogFormatError(f"{path}: an odometry orientation that is not a unit quaternion "
                                             f"({q.x}, {q.y}, {q.z}, {q.w}) at {_stamp(msg.header)} s")
                    odometry.append((_stamp(msg.header), p.x, p.y, yaw_of_quaternion(q.x, q.y, q.z, q.w)))
                else:
                    scans.append(msg)
    except LogFormatError:
        raise
    except Exception as exc:                      # rosbags' own errors: unreadable or malformed bags
        raise LogFileError(f"{path}: cannot read the bag: {type(exc).__name__}: {exc}") from exc
    if not scans:
        raise LogFormatError(f"{path}: no LaserScan message")
    odo = np.array(sorted(odometry), dtype=np.float64).reshape(-1, 4)
    if len(odo) >= 2 and (np.abs(odo[:, 1:3]).max() > MAX_COORDINATE or np.abs(odo[:, 3]).max() > MAX_ANGLE):
        raise LogFormatError(f"{path}: odometry poses beyond {MAX_COORDINATE:g} m or {MAX_ANGLE:g} rad")
    if len(odo) < 2 or not np.all(np.isfinite(odo)):
        raise LogFormatError(f"{path}: fewer than two finite Odometry messages "
                             "(a log without odometry cannot be mapped)")
    repeated = odo[1:, 0] == odo[:-1, 0]              # one stamp twice: the same pose kept once, else an error
    if np.any(repeated & np.any(odo[1:, 1:] != odo[:-1, 1:], axis=1)):
        stamp = float(odo[1:, 0][repeated][0])
        raise LogFormatError(f"{path}: two Odometry messages stamped {stamp!r} s with different poses: the poses "
                             f"between them cannot be interpolated")
    odo = odo[np.r_[True, ~repeated]]
    if len(odo) < 2:
        raise LogFormatError(f"{path}: fewer than two Odometry messages at different stamps "
                             "(a log without odometry cannot be mapped)")
    heading = np.unwrap(odo[:, 3])
    out, left_out = [], 0
    for msg in sorted(scans, key=lambda m: _stamp(m.header)):
        t = _stamp(msg.header)
        if not odo[0, 0] <= t <= odo[-1, 0]:
            left_out += 1
            continue
        pose = np.array([np.interp(t, odo[:, 0], odo[:, 1]), np.interp(t, odo[:, 0], odo[:, 2]),
                         np.interp(t, odo[:, 0], heading)])
        pose[2] = np.arctan2(np.sin(pose[2]), np.cos(pose[2]))
        try:
            out.append(scan_from_laserscan(msg, pose))
        except LogFormatError as exc:
            raise LogFormatError(f"{path}: {exc}") from None
    if not out:
        raise LogFormatError(f"{path}: no LaserScan inside the odometry's time span")
    return LaserLog(tuple(out), odo), left_out
