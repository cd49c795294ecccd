"""Trajectory errors against a reference, as evo computes them (checked against evo in the tests).

- ATE: the estimate aligned to the reference by the rigid SE(2) motion that best fits the
  positions (Umeyama, without scale), then the RMSE of the position errors and of the heading
  errors.
- RPE over ``delta`` scans: for each pair (i, i + delta) the relative motion of the estimate
  against the reference's, ``E = (Q_i^-1 Q_i+d)^-1 (P_i^-1 P_i+d)``; the RMSE of |E|'s translation
  and of its angle.
- A submap frame's reference pose (``frame_reference``): the rigid motion that carries the poses
  its scans were cast at, in the frame, onto their reference poses, so a frame is judged by the
  whole grid a match saw.

Poses (N, 3) as (x, y, theta), metres and radians, one row per scan in both; degrees out.
"""

import math

import numpy as np

from ._se2 import compose, inverse, wrap_angle

__all__ = ["align_se2", "frame_reference", "trajectory_errors"]


def align_se2(poses, reference):
    """``poses`` moved by the rigid SE(2) motion that best fits their positions to the reference's."""
    p, q = np.asarray(poses, dtype=np.float64), np.asarray(reference, dtype=np.float64)
    mp, mq = p[:, :2].mean(axis=0), q[:, :2].mean(axis=0)
    u, _, vt = np.linalg.svd((q[:, :2] - mq).T @ (p[:, :2] - mp))
    d = np.diag([1.0, np.sign(np.linalg.det(u @ vt))])
    r = u @ d @ vt
    theta = np.arctan2(r[1, 0], r[0, 0])
    t = mq - r @ mp
    return np.array([compose((t[0], t[1], theta), row) for row in p])


def _relative(poses, delta):
    return np.array([compose(inverse(a), b) for a, b in zip(poses[:-delta], poses[delta:])])


def trajectory_errors(poses, reference, delta: int = 10) -> dict:
    """ATE and RPE (see the module docstring): {"ate_m", "ate_deg", "rpe_m", "rpe_deg"}."""
    poses, reference = np.asarray(poses, dtype=np.float64), np.asarray(reference, dtype=np.float64)
    if poses.shape != reference.shape or poses.ndim != 2 or poses.shape[1] != 3:
        raise ValueError(f"poses {poses.shape} and reference {reference.shape} must both be (N, 3)")
    for name, array in (("poses", poses), ("reference", reference)):
        if not np.all(np.isfinite(array)) or np.abs(array[:, :2]).max(initial=0.0) > 1e6:
            raise ValueError(f"{name} must be finite, positions within 1e6 m")
    aligned = align_se2(poses, reference)
    out = {"ate_m": float(np.sqrt(np.mean(np.sum((aligned[:, :2] - reference[:, :2]) ** 2, axis=1)))),
           "ate_deg": float(np.degrees(np.sqrt(np.mean(wrap_angle(aligned[:, 2] - reference[:, 2]) ** 2))))}
    if len(poses) > delta:
        est, ref = _relative(poses, delta), _relative(reference, delta)
        e = np.array([compose(inverse(b), a) for a, b in zip(est, ref)])
        out["rpe_m"] = float(np.sqrt(np.mean(e[:, 0] ** 2 + e[:, 1] ** 2)))
        out["rpe_deg"] = float(np.degrees(np.sqrt(np.mean(wrap_angle(e[:, 2]) ** 2))))
    else:
        out["rpe_m"] = out["rpe_deg"] = float("nan")
    return out


def frame_reference(scans, poses, reference) -> np.ndarray:
    """The reference pose (x, y, theta) of a submap's frame.

    Parameters
    ----------
    scans : array_like of int
        The indices, into ``reference``, of the scans the submap holds.
    poses : array_like, shape (len(scans), 3)
        The poses those scans were cast at, in the submap's frame.
    reference : array_like, shape (N, 3)
        The reference trajectory, one row per scan.

    Returns
    -------
    numpy.ndarray
        The rigid motion that best carries ``poses`` onto ``reference[scans]``: its rotation is
        the circular mean of the heading offsets, its translation the mean position offset once
        rotated.
    """
    ref = np.asarray(reference, dtype=np.float64)[np.asarray(scans, dtype=np.intp)]
    poses = np.asarray(poses, dtype=np.float64).reshape(-1, 3)
    theta = math.atan2(np.sin(ref[:, 2] - poses[:, 2]).mean(), np.cos(ref[:, 2] - poses[:, 2]).mean())
    c, s = math.cos(theta), math.sin(theta)
    moved = poses[:, :2] @ np.array([[c, s], [-s, c]])
    t = (ref[:, :2] - moved).mean(axis=0)
    return np.array([t[0], t[1], theta])
