"""Is ``MatchResult.calibrated_covariance`` consistent on submaps built like the real ones?

A simulated robot drives through an asymmetric indoor scene of line segments (15 m x 10 m: three
rooms joined by doorways, with boxes, a pillar and a slanted cabinet). Its laser (361 beams over
180 degrees, the first at -90 degrees, 0.5 degree steps, 30 m maximum range) measures ranges by
exact ray-segment intersection, plus seeded Gaussian range noise. Submaps of 16 scans are built
by ``scans_to_grid`` from the true poses, each in the frame of its middle scan, so the truth
r_A2B is exact. B (the second half of A's stretch and the next 8 scans) is matched in A from
seeded guesses; the normalised estimation error squared NEES = e^T C^-1 e, C the calibrated
covariance, averages 3 over the results when C is consistent.
"""

import numpy as np
import pytest
from scipy import stats

import taichi_match
from taichi_match._se2 import compose, inverse, wrap_angle
from taichi_match.logs import Scan
from taichi_match.scans import scans_to_grid

# --- the scene: line segments (x0, y0, x1, y1), metres ----------------------------------------------


def _box(x0, y0, x1, y1):
    return [(x0, y0, x1, y0), (x1, y0, x1, y1), (x1, y1, x0, y1), (x0, y1, x0, y0)]


SEGMENTS = np.array([
    # the outer walls
    *_box(0.0, 0.0, 15.0, 10.0),
    # the left room (x < 6): a doorway at y 3.5..4.7 to the right part, a partition at y = 6.5
    (6.0, 0.0, 6.0, 3.5), (6.0, 4.7, 6.0, 10.0),
    (0.0, 6.5, 3.8, 6.5),
    # the right part: a wall at y = 5.5 with a doorway at x 9.5..10.8, a partition hanging from the far wall at x = 11
    (6.0, 5.5, 9.5, 5.5), (10.8, 5.5, 15.0, 5.5),
    (11.0, 10.0, 11.0, 8.4),
    # clutter
    *_box(2.6, 0.6, 3.4, 1.2),                 # a box in the left room
    *_box(4.2, 8.0, 5.0, 8.5),                 # a table behind the partition
    *_box(0.0, 4.0, 0.6, 5.0),                 # a cabinet against the left wall
    (8.0, 1.0, 9.2, 2.1),                      # a slanted cabinet in the lower right room
    *_box(12.35, 2.35, 12.65, 2.65),           # a pillar
    *_box(13.0, 7.5, 14.0, 8.2),               # a desk in the upper right room
    (7.2, 2.4, 7.2, 3.3),                      # a screen beyond the doorway
    (14.2, 0.0, 14.2, 1.3),                    # a short stub in the corner
], dtype=np.float64)

# the robot's path: a polyline through the doorways, sampled every STEP metres
WAYPOINTS = np.array([[1.5, 1.2], [4.5, 4.1], [8.5, 4.3], [10.15, 4.6], [10.15, 7.2], [13.5, 9.0]])
STEP = 0.12
BEAMS = 361
ANGLES = -np.pi / 2 + np.arange(BEAMS) * np.deg2rad(0.5)
MAX_RANGE = 30.0
RANGE_NOISE = 0.015              # metres, standard deviation
SCANS_PER_SUBMAP = 16
RESOLUTION = 0.05

PAIRS = 8                        # map pairs, each from its own stretch of the path and noise seed
GUESSES = 5                      # guesses per pair
GUESS_XY = 0.3                   # metres (within a disc)
GUESS_THETA = 0.1                # radians


def path_poses():
    """(S, 3) laser poses along WAYPOINTS: heading along the path, swaying by +-0.15 rad."""
    seg = np.diff(WAYPOINTS, axis=0)
    lengths = np.hypot(seg[:, 0], seg[:, 1])
    cum = np.concatenate([[0.0], np.cumsum(lengths)])
    s = np.arange(0.0, cum[-1], STEP)
    k = np.minimum(np.searchsorted(cum, s, side="right") - 1, len(seg) - 1)
    t = (s - cum[k]) / lengths[k]
    xy = WAYPOINTS[k] + t[:, None] * seg[k]
    heading = np.arctan2(seg[k, 1], seg[k, 0]) + 0.15 * np.sin(s / 0.7)
    return np.column_stack([xy, heading])


def exact_ranges(pose, angles=ANGLES, segments=SEGMENTS, max_range=MAX_RANGE):
    """The distance along each beam from the laser at ``pose`` to the nearest segment (ray-segment
    intersection), ``max_range`` where none is hit within it."""
    x, y, theta = pose
    d = np.column_stack([np.cos(theta + angles), np.sin(theta + angles)])[:, None, :]    # (N, 1, 2)
    p = segments[None, :, :2]
    s = segments[None, :, 2:] - segments[None, :, :2]                                    # (1, M, 2)
    w = p - np.array([x, y])
    denom = d[..., 0] * s[..., 1] - d[..., 1] * s[..., 0]
    with np.errstate(divide="ignore", invalid="ignore"):
        t = (w[..., 0] * s[..., 1] - w[..., 1] * s[..., 0]) / denom
        u = (w[..., 0] * d[..., 1] - w[..., 1] * d[..., 0]) / denom
    hit = (denom != 0.0) & (t > 0.0) & (u >= 0.0) & (u <= 1.0)
    r = np.where(hit, t, np.inf).min(axis=1)
    return np.where(r < max_range, r, max_range)


def simulated_scans(poses, rng):
    """Scans at ``poses`` with Gaussian range noise on every return."""
    scans = []
    for i, pose in enumerate(poses):
        r = exact_ranges(pose)
        ret = r < MAX_RANGE
        r = np.where(ret, r + rng.normal(0.0, RANGE_NOISE, BEAMS), MAX_RANGE)
        scans.append(Scan(float(i), r, ANGLES, np.asarray(pose, dtype=np.float64), MAX_RANGE))
    return scans


def submap(scans, poses):
    """(frame pose = the middle scan's, grid built from the true poses in that frame)."""
    middle = poses[len(poses) // 2]
    local = np.array([compose(inverse(middle), p) for p in poses])
    return middle, scans_to_grid(scans, local, resolution=RESOLUTION)


def build_pairs():
    """[(A, B, truth r_A2B, guesses)]: pair k uses its own stretch of the path and noise seed."""
    poses = path_poses()
    span = SCANS_PER_SUBMAP + SCANS_PER_SUBMAP // 2
    starts = np.linspace(0, len(poses) - span, PAIRS).round().astype(int)
    pairs = []
    for k, start in enumerate(starts):
        rng = np.random.default_rng(1000 + k)
        stretch = poses[start:start + span]
        scans = simulated_scans(stretch, rng)
        half = SCANS_PER_SUBMAP // 2
        frame_a, grid_a = submap(scans[:SCANS_PER_SUBMAP], stretch[:SCANS_PER_SUBMAP])
        frame_b, grid_b = submap(scans[half:], stretch[half:])
        truth = compose(inverse(frame_a), frame_b)
        radius = GUESS_XY * np.sqrt(rng.random(GUESSES))
        angle = rng.uniform(-np.pi, np.pi, GUESSES)
        guesses = truth + np.column_stack([radius * np.cos(angle), radius * np.sin(angle),
                                           rng.uniform(-GUESS_THETA, GUESS_THETA, GUESSES)])
        pairs.append((grid_a, grid_b, truth, guesses))
    return pairs


def pose_error(pose, truth):
    e = np.asarray(pose, dtype=np.float64) - truth
    e[2] = wrap_angle(e[2])
    return e


@pytest.fixture(scope="module", params=["nearest", "bilinear"])
def matches(request):
    """[(truth, result)] of every guess of every pair, one Matcher with the default options and the
    envelope looked up at the nearest cell (the default) or bilinearly, each with its own
    calibration (``_covariance.CALIBRATION``)."""
    matcher = taichi_match.Matcher(interpolation=request.param)
    out = []
    for grid_a, grid_b, truth, guesses in build_pairs():
        for guess in guesses:
            out.append((truth, matcher.match(grid_a, grid_b, guess)))
    return out


@pytest.fixture(scope="module")
def summary(matches):
    """The NEES and the per-axis errors over the accepted, non-degenerate results; printed."""
    used = [(truth, res) for truth, res in matches if res.accepted and len(res.degenerate) == 0]
    errors = np.array([pose_error(res.pose, truth) for truth, res in used]).reshape(-1, 3)
    covs = [res.calibrated_covariance for _, res in used]
    nees = np.array([e @ np.linalg.solve(c, e) for e, c in zip(errors, covs)])
    sds = np.array([np.sqrt(np.diag(c)) for c in covs]).reshape(-1, 3)
    n = len(used)
    out = dict(
        n=n, total=len(matches), accepted=sum(res.accepted for _, res in matches),
        mean_nees=float(nees.mean()) if n else np.nan,
        band=stats.chi2.ppf([0.025, 0.975], 3 * n) / n if n else np.array([np.nan, np.nan]),
        rms_error=np.sqrt((errors ** 2).mean(axis=0)), mean_error=errors.mean(axis=0),
        max_error=np.abs(errors).max(axis=0), mean_sd=sds.mean(axis=0))
    print(f"\n[NEES] {out['accepted']}/{out['total']} accepted, {n} accepted and non-degenerate; "
          f"mean NEES {out['mean_nees']:.3f} (n = {n}, 3 dof), chi-square 95 % band of the mean "
          f"{out['band'][0]:.3f} .. {out['band'][1]:.3f}")
    for axis, name, unit, k in ((0, "x", "mm", 1e3), (1, "y", "mm", 1e3), (2, "theta", "mrad", 1e3)):
        print(f"[NEES] {name:5s}: error rms {k * out['rms_error'][axis]:6.2f} {unit}, mean "
              f"{k * out['mean_error'][axis]:+6.2f}, max |e| {k * out['max_error'][axis]:6.2f}; "
              f"predicted sd (mean) {k * out['mean_sd'][axis]:6.2f} {unit}")
    return out


def test_nearly_all_matches_are_accepted_and_none_is_degenerate(matches, summary):
    # the scene constrains the pose fully: otherwise the NEES below would rest on few samples
    assert summary["total"] == PAIRS * GUESSES
    assert summary["n"] >= 0.9 * summary["total"]


def test_accepted_results_are_within_a_decimetre_and_a_degree(matches):
    accepted = [pose_error(res.pose, truth) for truth, res in matches if res.accepted]
    assert accepted
    for e in accepted:
        assert np.hypot(e[0], e[1]) <= 0.1 and abs(e[2]) <= np.deg2rad(1.0), e


# Measured (seeded, deterministic, 2026-12-06), each lookup with its published model (nearest: s
# 4.25, exponent 0.55; bilinear: s 3.0, exponent 0.9; both with the plateau floor): 40 of 40
# accepted either way; mean NEES 0.91 (nearest) and 1.12 (bilinear) against the band 2.289 ..
# 3.805 for n = 40: error rms 3.0 / 3.0 mm and 1.2 mrad against predicted sd 5.3 / 5.7 mm and 1.8
# mrad (nearest), 2.0 / 2.3 mm and 0.9 mrad against 3.0 / 3.2 mm and 1.0 mrad (bilinear),
# conservative by 1.6-1.8 in sd. The models are fitted on real data (the cycles of real laser
# submaps and real-map crops, bench/calibrate_covariance.py), whose errors are larger for the same
# residual: here the residual comes from range noise alone, with no pose error inside a submap and
# nobody walking by. So what holds, and is asserted: not optimistic (the mean at most the band's
# upper end, each axis's error rms at most the mean predicted sd), and not absurdly conservative
# (mean NEES at least LOWER_NEES, a factor 4 in sd).
LOWER_NEES = 0.2


def test_calibrated_covariance_is_not_optimistic_nor_absurdly_conservative(summary):
    n, mean, band = summary["n"], summary["mean_nees"], summary["band"]
    assert n >= 30
    assert mean <= band[1], f"optimistic: mean NEES {mean:.3f} above the 95 % band {band} (n = {n})"
    assert np.all(summary["rms_error"] <= summary["mean_sd"]), (summary["rms_error"], summary["mean_sd"])
    assert mean >= LOWER_NEES, f"absurdly conservative: mean NEES {mean:.3f} < {LOWER_NEES} (n = {n})"


@pytest.mark.xfail(strict=True, reason="the calibrated covariance is 1.6-1.8x conservative in sd on "
                                       "simulated submaps built from exact poses (mean NEES 0.91 nearest, "
                                       "1.12 bilinear, band 2.29-3.81): fitted on real laser submaps and "
                                       "real-map crops")
def test_mean_nees_lies_in_the_chi_square_band(summary):
    band = summary["band"]
    assert band[0] <= summary["mean_nees"] <= band[1]
