"""Eq. (11): the covariance of the pose from the numeric Hessian of the discrepancy.

``cov(r*) ~ H(e)^-1``. In a corridor, at a kink or with little overlap, H is singular or
indefinite. We compare its eigenvalues in scaled coordinates (theta multiplied by a length, the
matcher's B rms radius, so every axis is in metres): a direction whose curvature is below ``degenerate_rtol``
times the largest is reported as degenerate, and every eigenvalue is floored at ``floor_rtol``
times the largest (and at an absolute ``floor_abs``) before inversion, so an unconstrained
direction shows as a very large but finite variance, never NaN.
"""

import numpy as np

__all__ = ["covariance_from_hessian"]


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
