"""Eq. (11): the covariance of the pose from the numeric Hessian of the discrepancy.

``cov(r*) ~ H(e)^-1``. In a corridor, at a kink or with little overlap, H is singular or
indefinite. We compare its eigenvalues in metric coordinates z = M r, every axis in metres (the
matcher's M: the position of B's centroid in A, and theta times B's rms radius about its
centroid; a scalar L means M = diag(1, 1, L)): a direction whose curvature is below
``degenerate_rtol`` times the largest is reported as degenerate, and every eigenvalue is floored
at ``floor_rtol`` times the largest (and at an absolute ``floor_abs``) before inversion, so an
unconstrained direction shows as a very large but finite variance, never NaN.

Before that, each cross term is clipped to the bound a positive semi-definite matrix obeys,
|H_ij| <= sqrt(H_ii H_jj) (negative curvatures taken as 0). The stencil's cross terms are
differences of four evaluations and carry noise the diagonal does not show: on the paper's
corridor H_xx is 0 (x is free) while H_x,theta came out +-1461, about 1e-3 of H_theta,theta. That
tilts the free direction off x by 6e-4 rad per metre, and the floored eigenvalue's huge variance
leaked through the tilt into theta: a standard deviation of 0.03-0.05 rad where theta's own
curvature gives 7e-4 (and the matches' theta errors are 1e-4). Clipped, the free direction is x
and theta keeps its own.

The calibrated covariance (``MatchResult.calibrated_covariance``) scales H^-1 with the residual
and adds the covariance of the plateau of e, an error the Hessian cannot see (``plateau_sd``,
``covariance_floor``).
"""

import numpy as np

__all__ = ["covariance_from_hessian", "covariance_floor", "plateau_sd", "centroid_metric", "calibrate",
           "CALIBRATED_COVARIANCE_SCALE", "CALIBRATION", "RESIDUAL_EXPONENT", "RESIDUAL_MIN"]

# s of the calibrated covariance, s * max(q, RESIDUAL_MIN)**RESIDUAL_EXPONENT * H(e)^-1 + plateau
# (``calibrate``; q the residual, e per wall compared). Fitted with the exponent where no
# reference has to be trusted (bench/calibrate_covariance.py, bench/TUNING.md): laser submaps i,
# i+1, i+2, the pose of i+2 in i by way of i+1 against the direct match, and real-map crops
# (exact truth): bench/SUBMAPS.md's cycles 2.83 (band 2.76-3.25, 397 triplets), crops 2.98 /
# 3.32 / 3.16 on seeds 0, 1, 2 (2.66-3.36), a map against itself 1.95 (2.52-3.52: the plateau,
# conservative); crop seed 3, held out: 2.52, conservative (bench/REAL_MAPS_seed3.md).
# Refitted when walls on unknown cells next to the other map's walls started paying their
# distance (``_envelope``): matches became more accurate and their Hessians smoother, and the
# previous model (11, 0.65) was 1.7x conservative in variance; and again after the coarse
# levels' envelope became the maximum over walls (4.75 -> 4.25). Valid for the default options
# (the envelope looked up at the nearest cell).
CALIBRATED_COVARIANCE_SCALE = 4.25
RESIDUAL_EXPONENT = 0.55
# (s, exponent) per lookup of the envelope (``MatchOptions.interpolation``). Looked up bilinearly
# the envelope is smooth, its Hessian larger, and the nearest cell's model 4x conservative in
# variance (real-map crops: mean NEES 0.78; cycles 1.96); fitted the same way (2026-12-06, 392
# cycles, 384 crops of seeds 0 and 1): cycles 3.01, crops 2.93, a map against itself 1.97
# (conservative, as with the nearest cell), crop seed 3 held out 2.53 (docs/slam.md, 2026-12-06).
CALIBRATION = {"nearest": (CALIBRATED_COVARIANCE_SCALE, RESIDUAL_EXPONENT), "bilinear": (3.0, 0.9)}
# q is taken as at least this: maps that agree exactly (a map against itself) keep a share of H^-1,
# and with it the huge variance along a degenerate direction.
RESIDUAL_MIN = 0.01


def calibrate(inverse_hessian, residual, floor, interpolation: str = "nearest"):
    """The calibrated covariance ``s * max(residual, RESIDUAL_MIN)**a * inverse_hessian + floor``
    ((s, a) ``CALIBRATION[interpolation]``; ``floor`` from ``covariance_floor`` of ``plateau_sd``)."""
    scale, exponent = CALIBRATION[interpolation]
    return scale * max(residual, RESIDUAL_MIN) ** exponent * inverse_hessian + floor


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
    hz = 0.5 * (hz + hz.T)
    root = np.sqrt(np.maximum(np.diag(hz), 0.0))
    bound = np.outer(root, root)
    hz = np.where(np.eye(3, dtype=bool), hz, np.clip(hz, -bound, bound))
    evals, evecs = np.linalg.eigh(hz)
    top = max(float(evals.max()), 0.0)
    floor = max(floor_rtol * top, floor_abs)
    cov_z = (evecs / np.maximum(evals, floor)) @ evecs.T
    cov = scale * m_inv @ cov_z @ m_inv.T
    degenerate = evals <= max(degenerate_rtol * top, floor_abs)
    dirs = (m_inv @ evecs[:, degenerate]).T                # back to (x, y, theta) units
    dirs = dirs / np.linalg.norm(dirs, axis=1, keepdims=True) if len(dirs) else np.zeros((0, 3))
    signs = np.where(dirs[np.arange(len(dirs)), np.abs(dirs).argmax(axis=1)] < 0, -1.0, 1.0)
    return 0.5 * (cov + cov.T), dirs * signs[:, None]


def covariance_floor(sd, centroid, spread, theta):
    """The covariance (x, y, theta) of an error of standard deviation ``sd`` metres at B's centroid
    in each direction, and of a rotation moving a typical cell of B (at rms distance ``spread``
    from the centroid ``centroid`` in B's frame) as far."""
    m_inv = np.linalg.inv(centroid_metric(centroid, spread, theta))
    return sd * sd * (m_inv @ m_inv.T)


def plateau_sd(rows, cols):
    """The standard deviation, in cells, of a pose error spread evenly over the plateau of e that
    points (the other map's walls placed in a grid, as continuous (row, col) coordinates of
    ``GridMap.grid_coordinates``) leave.

    With nearest-cell lookups e does not change while no point crosses a cell boundary. Along
    each grid axis the points' fractional coordinates cut the cell into gaps; the widest is the
    longest shift that moves no point into another cell. A map against itself puts every point
    at the same fraction (a whole cell: sd 1/sqrt(12) = 0.29 cell); maps turned against each
    other spread them (a plateau of a small fraction of a cell). The larger axis is returned."""
    if len(rows) < 2:
        return 1.0 / np.sqrt(12.0)
    widest = 0.0
    for x in (rows, cols):
        f = np.sort(x - np.floor(x))         # = np.mod(x, 1.0), bit for bit, in a fifth of the time
        widest = max(widest, float(np.max(np.diff(f))), 1.0 - float(f[-1] - f[0]))
    return widest / np.sqrt(12.0)
