"""Eq. (11): the covariance of the pose from the numeric Hessian of the discrepancy.

``cov(r*) ~ H(e)^-1``. In a corridor, at a kink or with little overlap, H is singular or
indefinite. We compare its eigenvalues in metric coordinates z = M r, every axis in metres (the
matcher's M: the position of B's centroid in A, and theta times B's rms radius about its
centroid; a scalar L means M = diag(1, 1, L)): a direction whose curvature is below
``degenerate_rtol`` times the largest is reported as degenerate, and every eigenvalue is floored
at ``floor_rtol`` times the largest (and at an absolute ``floor_abs``) before inversion, so an
unconstrained direction shows as a very large but finite variance, never NaN.

The calibrated covariance adds ``covariance_floor``: the error the Hessian cannot see.
"""

import numpy as np

__all__ = ["covariance_from_hessian", "covariance_floor", "centroid_metric", "FLOOR_CELLS"]

# The standard deviation, in cells of A, of the error the Hessian cannot see (e is flat within a
# cell: nearest-cell lookups). Fitted with CALIBRATED_COVARIANCE_SCALE on real-map crops, whose
# truth is exact (bench/calibrate_covariance.py): 0.1 cell.
FLOOR_CELLS = 0.1


def centroid_metric(centroid, spread, theta):
    """M (3 x 3) with z = M r linear in r near ``theta``: z = (B's centroid in A, theta * spread),
    for B's known cells with centroid ``centroid`` (B's frame) and rms distance ``spread`` from it."""
    c, s = np.cos(theta), np.sin(theta)
    cx, cy = centroid
    return np.array([[1.0, 0.0, -s * cx - c * cy], [0.0, 1.0, c * cx - s * cy], [0.0, 0.0, spread]])


def covariance_from_hessian(hessian, metric, *, scale=1.0, degenerate_rtol=1e-3, floor_rtol=1e-9,
                            floor_abs=1e-12):
    """Return (covariance 3x3, degenerate directions (k, 3) as unit vectors in (x, y, theta)).

    ``metric``: M of z = M r (3 x 3), or a length L for M = diag(1, 1, L)."""
    h = np.asarray(hessian, dtype=np.float64)
    h = 0.5 * (h + h.T)
    m = np.diag([1.0, 1.0, float(metric)]) if np.ndim(metric) == 0 else np.asarray(metric, dtype=np.float64)
    m_inv = np.linalg.inv(m)
    hz = m_inv.T @ h @ m_inv
    evals, evecs = np.linalg.eigh(0.5 * (hz + hz.T))
    top = max(float(evals.max()), 0.0)
    floor = max(floor_rtol * top, floor_abs)
    cov_z = (evecs / np.maximum(evals, floor)) @ evecs.T
    cov = scale * m_inv @ cov_z @ m_inv.T
    degenerate = evals <= max(degenerate_rtol * top, floor_abs)
    dirs = (m_inv @ evecs[:, degenerate]).T                # back to (x, y, theta) units
    dirs = dirs / np.linalg.norm(dirs, axis=1, keepdims=True) if len(dirs) else np.zeros((0, 3))
    signs = np.where(dirs[np.arange(len(dirs)), np.abs(dirs).argmax(axis=1)] < 0, -1.0, 1.0)
    return 0.5 * (cov + cov.T), dirs * signs[:, None]


def covariance_floor(resolution, centroid, spread, theta, cells=None):
    """The covariance (x, y, theta) of an error of ``cells`` cells (default ``FLOOR_CELLS``) of
    size ``resolution`` at B's centroid in each direction, and of a rotation moving a typical
    cell of B (at rms distance ``spread`` from the centroid ``centroid`` in B's frame) as far."""
    sd = (FLOOR_CELLS if cells is None else cells) * resolution
    m_inv = np.linalg.inv(centroid_metric(centroid, spread, theta))
    return sd * sd * (m_inv @ m_inv.T)
