"""The paper's experiments (sec. 5) as plain computations, and a covariance check beyond it.

Nothing here draws or writes files: ``taichi_match.plots`` draws, ``taichi_match.reproduce``
writes the report, the command line calls both.

- ``TABLES``: the rows of Tables 1 and 2 with the paper's protocol and numbers.
- ``run_row``: 100 seeded trials of one row: success rates in the paper's bands, iterations, time.
- ``surface``: e or h over a grid of (x, y) at fixed theta, one kernel launch per row of poses.
- ``covariance_check``: matches against noisy copies of B; the scatter of the estimates against
  the predicted covariance, a scale factor calibrated on one half and NEES tested on the other.
"""

from dataclasses import dataclass, field

import numpy as np

from ._cost import prior_values
from ._engines import make_engine
from ._prepared import PreparedMap
from .scenes import noisy_copy, parallel_corridors_y

__all__ = ["TableRow", "TABLES", "RowResult", "run_row", "surface", "covariance_check", "CovarianceCheck"]


@dataclass(frozen=True)
class TableRow:
    """One row of the paper's Tables 1-2: initial poses r0 = centre + U(-1, 1) * ranges."""

    table: str
    label: str
    ranges: tuple            # half-widths of the uniform initial-pose noise (x, y, theta)
    centre: tuple            # centre of the initial poses
    target_y: float          # the y of the answer counted as right (theta = 0 is the other target)
    bands: tuple             # ((|y - target|, |theta|), ...) as in the paper, tightest first
    paper: tuple             # the paper's success percentages per band
    paper_iterations: float
    paper_seconds: float
    cumulative: bool = True  # False: the paper's second band counts only trials outside the first


TABLES = (
    TableRow("Table 1", "x, y, theta in +-0.5", (0.5, 0.5, 0.5), (0.0, 0.0, 0.0), 0.0,
             ((0.025, 0.045), (0.05, 0.09)), (99, 1), 35, 6.0, cumulative=False),
    TableRow("Table 1", "x, y in +-1.5, theta in +-0.38", (1.5, 1.5, 0.38), (0.0, 0.0, 0.0), 0.0,
             ((0.025, 0.045), (0.05, 0.09)), (98, 0), 35, 6.0, cumulative=False),
    TableRow("Table 2", "x in +-1.5, y in 5 +-1.5, theta in +-0.38", (1.5, 1.5, 0.38), (0.0, 5.0, 0.0),
             parallel_corridors_y(), ((0.025, 0.045), (0.05, 0.09), (0.2, 0.16)), (62, 73, 93), 23, 3.6),
)


@dataclass
class RowResult:
    row: TableRow
    rates: list              # our success percentages per band, counted as the paper counts them
    mean_iterations: float
    mean_seconds: float
    median_seconds: float
    initial: np.ndarray = field(repr=False)
    final: np.ndarray = field(repr=False)
    results: list = field(repr=False, default_factory=list)


def run_row(matcher, grid, row: TableRow, *, trials=100, seed=0, progress=None):
    """Match ``grid`` against itself from ``trials`` seeded initial poses of ``row``."""
    rng = np.random.default_rng(seed)
    initial = rng.uniform(-1.0, 1.0, (trials, 3)) * row.ranges + row.centre
    results = []
    for r0 in initial:
        results.append(matcher.match(grid, grid, r0))
        if progress is not None:
            progress(1)
    final = np.array([r.pose for r in results])
    dy = np.abs(final[:, 1] - row.target_y)
    dt = np.abs(final[:, 2])
    inside = [(dy < by) & (dt < bt) for by, bt in row.bands]
    if not row.cumulative:                      # the paper's Table 1: trials between the bands
        inside = [inside[0]] + [now & ~before for before, now in zip(inside, inside[1:])]
    seconds = np.array([r.seconds for r in results])
    return RowResult(row, [100.0 * np.mean(m) for m in inside], float(np.mean([r.iterations for r in results])),
                     float(seconds.mean()), float(np.median(seconds)), initial, final, results)


def surface(a: PreparedMap, b: PreparedMap, xs, ys, *, theta=0.0, prior=None, engine="taichi", unknown_cost=0.0):
    """e(A, B, (x, y, theta)) over the grid ys x xs (rows follow y), one launch per row of poses.

    ``a`` and ``b`` are prepared maps (blurred or not); with ``prior = (r0, K, L)`` the surface is
    h = e + K ||r - r0|| (eq. 8). ``unknown_cost`` applies to the envelope discrepancy.
    """
    evaluate = make_engine(engine, a, b, unknown_cost)
    xs = np.asarray(xs, dtype=np.float64)
    out = np.empty((len(ys), len(xs)))
    for i, y in enumerate(ys):
        poses = np.column_stack([xs, np.full_like(xs, y), np.full_like(xs, theta)])
        out[i] = evaluate(poses, "none")[0]
        if prior is not None:
            out[i] += prior_values(poses, *prior)
    return out


@dataclass
class CovarianceCheck:
    """Estimates against predictions on the corridor's informative axes (y, theta)."""

    noise: dict
    trials: int
    scale: float                 # calibrated factor: covariance = scale * H(e)^-1
    nees_mean: float             # on the test half, with the calibrated scale
    nees_band: tuple             # chi-square 95 % band of the mean NEES
    scatter: np.ndarray          # sample covariance of the test half's (y, theta) errors
    predicted: np.ndarray        # calibrated prediction, test half: s * (mean information on y, theta)^-1
    mean_error: np.ndarray
    errors: np.ndarray = field(repr=False)
    covariances: np.ndarray = field(repr=False)

    @property
    def consistent(self):
        return self.nees_band[0] <= self.nees_mean <= self.nees_band[1]


def covariance_check(matcher, grid, *, flip=0.002, drop=0.1, trials=200, seed=0, ranges=(0.5, 0.5, 0.5),
                     scale=None, progress=None):
    """Match ``grid`` against noisy copies of itself (truth: y = theta = 0) from seeded initial poses.

    The first half of the trials calibrates the scale of the covariance (mean NEES = 2 on y and
    theta), unless ``scale`` is given; the second half tests it: the mean NEES should fall in the
    chi-square 95 % band. x runs along the corridor and carries no information, so it is left out.
    """
    rng = np.random.default_rng(seed)
    errors, covs = [], []
    for _ in range(trials):
        b = noisy_copy(grid, flip=flip, drop=drop, rng=rng)
        r0 = rng.uniform(-1.0, 1.0, 3) * ranges
        res = matcher.match(grid, b, r0)
        errors.append(res.pose[1:])
        covs.append(res.covariance[1:, 1:] / res.options.covariance_scale)     # H(e)^-1 block
        if progress is not None:
            progress(1)
    errors, covs = np.array(errors), np.array(covs)
    half = trials // 2 if scale is None else 0
    raw = np.array([e @ np.linalg.solve(c, e) for e, c in zip(errors, covs)])
    if scale is None:
        scale = float(np.mean(raw[:half]) / 2.0)
    test = slice(half, trials)
    n = trials - half
    nees = raw[test] / scale
    from scipy import stats

    band = (stats.chi2.ppf(0.025, 2 * n) / n, stats.chi2.ppf(0.975, 2 * n) / n)
    return CovarianceCheck(dict(flip=flip, drop=drop), trials, scale, float(nees.mean()), band,
                           np.cov(errors[test].T), scale * np.linalg.inv(np.linalg.inv(covs[test]).mean(axis=0)),
                           errors[test].mean(axis=0), errors, covs)
