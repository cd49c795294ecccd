"""Laser log files: CARMEN logs (scans with odometry) and TUM trajectories.

Apart from the core (which never imports it). Conventions:

- A ``Scan`` holds one 2-D laser scan: ``ranges`` (n,) metres along ``angles`` (n,) radians in the
  laser's frame (counter-clockwise from its x axis, which looks forward), the laser's ``pose``
  (x, y, theta) in the log's odometry frame as the log records it, and the scan's ``timestamp``
  in seconds. A range at or above ``max_range`` means no return.
- CARMEN ``FLASER n r_1 .. r_n x y theta odom_x odom_y odom_theta timestamp host logger_timestamp``:
  the first beam at -90 degrees (the robot's right), the others counter-clockwise at the SICK
  scanners' angular steps: 180 / (n - 1) degrees for an odd n (181 beams: 1 degree, 361: 0.5,
  the last beam at +90) and 180 / n for an even n (180 beams: 1 degree, 360: 0.5, the last beam
  one step short of +90), as GMapping's CARMEN reader has it. On the logs of ``shared/logs``
  this gives sharper maps than spreading every count over exactly 180 degrees (the distinct
  5 cm cells holding returns of 20 consecutive scans: aces, 180 beams, 0.517 against 0.537 per
  return; freiburg-101, 360 beams, 0.352 against 0.367). The laser pose is (x, y, theta).
  ``ROBOTLASER1`` lines carry their own start angle, angular step, maximum range and laser pose.
  ``ODOM x y theta tv rv accel timestamp host logger_timestamp`` lines are kept apart as the
  odometry stream. Other lines are ignored.
- TUM: ``timestamp x y z qx qy qz qw`` per line; the planar pose is (x, y, yaw about z).

Files may be gzipped (by content, whatever their name: ``.log``, ``.clf``, ``.gz``). A malformed
line raises ``LogFormatError`` naming the file and line; an unreadable file ``LogFileError``.
"""

import gzip
import math
import zlib
from dataclasses import dataclass
from pathlib import Path
from typing import Optional

import numpy as np

from ._errors import InvalidOptionError, LogFileError, LogFormatError, shown

__all__ = ["Scan", "LaserLog", "read_carmen", "write_carmen", "read_tum", "write_tum"]

# Lines longer than this are refused (the longest real laser lines hold a few thousand numbers).
_MAX_LINE = 1 << 20
# A log holds at most this many lines (a laser log of a million scans has a few million): a gzip
# of nothing but newlines, a thousand times smaller than what it unpacks to, is refused in seconds
# rather than read for minutes
MAX_LINES = 20_000_000
_MAX_BEAMS = 100_000
MAX_COORDINATE = 1e6         # metres: poses farther from the origin are refused as corrupt
MAX_ANGLE = 1e3              # radians (headings may be unwrapped, but not by 1e20)


@dataclass(frozen=True)
class Scan:
    """One laser scan; see the module docstring for the conventions."""

    timestamp: float
    ranges: np.ndarray
    angles: np.ndarray
    pose: np.ndarray
    max_range: float


@dataclass(frozen=True)
class LaserLog:
    """The scans of a log in file order, and its ODOM lines as (timestamp, x, y, theta) rows.
    ``laser_mount``: how a bag's scans were placed on the robot, in words (``bags.read_rosbag``);
    None for a CARMEN log, whose scans carry the laser's own pose."""

    scans: tuple
    odometry: np.ndarray
    laser_mount: Optional[str] = None

    @property
    def poses(self) -> np.ndarray:
        """(S, 3) the scans' recorded laser poses (odometry frame)."""
        return np.array([s.pose for s in self.scans]).reshape(-1, 3)

    @property
    def timestamps(self) -> np.ndarray:
        return np.array([s.timestamp for s in self.scans], dtype=np.float64)

    def __len__(self):
        return len(self.scans)


def _open_text(path):
    path = Path(path)
    try:
        if not path.is_file():
            raise LogFileError(f"{path}: not a regular file")
        with open(path, "rb") as raw:
            magic = raw.read(2)
        if magic == b"\x1f\x8b":
            return gzip.open(path, "rt", encoding="utf-8", errors="replace")
        return open(path, encoding="utf-8", errors="replace")
    except OSError as exc:
        if isinstance(exc, LogFileError):
            raise
        raise LogFileError(f"{path}: cannot read ({exc.strerror or exc})") from exc


def _lines(path):
    """(line number, stripped line) of a text or gzipped file, with read errors as LogFileError."""
    try:
        with _open_text(path) as f:
            number = 0
            while True:
                line = f.readline(_MAX_LINE + 1)            # never more than that in memory
                if not line:
                    break
                number += 1
                if number > MAX_LINES:
                    raise LogFormatError(f"{path}: more than {MAX_LINES} lines: not a laser log this reader takes")
                if len(line) > _MAX_LINE:
                    raise LogFormatError(f"{path}:{number}: line longer than {_MAX_LINE} characters")
                yield number, line.strip()
    except (OSError, EOFError, gzip.BadGzipFile, zlib.error) as exc:            # (a corrupt gzip body: zlib's)
        if isinstance(exc, LogFileError):
            raise
        raise LogFileError(f"{path}: cannot read ({exc})") from exc


def _floats(words, where):
    try:
        values = np.array([float(w) for w in words], dtype=np.float64)
    except ValueError as exc:
        raise LogFormatError(f"{where}: expected numbers; {exc}") from None
    return values


def _beam_count(word, where):
    try:
        n = int(word)
    except ValueError:
        raise LogFormatError(f"{where}: the number of beams {word!r} is not an integer") from None
    if not 1 <= n <= _MAX_BEAMS:
        raise LogFormatError(f"{where}: the number of beams must be in 1..{_MAX_BEAMS}; got {n}")
    return n


def _flaser(words, where):
    if len(words) < 2:
        raise LogFormatError(f"{where}: FLASER without the number of beams")
    n = _beam_count(words[1], where)
    if not 2 + n + 7 <= len(words) <= 2 + n + 9:
        raise LogFormatError(f"{where}: FLASER with {n} beams has {n + 7} to {n + 9} fields after n; "
                             f"got {len(words) - 2}")
    if len(words) > 2 + n + 7 and _is_number(words[2 + n + 7]):
        # the host's name where a number stands: the fields are off by one or two, and the beam
        # count is wrong (the last beams would be read as the pose, the pose as the timestamp)
        raise LogFormatError(f"{where}: FLASER with {n} beams: field {n + 8} after n should be the host's name, "
                             f"but it is the number {words[2 + n + 7]!r}: the number of beams disagrees with the "
                             f"line")
    ranges = _floats(words[2:2 + n], where)
    x, y, theta, _, _, _, timestamp = _floats(words[2 + n:2 + n + 7], where)
    return timestamp, ranges, flaser_angles(n), np.array([x, y, theta]), None


def _is_number(word) -> bool:
    try:
        float(word)
    except ValueError:
        return False
    return True


def flaser_angles(n):
    """The beam angles of a FLASER line with ``n`` beams (see the module docstring)."""
    step = math.pi / n if n % 2 == 0 else math.pi / max(n - 1, 1)
    return -math.pi / 2 + np.arange(n) * step


def yaw_of_quaternion(qx, qy, qz, qw):
    """The rotation about z of a quaternion (arrays or floats), radians."""
    return np.arctan2(2.0 * (qw * qz + qx * qy), 1.0 - 2.0 * (qy * qy + qz * qz))


def _robotlaser(words, where):
    # ROBOTLASER1 type start fov step max_range accuracy remission_mode n r_1..r_n m rem_1..rem_m
    #             laser_x laser_y laser_theta robot_x robot_y robot_theta tv rv fsd ssd turn timestamp ...
    if len(words) < 9:
        raise LogFormatError(f"{where}: ROBOTLASER1 line too short")
    start, _, step, max_range = _floats(words[2:6], where)
    n = _beam_count(words[8], where)
    base = 9 + n
    if len(words) < base + 1:
        raise LogFormatError(f"{where}: ROBOTLASER1 with {n} beams is truncated")
    m = _beam_count(words[base], where) if words[base] != "0" else 0
    tail = base + 1 + m
    if len(words) < tail + 12:
        raise LogFormatError(f"{where}: ROBOTLASER1 with {n} beams and {m} remissions is truncated")
    if not (np.isfinite(start) and np.isfinite(step) and step != 0.0 and abs(step) * (n - 1) <= 2 * math.pi + 1e-6
            and np.isfinite(max_range) and max_range > 0.0):
        raise LogFormatError(f"{where}: ROBOTLASER1 needs a finite start angle, a non-zero step with all beams within "
                             f"one turn and a finite maximum range > 0; got {start}, {step}, {max_range}")
    ranges = _floats(words[9:9 + n], where)
    x, y, theta = _floats(words[tail:tail + 3], where)
    timestamp = _floats(words[tail + 11:tail + 12], where)[0]
    return timestamp, ranges, start + np.arange(n) * step, np.array([x, y, theta]), max_range


def _saturation(raw):
    """The sensor's maximum range as FLASER scans show it: the largest value that is the largest
    reading of two scans or more (one bad reading of 65.5 m among readings saturated at 4 m made
    every 4 m reading a wall), else the largest reading; 0 without a finite reading."""
    tops = [float(ranges[np.isfinite(ranges)].max()) for _, ranges, *_ in raw if np.isfinite(ranges).any()]
    if not tops:
        return 0.0
    values, counts = np.unique(tops, return_counts=True)
    repeated = values[counts >= 2]
    return float(repeated[-1]) if len(repeated) else float(values[-1])


def read_carmen(path, *, max_range=None) -> LaserLog:
    """Read a CARMEN log (``FLASER``, ``ROBOTLASER1`` and ``ODOM`` lines; gzipped or not).

    Parameters
    ----------
    path : str or Path
        The log file.
    max_range : float, optional
        The sensor's maximum range, metres: a reading at or above it means no return. By default
        ROBOTLASER1 lines give their own and FLASER lines take the largest reading that is the
        largest of at least two scans (a saturated sensor reports exactly its maximum, again and
        again; a lone larger reading is a glitch), or the largest reading when none repeats.

    Returns
    -------
    LaserLog
    """
    if max_range is not None and not (isinstance(max_range, (int, float)) and not isinstance(max_range, bool)
                                      and math.isfinite(max_range) and max_range > 0):
        raise InvalidOptionError(f"max_range must be a finite number of metres > 0 or None; got {shown(max_range)}")
    raw, odometry = [], []
    for number, line in _lines(path):
        if not line or line.startswith("#"):
            continue
        words = line.split()
        where = f"{path}:{number}"
        if words[0] in ("FLASER", "ROBOTLASER1"):
            scan = _flaser(words, where) if words[0] == "FLASER" else _robotlaser(words, where)
            if not (np.isfinite(scan[0]) and np.all(np.isfinite(scan[3]))):
                raise LogFormatError(f"{where}: the scan's timestamp or pose is not finite")
            if np.abs(scan[3][:2]).max() > MAX_COORDINATE or abs(scan[3][2]) > MAX_ANGLE:
                raise LogFormatError(f"{where}: the scan's pose {tuple(scan[3])} lies beyond {MAX_COORDINATE:g} m "
                                     f"or {MAX_ANGLE:g} rad")
            raw.append(scan)
        elif words[0] == "ODOM":
            if len(words) < 8:
                raise LogFormatError(f"{where}: ODOM needs x y theta tv rv accel timestamp")
            x, y, theta, _, _, _, timestamp = _floats(words[1:8], where)
            odometry.append((timestamp, x, y, theta))
    if not raw:
        raise LogFormatError(f"{path}: no FLASER or ROBOTLASER1 line")
    inferred = _saturation(raw)
    if max_range is None and not inferred > 0 and any(own is None for *_, own in raw):
        raise LogFormatError(f"{path}: no usable beam: every FLASER range is NaN, infinite, zero or negative (and "
                             f"the sensor's maximum range cannot be inferred from them)")
    scans = []
    for timestamp, ranges, angles, pose, own_max in raw:
        limit = max_range if max_range is not None else (own_max if own_max is not None else inferred)
        ranges.setflags(write=False)
        angles.setflags(write=False)
        pose.setflags(write=False)
        scans.append(Scan(float(timestamp), ranges, angles, pose, float(limit)))
    odo = np.array(odometry, dtype=np.float64).reshape(-1, 4)
    return LaserLog(tuple(scans), odo)


def write_carmen(path, log: LaserLog):
    """Write ``log``'s scans as CARMEN ``FLASER`` lines (both poses the scan's pose; ranges to the
    millimetre). Their beams must follow FLASER's angles (see the module docstring), which is what
    ``read_carmen`` gives them back."""
    with open(path, "w", encoding="utf-8") as f:
        f.write("# written by taichi_match.logs.write_carmen\n")
        for scan in log.scans:
            n = len(scan.ranges)
            if not np.allclose(scan.angles, flaser_angles(n), atol=1e-9):
                raise ValueError("FLASER lines hold scans over 180 degrees from -90 only")
            x, y, theta = scan.pose
            ranges = " ".join(f"{r:.3f}" for r in scan.ranges)
            f.write(f"FLASER {n} {ranges} {x:.6f} {y:.6f} {theta:.6f} {x:.6f} {y:.6f} {theta:.6f} "
                    f"{scan.timestamp:.6f} taichi_match {scan.timestamp:.6f}\n")


def read_tum(path):
    """Read a TUM trajectory: (timestamps (N,), poses (N, 3) as x, y, yaw about z)."""
    rows = []
    for number, line in _lines(path):
        if not line or line.startswith("#"):
            continue
        words = line.split()
        if len(words) != 8:
            raise LogFormatError(f"{path}:{number}: a TUM line has 8 fields; got {len(words)}")
        rows.append(_floats(words, f"{path}:{number}"))
    if not rows:
        raise LogFormatError(f"{path}: no pose")
    data = np.array(rows)
    if not np.all(np.isfinite(data)):
        raise LogFormatError(f"{path}: values that are not finite")
    if np.abs(data[:, 1:3]).max() > MAX_COORDINATE:
        raise LogFormatError(f"{path}: positions beyond {MAX_COORDINATE:g} m")
    if not np.allclose(np.linalg.norm(data[:, 4:8], axis=1), 1.0, atol=1e-3):
        raise LogFormatError(f"{path}: quaternions that are not of unit length")
    qx, qy, qz, qw = data[:, 4:8].T
    yaw = yaw_of_quaternion(qx, qy, qz, qw)
    return data[:, 0], np.column_stack([data[:, 1], data[:, 2], yaw])


def write_tum(path, timestamps, poses):
    """Write planar poses (N, 3) with their timestamps (N,) as a TUM trajectory (z = 0). A timestamp
    is written with 6 decimals, or in full where those would change it (scans less than a
    microsecond apart kept apart)."""
    poses = np.asarray(poses, dtype=np.float64).reshape(-1, 3)
    timestamps = np.asarray(timestamps, dtype=np.float64).reshape(-1)
    if len(timestamps) != len(poses):
        raise ValueError(f"{len(timestamps)} timestamps for {len(poses)} poses")
    with open(path, "w", encoding="utf-8") as f:
        f.write("# timestamp x y z qx qy qz qw\n")
        for t, (x, y, yaw) in zip(timestamps, poses):
            stamp = f"{t:.6f}"
            if float(stamp) != t:
                stamp = repr(float(t))
            f.write(f"{stamp} {x:.6f} {y:.6f} 0 0 0 {math.sin(yaw / 2):.9f} {math.cos(yaw / 2):.9f}\n")
