"""Eq. (11): the covariance of the pose from the numeric Hessian of the discrepancy.

``cov(r*) ~ H(e)^-1``. In a corridor, at a kink or with little overlap, H is singular or
indefinite. We compare its eigenvalues in scaled coordinates (theta multiplied by a length, the
matcher's B rms radius, so every axis is in metres): a direction whose curvature is below ``degenerate_rtol``
times the largest is reported as degenerate, and every eigenvalue is floored at ``floor_rtol``
times the largest (and at an absolute ``floor_abs``) before inversion, so an unconstrained
direction shows as a very large but finite variance, never NaN.
"""

import numpy as np

__all__ = ["covariance_from_hessian", "covariance_floor", "FLOOR_CELLS"]

# The standard deviation, in cells of A, of the error that the Hessian cannot see: e is flat
# within a cell (nearest-cell lookups), so the minimum is a plateau about a cell wide, and the
# prior parks the pose anywhere on it. Fitted with CALIBRATED_COVARIANCE_SCALE (bench/TUNING.md).
FLOOR_CELLS = 0.1


def covariance_from_hessian(hessian, rotation_scale, *, scale=1.0, degenerate_rtol=1e-3,
                            floor_rtol=1e-9, floor_abs=1e-12):
    """Return (covariance 3x3, degenerate directions (k, 3) as unit vectors in (x, y, theta))."""
    h = np.asarray(hessian, dtype=np.float64)
    h = 0.5 * (h + h.T)
    d = np.array([1.0, 1.0, 1.0 / rotation_scale])      # z = r / d: theta in metres
    hz = h * np.outer(d, d)
    evals, evecs = np.linalg.eigh(hz)
    top = max(float(evals.max()), 0.0)
    floor = max(floor_rtol * top, floor_abs)
    cov_z = (evecs / np.maximum(evals, floor)) @ evecs.T
    cov = scale * cov_z * np.outer(d, d)
    degenerate = evals <= max(degenerate_rtol * top, floor_abs)
    dirs = evecs[:, degenerate].T * d                    # back to (x, y, theta) units
    dirs = dirs / np.linalg.norm(dirs, axis=1, keepdims=True) if len(dirs) else np.zeros((0, 3))
    signs = np.where(dirs[np.arange(len(dirs)), np.abs(dirs).argmax(axis=1)] < 0, -1.0, 1.0)
    return cov, dirs * signs[:, None]


def covariance_floor(resolution, centroid, spread, theta, cells=None):
    """The covariance (x, y, theta) of an error of ``cells`` cells (default ``FLOOR_CELLS``) of
    size ``resolution`` at B's centroid in each direction, and of a rotation moving a typical
    cell of B (at rms distance ``spread`` from the centroid ``centroid`` in B's frame) as far."""
    sd = (FLOOR_CELLS if cells is None else cells) * resolution
    c, s = np.cos(theta), np.sin(theta)
    cx, cy = centroid
    to_z = np.array([[1.0, 0.0, -s * cx - c * cy], [0.0, 1.0, c * cx - s * cy], [0.0, 0.0, spread]])
    from_z = np.linalg.inv(to_z)
    return sd * sd * (from_z @ from_z.T)
