"""ROS 1 and ROS 2 bags in: ``sensor_msgs/LaserScan`` with ``nav_msgs/Odometry``, as a ``LaserLog``.

Apart from the core; ``read_rosbag`` needs ``rosbags`` (the ``slam`` extra), which reads both bag
formats without a ROS installation. ``scan_from_laserscan`` turns one message, from a bag or from a
live subscription, into a ``Scan`` for ``slam.Slam.add`` (no ROS package needed: it reads the
message's fields). Conventions, beyond those of ``logs``:

- Each scan's angles are ``angle_min + i * angle_increment``; a reading below ``range_min`` or not
  finite and negative is invalid (NaN), one at or above ``range_max`` (or +inf) is no return.
- Each scan's pose is the odometry pose at the scan's header stamp, interpolated linearly between
  the two odometry messages around it (headings unwrapped), composed with the laser's mounting:
  its pose in the odometry's child frame (the robot's base), given (``laser_pose``, ``upside_down``)
  or read from the bag's ``/tf_static`` (the chain of fixed transforms from the base to the scans'
  frame, projected onto the floor: the laser level, or upside down, when its beams' angles are
  negated).
  Without either, or when the scans' frame is the base's, the laser sits at the base (with a
  ``LaserMountWarning`` when the two frames differ). Moving transforms (``/tf``) are not read.
  Scans before the first or after the last odometry message are left out, and so counted in
  ``read_rosbag``'s second return value.
- A bag with several LaserScan (or Odometry) topics needs the topic named.
"""

import math
import warnings
from pathlib import Path

import numpy as np

from ._errors import InvalidOptionError, LogFileError, LogFormatError
from ._se2 import compose, wrap_angle
from .logs import _MAX_BEAMS as MAX_BEAMS
from .logs import MAX_ANGLE, MAX_COORDINATE, LaserLog, Scan, yaw_of_quaternion

__all__ = ["LaserMountWarning", "laser_mount", "read_rosbag", "scan_from_laserscan"]

SCAN_TYPE = "sensor_msgs/msg/LaserScan"
ODOMETRY_TYPE = "nav_msgs/msg/Odometry"
TF_TYPE = "tf2_msgs/msg/TFMessage"
# a laser counts as level (or upside down) when its z axis lies within this of the base's (or of
# its opposite): its beams then sweep the floor plane to within the cosine's error
LEVEL_TOLERANCE = math.radians(5.0)
MAX_MOUNT_M = 100.0                     # a laser this far from the robot's base is a units mistake


class LaserMountWarning(UserWarning):
    """The bag does not say where the laser sits on the robot: it is taken to sit at the base."""


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


def scan_from_laserscan(msg, pose, *, upside_down: bool = False) -> Scan:
    """A ``sensor_msgs/LaserScan`` message (ROS 1 or 2, from a bag or a live subscription: any
    object with its fields) as a ``Scan`` at ``pose``, the laser's (x, y, theta) in the odometry
    frame at the message's stamp (the caller's odometry or TF lookup, composed with the laser's
    mounting: ``laser_mount``), for ``slam.Slam.add``. ``upside_down``: the laser is mounted
    upside down (as ``laser_mount`` says), and its beams' angles are negated. Ranges as the module
    docstring says; a message with more than ``logs`` allows of beams, or without a finite
    ``range_max`` > 0, a finite ``angle_min`` and a non-zero ``angle_increment`` keeping every beam
    within one turn, raises LogFormatError."""
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
    if upside_down:
        angles = -angles
    pose = np.array(pose, dtype=np.float64)
    for array in (r, angles, pose):
        array.setflags(write=False)
    return Scan(float(t), r, angles, pose, max_range)


def _rotation(q):
    """The 3 x 3 rotation of a unit quaternion (x, y, z, w)."""
    x, y, z, w = q
    return np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
                     [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
                     [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)]])


def _up_to_root(transforms, frame: str) -> dict:
    """{ancestor: (rotation, translation) of ``frame`` in it} for ``frame`` and each frame above it
    (``transforms`` as ``laser_mount`` takes them), up to the root or a cycle. A transform without a
    finite translation within ``MAX_MOUNT_M`` and a unit quaternion is a LogFormatError."""
    rotation, translation = np.eye(3), np.zeros(3)
    chain = {frame: (rotation, translation)}
    while frame in transforms:
        parent, t, q = transforms[frame]
        parent = parent.lstrip("/")
        q, t = np.asarray(q, dtype=np.float64), np.asarray(t, dtype=np.float64)
        if not (np.all(np.isfinite(t)) and np.abs(t).max() <= MAX_MOUNT_M and np.all(np.isfinite(q))
                and abs(np.linalg.norm(q) - 1.0) <= 1e-3):
            raise LogFormatError(f"the static transform from {parent!r} to {frame!r} needs a finite translation "
                                 f"within {MAX_MOUNT_M:g} m (metres) and a unit quaternion; got {tuple(t)}, {tuple(q)}")
        step = _rotation(q / np.linalg.norm(q))
        rotation, translation = step @ rotation, step @ translation + t
        if parent in chain:                   # a cycle: no root above
            break
        chain[parent] = (rotation, translation)
        frame = parent
    return chain


def laser_mount(transforms, base: str, laser: str):
    """The laser's mounting on the floor plane: ((x, y, theta) of the laser frame in the base frame,
    upside_down), from ``transforms``, {child frame: (parent frame, (tx, ty, tz), (qx, qy, qz, qw))}
    as ``geometry_msgs/TransformStamped`` give them (``/tf_static``): through the nearest frame
    both lie under (either may be the other's ancestor); None when no transforms join them. Each
    transform must hold a finite translation within ``MAX_MOUNT_M`` and a unit quaternion, and the
    laser be level or upside down (its z axis within ``LEVEL_TOLERANCE`` of the base's or of its
    opposite), else LogFormatError: its beams would not sweep the floor plane.
    """
    base, laser = base.lstrip("/"), laser.lstrip("/")
    above_base, above_laser = _up_to_root(transforms, base), _up_to_root(transforms, laser)
    common = next((frame for frame in above_laser if frame in above_base), None)
    if common is None:
        return None
    r_base, t_base = above_base[common]
    r_laser, t_laser = above_laser[common]
    rotation, translation = r_base.T @ r_laser, r_base.T @ (t_laser - t_base)      # base_T_laser
    if np.abs(translation).max() > MAX_MOUNT_M:
        raise LogFormatError(f"the laser's frame {laser!r} lies {np.abs(translation).max():.3g} m from {base!r} "
                             f"in the static transforms: more than {MAX_MOUNT_M:g} m (metres expected)")
    up = rotation[2, 2]                       # the laser's z axis against the base's
    if abs(up) < math.cos(LEVEL_TOLERANCE):
        tilt = math.degrees(math.acos(min(abs(up), 1.0)))
        raise LogFormatError(f"the laser's frame {laser!r} is tilted {tilt:.2f} degrees from level in {base!r} "
                             f"(at most {math.degrees(LEVEL_TOLERANCE):g}): its beams do not sweep the floor plane")
    theta = math.atan2(rotation[1, 0], rotation[0, 0])
    return (float(translation[0]), float(translation[1]), theta), bool(up < 0)


def read_rosbag(path, *, scan_topic: str = None, odometry_topic: str = None, laser_pose=None,
                upside_down: bool = False):
    """Read a ROS 1 (``.bag``) or ROS 2 (folder or ``.db3``/``.mcap``) bag.

    ``laser_pose``: the laser's (x, y, theta) in the odometry's child frame (metres, radians), level,
    or with ``upside_down`` mounted upside down (its beams' angles negated); None (the default):
    from the bag's ``/tf_static`` (see the module docstring).

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
    mount = None
    if not isinstance(upside_down, (bool, np.bool_)):
        raise InvalidOptionError(f"upside_down must be True or False; got {upside_down!r}")
    if upside_down and laser_pose is None:
        raise InvalidOptionError("upside_down goes with laser_pose (without it the bag's /tf_static says how the "
                                 "laser is mounted)")
    if laser_pose is not None:
        try:
            given = np.asarray(laser_pose)
            given = given.astype(np.float64) if given.dtype.kind in "iuf" else np.full(3, np.nan)
        except (TypeError, ValueError, OverflowError):
            given = np.full(3, np.nan)
        if (given.shape != (3,) or not np.all(np.isfinite(given)) or np.abs(given[:2]).max() > MAX_MOUNT_M
                or abs(given[2]) > 2 * math.pi):
            raise InvalidOptionError(f"laser_pose must be three numbers (x, y, theta): x and y metres within "
                                     f"{MAX_MOUNT_M:g}, theta radians within 2 pi; got {laser_pose!r}")
        mount = (tuple(float(v) for v in given), bool(upside_down))
    path = Path(path)
    bag = path.parent if path.suffix in (".db3", ".mcap") else path
    scans, odometry, static, bases = [], [], {}, set()
    try:
        with AnyReader([bag], default_typestore=get_typestore(Stores.ROS2_HUMBLE)) as reader:
            scan_name = _topic(reader.connections, SCAN_TYPE, scan_topic, path)
            odom_name = _topic(reader.connections, ODOMETRY_TYPE, odometry_topic, path)
            wanted = [c for c in reader.connections if c.topic in (scan_name, odom_name)
                      or (c.topic == "/tf_static" and c.msgtype == TF_TYPE)]
            for connection, _, raw in reader.messages(connections=wanted):
                msg = reader.deserialize(raw, connection.msgtype)
                if connection.topic == "/tf_static":
                    for tf in msg.transforms:
                        t, q = tf.transform.translation, tf.transform.rotation
                        static[tf.child_frame_id.lstrip("/")] = (tf.header.frame_id, (t.x, t.y, t.z),
                                                                 (q.x, q.y, q.z, q.w))
                elif connection.topic == odom_name:
                    bases.add(msg.child_frame_id.lstrip("/"))
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
    (mount, upside_down), said = _mount_from_bag(path, static, bases, scans, mount)
    out, left_out = [], 0
    for msg in sorted(scans, key=lambda m: _stamp(m.header)):
        t = _stamp(msg.header)
        if not odo[0, 0] <= t <= odo[-1, 0]:
            left_out += 1
            continue
        pose = np.array([np.interp(t, odo[:, 0], odo[:, 1]), np.interp(t, odo[:, 0], odo[:, 2]),
                         np.interp(t, odo[:, 0], heading)])
        pose = compose(pose, mount)                   # the laser's pose, its heading wrapped
        try:
            out.append(scan_from_laserscan(msg, pose, upside_down=upside_down))
        except LogFormatError as exc:
            raise LogFormatError(f"{path}: {exc}") from None
    if not out:
        raise LogFormatError(f"{path}: no LaserScan inside the odometry's time span")
    x, y, theta = mount
    said = f"x {x:.4g} m, y {y:.4g} m, theta {theta:.4g} rad{', upside down' if upside_down else ''} ({said})"
    return LaserLog(tuple(out), odo, laser_mount=said), left_out


def _mount_from_bag(path, static, bases, scans, given):
    """The scans' mounting and where it came from, in words: ``given`` (``laser_pose``), with a
    ``LaserMountWarning`` when the bag's static transforms say otherwise; else ``laser_mount`` from
    the odometry's child frame to the scans' frame: identity when they are one frame; identity with
    a ``LaserMountWarning`` when one is unnamed or no static transform joins them."""
    def warn(text):
        warnings.warn(f"{path}: {text}", LaserMountWarning, stacklevel=4)

    frames = {msg.header.frame_id.lstrip("/") for msg in scans}
    if given is None and len(bases) > 1:
        raise LogFormatError(f"{path}: the odometry moves several frames {sorted(bases)}; name one topic")
    if given is None and len(frames) > 1:
        raise LogFormatError(f"{path}: the LaserScan messages come in several frames {sorted(frames)}")
    base, laser = (next(iter(bases)) if len(bases) == 1 else ""), (next(iter(frames)) if len(frames) == 1 else "")
    try:
        found = laser_mount(static, base, laser) if base and laser and base != laser else None
    except LogFormatError as exc:
        if given is None:
            raise LogFormatError(f"{path}: {exc}") from None
        found = None
    if given is not None:
        apart = np.subtract(found[0], given[0]) if found is not None else np.zeros(3)
        apart[2] = wrap_angle(apart[2])
        if found is not None and (found[1] != given[1] or np.abs(apart).max() > 1e-3):
            said = {False: "level", True: "upside down"}
            warn(f"laser_pose {given[0]}, {said[given[1]]}, differs from the bag's static transforms from {base!r} "
                 f"to {laser!r}: {found[0]}, {said[found[1]]}; laser_pose is used")
        return given, "as given: laser_pose"
    if base and base == laser:
        return ((0.0, 0.0, 0.0), False), f"the scans' frame is the odometry's, {base!r}"
    if found is None:
        if not base or not laser:
            warn(f"the odometry's child frame {base!r} or the scans' frame {laser!r} is unnamed: the laser is taken "
                 f"to sit at the robot's base (give its pose: laser_pose, --laser-pose)")
        else:
            warn(f"no static transform (/tf_static) joins the odometry's frame {base!r} and the scans' frame "
                 f"{laser!r}: the laser is taken to sit at {base!r} (give its pose: laser_pose, --laser-pose)")
        return ((0.0, 0.0, 0.0), False), "taken to sit at the robot's base: no transform found"
    return found, f"the bag's /tf_static from {base!r} to {laser!r}"
