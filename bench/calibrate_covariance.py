"""Fit the covariance model of ``MatchResult.calibrated_covariance``:

    s * max(q, RESIDUAL_MIN)**a * H(e)^-1 + plateau

q is the residual (e per wall compared at the pose found), s is published as
``taichi_match.CALIBRATED_COVARIANCE_SCALE`` and a as ``taichi_match._covariance.RESIDUAL_EXPONENT``
(the nearest cell's; each lookup's pair in ``taichi_match._covariance.CALIBRATION``);
the plateau (``_covariance.plateau_sd``) has no free parameter. It is fitted where the answer does
not depend on a reference we cannot check:

- **cycles of laser-built submaps** (from the records of ``bench/submaps.py --records``): for
  submaps i, i+1, i+2 whose three matches from good guesses are accepted and correct, the pose of
  i+2 in i by way of i+1 against the direct match (``submaps.cycle_nees``). No reference pose
  enters the difference; the three covariances are propagated as independent.
- **real-map crops** (``bench/real_maps.py --records``): B resampled from A's own map, exact truth.
- **self-matches**: each real-map crop A of ``bench/real_maps.py`` matched against itself from
  starts up to 0.15 m and 0.03 rad off (exact truth; the error is the plateau of e).

For a grid of (a, s) it prints the mean NEES of each (3 is consistent; the chi-square 95 % band
of the mean is printed) and, for reference, of the submaps against the reference trajectories
(SLAM results with errors of their own).

    python bench/submaps.py --records /tmp/submaps.jsonl
    python bench/real_maps.py --records /tmp/crops0.jsonl
    python bench/real_maps.py --seed 1 --records /tmp/crops1.jsonl
    python bench/calibrate_covariance.py --submaps /tmp/submaps.jsonl --crops /tmp/crops0.jsonl /tmp/crops1.jsonl
"""

import argparse
import json
import sys
from pathlib import Path

import numpy as np
from scipy import stats

import taichi_match as tm
from taichi_match._covariance import CALIBRATION, RESIDUAL_MIN, centroid_metric

sys.path.insert(0, str(Path(__file__).resolve().parent))
import real_maps  # noqa: E402
import submaps  # noqa: E402

EXPONENTS = (0.0, 0.5, 0.55, 0.6, 0.65, 0.75, 0.9, 1.0)
SCALES = (2.0, 3.0, 4.0, 4.25, 4.5, 4.75, 5.0, 5.5, 6.0, 8.0, 11.0, 16.0)


def self_matches(seed=3, crops_per_map=4, starts=3, interpolation="nearest"):
    """[(error, H^-1, plateau covariance, residual)] of each crop of the real maps matched against
    itself (correct ones without a degenerate direction: within 0.1 m at the crop's centroid and
    1 degree)."""
    matcher = tm.Matcher(interpolation=interpolation)
    out = []
    for grid in real_maps.load_maps().values():
        rng = np.random.default_rng(seed)
        for a, _, _ in real_maps.make_pairs(grid, crops_per_map, rng):
            prepared = matcher.prepare(a)
            for _ in range(starts):
                r0 = np.concatenate([rng.uniform(-0.15, 0.15, 2), rng.uniform(-0.03, 0.03, 1)])
                res = matcher.match(a, a, r0)
                z = centroid_metric(prepared.centroid, prepared.spread, 0.0) @ res.pose
                if np.hypot(z[0], z[1]) < 0.1 and abs(res.pose[2]) < np.radians(1.0) and not len(res.degenerate):
                    out.append((res.pose.copy(), res.covariance, res.covariance_floor, res.residual))
    return out


def model(cov, floor, residual, s, a):
    return s * max(residual, RESIDUAL_MIN) ** a * np.asarray(cov) + np.asarray(floor)


def mean_nees(data, s, a):
    return float(np.mean([e @ np.linalg.solve(model(c, f, q, s, a), e) for e, c, f, q in data]))


def band(n):
    return stats.chi2.ppf(0.025, 3 * n) / n, stats.chi2.ppf(0.975, 3 * n) / n


def as_data(records):
    return [(np.array(r["error"]), r["covariance"], r["floor"], r["residual"]) for r in records]


def main():
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--submaps", required=True, help="records of bench/submaps.py --records")
    parser.add_argument("--crops", nargs="+", required=True, help="records of bench/real_maps.py --records")
    parser.add_argument("--interpolation", choices=("nearest", "bilinear"), default="nearest",
                        help="the lookup of the self-matches: the one the records were made with (bilinear: "
                             "submaps.py and real_maps.py with --option interpolation=bilinear)")
    args = parser.parse_args()
    records = [json.loads(line) for line in open(args.submaps)]
    reference = as_data([r for r in records if r["correct"] and r["guess"] == "good" and r["pair"] != "disjoint"
                         and not r["degenerate"]])
    crops = as_data([r for path in args.crops for line in open(path) for r in [json.loads(line)]
                     if r["correct"] and not r["degenerate"]])
    selves = self_matches(interpolation=args.interpolation)
    n_cycles = submaps.cycle_nees(records)[1]
    columns = [("cycles", n_cycles), ("crops", len(crops)), ("self", len(selves)), ("reference", len(reference))]
    print("mean NEES; bands: " + ", ".join(f"{k} {band(n)[0]:.2f}-{band(n)[1]:.2f} (n {n})" for k, n in columns))
    print("     a      s | cycles  crops   self  reference")
    fits = []
    for a in EXPONENTS:
        for s in SCALES:
            cyc = submaps.cycle_nees([dict(r, calibrated=model(r["covariance"], r["floor"], r["residual"], s, a))
                                      for r in records])[0]
            values = [cyc, mean_nees(crops, s, a), mean_nees(selves, s, a)]
            ok = all(band(n)[0] <= v <= band(n)[1] for v, (_, n) in zip(values, columns))
            fits += [(a, s)] if ok else []
            print(f"  {a:4.2f} {s:6.1f} | " + " ".join(f"{v:6.2f}" for v in values)
                  + f" {mean_nees(reference, s, a):10.2f}{'   all three in band' if ok else ''}")
    published = ", ".join(f"{lookup}: a = {a}, s = {s}" for lookup, (s, a) in CALIBRATION.items())
    print(f"published ({published}); all three in band: {fits}")


if __name__ == "__main__":
    main()
