"""SE(2) helpers: eq. (4) of the paper.

A pose ``r_A2B = (x, y, theta)`` maps points of frame B into frame A::

    v_A = R(theta) @ v_B + (x, y)

in metres and radians, theta reported in (-pi, pi].
"""

import numpy as np

from ._errors import InvalidPoseError

__all__ = ["wrap_angle", "as_pose", "as_poses", "rotation", "transform_points", "compose", "inverse"]


def wrap_angle(theta):
    """Wrap angles (radians) into (-pi, pi]."""
    theta = np.asarray(theta, dtype=np.float64)
    wrapped = np.pi - np.mod(np.pi - theta, 2.0 * np.pi)
    return wrapped if wrapped.ndim else float(wrapped)


def as_pose(pose, name="pose"):
    """Validate one pose: a finite array of shape (3,), float64."""
    try:
        arr = np.asarray(pose, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise InvalidPoseError(f"{name} must be three numbers (x, y, theta); got {pose!r}") from exc
    if arr.shape != (3,):
        raise InvalidPoseError(f"{name} must have shape (3,) as (x, y, theta); got shape {arr.shape}")
    if not np.all(np.isfinite(arr)):
        raise InvalidPoseError(f"{name} must be finite; got {arr.tolist()}")
    return arr


def as_poses(poses, name="poses"):
    """Validate a batch of poses: a finite array of shape (N, 3), float64 (one pose is promoted)."""
    try:
        arr = np.asarray(poses, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise InvalidPoseError(f"{name} must be an (N, 3) array of (x, y, theta); got {poses!r}") from exc
    if arr.ndim == 1 and arr.shape == (3,):
        arr = arr[None, :]
    if arr.ndim != 2 or arr.shape[1] != 3:
        raise InvalidPoseError(f"{name} must have shape (N, 3) as rows of (x, y, theta); got shape {arr.shape}")
    if not np.all(np.isfinite(arr)):
        raise InvalidPoseError(f"{name} must be finite")
    return arr


def rotation(theta):
    """The 2x2 rotation matrix R(theta)."""
    c, s = np.cos(theta), np.sin(theta)
    return np.array([[c, -s], [s, c]])


def transform_points(pose_a2b, points_b):
    """Map points (..., 2) given in frame B into frame A with pose r_A2B (eq. 4)."""
    x, y, theta = pose_a2b
    points_b = np.asarray(points_b, dtype=np.float64)
    return points_b @ rotation(theta).T + np.array([x, y])


def compose(pose_a2b, pose_b2c):
    """r_A2C = r_A2B (+) r_B2C."""
    x, y, theta = pose_a2b
    t = transform_points(pose_a2b, np.asarray(pose_b2c[:2], dtype=np.float64))
    return np.array([t[0], t[1], wrap_angle(theta + pose_b2c[2])])


def inverse(pose_a2b):
    """r_B2A, the inverse of r_A2B."""
    x, y, theta = pose_a2b
    t = -rotation(theta).T @ np.array([x, y])
    return np.array([t[0], t[1], wrap_angle(-theta)])
