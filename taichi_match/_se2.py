"""SE(2) helpers: eq. (4) of the paper.

A pose ``r_A2B = (x, y, theta)`` maps points of frame B into frame A::

    v_A = R(theta) @ v_B + (x, y)

in metres and radians, theta reported in (-pi, pi].
"""

import math

import numpy as np
import numpy.typing as npt

from ._errors import InvalidPoseError, shown

__all__ = ["wrap_angle", "as_pose", "as_poses", "rotation", "transform_points", "compose", "inverse"]


def wrap_angle(theta: npt.ArrayLike) -> float | np.ndarray:
    """Wrap angles (radians) into (-pi, pi].

    Parameters
    ----------
    theta : float or array_like
        Angles in radians, any range.

    Returns
    -------
    float or numpy.ndarray
        The same angles in (-pi, pi]: a float for a scalar input, else a float64 array of the
        input's shape.

    Examples
    --------
    >>> import numpy as np
    >>> from taichi_match import wrap_angle
    >>> print(f"{wrap_angle(3 * np.pi / 2):.4f}")
    -1.5708
    >>> wrap_angle([-np.pi, np.pi, 7.0]).round(4).tolist()      # -pi becomes +pi
    [3.1416, 3.1416, 0.7168]
    """
    theta = np.asarray(theta, dtype=np.float64)
    wrapped = np.pi - np.mod(np.pi - theta, 2.0 * np.pi)
    # the modulo rounds up to 2 pi itself for theta just above pi (and its turns): -pi, which is pi
    wrapped = np.where(wrapped == -np.pi, np.pi, wrapped)
    return wrapped if wrapped.ndim else float(wrapped)


def as_pose(pose: npt.ArrayLike, name: str = "pose") -> np.ndarray:
    """Validate one pose: a finite array of shape (3,), float64.

    Parameters
    ----------
    pose : array_like, shape (3,)
        (x, y, theta) in metres and radians.
    name : str
        The argument's name in the error message.

    Returns
    -------
    numpy.ndarray, shape (3,)
        The pose as float64 (theta not wrapped).

    Raises
    ------
    InvalidPoseError
        If ``pose`` is not three finite numbers.

    Examples
    --------
    >>> from taichi_match._se2 import as_pose
    >>> as_pose([1, 2, 0.5]).tolist()
    [1.0, 2.0, 0.5]
    """
    try:
        arr = np.asarray(pose, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise InvalidPoseError(f"{name} must be three numbers (x, y, theta); got {shown(pose)}") from exc
    if arr.shape != (3,):
        raise InvalidPoseError(f"{name} must have shape (3,) as (x, y, theta); got shape {arr.shape}")
    if not np.all(np.isfinite(arr)):
        raise InvalidPoseError(f"{name} must be finite; got {arr.tolist()}")
    return arr


def as_poses(poses: npt.ArrayLike, name: str = "poses") -> np.ndarray:
    """Validate a batch of poses: a finite array of shape (N, 3), float64 (one pose is promoted).

    Parameters
    ----------
    poses : array_like, shape (N, 3) or (3,)
        Rows of (x, y, theta) in metres and radians; a single pose of shape (3,) becomes one row.
    name : str
        The argument's name in the error message.

    Returns
    -------
    numpy.ndarray, shape (N, 3)
        The poses as float64 (theta not wrapped).

    Raises
    ------
    InvalidPoseError
        If ``poses`` is not of shape (N, 3) or (3,), or holds a non-finite value.

    Examples
    --------
    >>> from taichi_match._se2 import as_poses
    >>> as_poses((1, 2, 0.5)).tolist()
    [[1.0, 2.0, 0.5]]
    >>> as_poses([[0.0, 0.0]])
    Traceback (most recent call last):
        ...
    taichi_match._errors.InvalidPoseError: poses must have shape (N, 3) as rows of (x, y, theta); got shape (1, 2)
    """
    try:
        arr = np.asarray(poses, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise InvalidPoseError(f"{name} must be an (N, 3) array of (x, y, theta); got {shown(poses)}") from exc
    if arr.ndim == 1 and arr.shape == (3,):
        arr = arr[None, :]
    if arr.ndim != 2 or arr.shape[1] != 3:
        raise InvalidPoseError(f"{name} must have shape (N, 3) as rows of (x, y, theta); got shape {arr.shape}")
    if not np.all(np.isfinite(arr)):
        raise InvalidPoseError(f"{name} must be finite")
    return arr


def rotation(theta: float) -> np.ndarray:
    """The 2x2 rotation matrix R(theta).

    Parameters
    ----------
    theta : float
        Angle in radians, counter-clockwise.

    Returns
    -------
    numpy.ndarray, shape (2, 2)

    Examples
    --------
    >>> import numpy as np
    >>> from taichi_match._se2 import rotation
    >>> (rotation(np.pi / 2) @ [1.0, 0.0]).round(3).tolist()
    [0.0, 1.0]
    """
    c, s = np.cos(theta), np.sin(theta)
    return np.array([[c, -s], [s, c]])


def transform_points(pose_a2b: npt.ArrayLike, points_b: npt.ArrayLike) -> np.ndarray:
    """Map points (..., 2) given in frame B into frame A with pose r_A2B (eq. 4).

    Parameters
    ----------
    pose_a2b : array_like, shape (3,)
        r_A2B = (x, y, theta), metres and radians: B's frame in A's.
    points_b : array_like, shape (..., 2)
        Points (x, y) in frame B, metres.

    Returns
    -------
    numpy.ndarray, shape (..., 2)
        The points in frame A: R(theta) @ v_B + (x, y).

    Examples
    --------
    >>> import numpy as np
    >>> from taichi_match import transform_points
    >>> transform_points((1.0, 0.0, np.pi / 2), [[1.0, 0.0], [0.0, 2.0]]).round(3).tolist()
    [[1.0, 1.0], [-1.0, 0.0]]
    """
    x, y, theta = pose_a2b
    points_b = np.asarray(points_b, dtype=np.float64)
    return points_b @ rotation(theta).T + np.array([x, y])


def compose(pose_a2b: npt.ArrayLike, pose_b2c: npt.ArrayLike) -> np.ndarray:
    """r_A2C = r_A2B (+) r_B2C.

    Parameters
    ----------
    pose_a2b : array_like, shape (3,) or (..., 3)
        r_A2B = (x, y, theta): B's frame in A's, metres and radians.
    pose_b2c : array_like, shape (3,) or (..., 3)
        r_B2C: C's frame in B's. Batches of poses broadcast against each other.

    Returns
    -------
    numpy.ndarray, shape (3,) or the broadcast (..., 3)
        r_A2C, C's frame in A's, theta wrapped into (-pi, pi]: mapping a point of C into B and
        then into A is mapping it into A with r_A2C. A batch gives each pose the same bits as
        composing it alone where NumPy's cosine and sine are the C library's (NumPy 1.25 on; 1.23
        and 1.24 on AVX-512 machines differ in the last bit).

    Examples
    --------
    >>> import numpy as np
    >>> from taichi_match import compose, inverse, transform_points
    >>> a2b, b2c = (1.0, 0.0, np.pi / 2), (2.0, 0.0, np.pi)
    >>> a2c = compose(a2b, b2c)
    >>> a2c.round(3).tolist()
    [1.0, 2.0, -1.571]
    >>> point_c = [0.5, 0.25]
    >>> np.allclose(transform_points(a2c, point_c), transform_points(a2b, transform_points(b2c, point_c)))
    True
    >>> print(" ".join(f"{abs(v):.3f}" for v in compose(a2b, inverse(a2b))))
    0.000 0.000 0.000
    """
    a, b = np.asarray(pose_a2b, dtype=np.float64), np.asarray(pose_b2c, dtype=np.float64)
    if a.shape == b.shape == (3,) and math.isfinite(a[2]):
        # one pose: plain floats (the same IEEE arithmetic and libm as the batch, a fifth of the
        # time: the mapping loop composes tens of thousands of single poses a run)
        (x, y, theta), (bx, by, b_theta) = a.tolist(), b.tolist()
        c, s = math.cos(theta), math.sin(theta)
        return np.array([c * bx - s * by + x, s * bx + c * by + y, _wrapped(theta + b_theta)])
    _check_components(a, b)         # (a heading not finite comes here: NumPy's cosine NaN, math's raises)
    c, s = np.cos(a[..., 2]), np.sin(a[..., 2])
    return np.stack([c * b[..., 0] - s * b[..., 1] + a[..., 0], s * b[..., 0] + c * b[..., 1] + a[..., 1],
                     wrap_angle(a[..., 2] + b[..., 2])], axis=-1)


def inverse(pose_a2b: npt.ArrayLike) -> np.ndarray:
    """r_B2A, the inverse of r_A2B.

    Parameters
    ----------
    pose_a2b : array_like, shape (3,) or (..., 3)
        r_A2B = (x, y, theta), metres and radians (a batch: each pose's inverse).

    Returns
    -------
    numpy.ndarray, of the input's shape
        r_B2A = (-R(theta)^T (x, y), -theta), theta wrapped into (-pi, pi].

    Examples
    --------
    >>> import numpy as np
    >>> from taichi_match import inverse
    >>> inverse((1.0, 2.0, np.pi / 2)).round(3).tolist()
    [-2.0, 1.0, -1.571]
    """
    a = np.asarray(pose_a2b, dtype=np.float64)
    if a.shape == (3,) and math.isfinite(a[2]):
        x, y, theta = a.tolist()
        c, s = math.cos(theta), math.sin(theta)
        return np.array([-(c * x + s * y), s * x - c * y, _wrapped(-theta)])
    _check_components(a)
    c, s = np.cos(a[..., 2]), np.sin(a[..., 2])
    x, y = a[..., 0], a[..., 1]
    return np.stack([-(c * x + s * y), s * x - c * y, wrap_angle(-a[..., 2])], axis=-1)


def _wrapped(theta: float) -> float:
    """``wrap_angle`` of one float, in plain floats (Python's float modulo is NumPy's: the same bits)."""
    wrapped = math.pi - (math.pi - theta) % (2.0 * math.pi)
    return math.pi if wrapped == -math.pi else wrapped


def _check_components(*poses: np.ndarray) -> None:
    """Poses or batches of them: (x, y, theta) along the last axis, else an InvalidPoseError."""
    for pose in poses:
        if pose.ndim == 0 or pose.shape[-1] != 3:
            raise InvalidPoseError(f"a pose has three components (x, y, theta) along its last axis; got shape "
                                   f"{pose.shape}")
