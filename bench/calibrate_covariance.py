"""Fit the covariance model published as ``taichi_match.CALIBRATED_COVARIANCE_SCALE`` and
``taichi_match._covariance.FLOOR_CELLS``: ``s H(e)^-1 + floor``, the floor being FLOOR_CELLS
cells of A at B's centroid along x and y and the rotation that moves a typical cell of B as far.

The fit uses matches whose truth is exact: the records of ``bench/real_maps.py --records``
(correct matches from good guesses, no degenerate direction), and prints the mean NEES for a
grid of (s, floor) (3 is consistent; the chi-square 95 % band of the mean is printed). Given the
records of ``bench/submaps.py --records`` too, it prints the same for the laser-built submaps,
whose truth is a SLAM reference trajectory with errors of its own.

    python bench/real_maps.py --records /tmp/crops0.jsonl
    python bench/real_maps.py --seed 1 --records /tmp/crops1.jsonl
    python bench/submaps.py --records /tmp/submaps.jsonl
    python bench/calibrate_covariance.py /tmp/crops0.jsonl /tmp/crops1.jsonl --submaps /tmp/submaps.jsonl
"""

import argparse
import json

import numpy as np
from scipy import stats

import taichi_match as tm
from taichi_match._covariance import FLOOR_CELLS

SCALES = (1.0, 1.5, 2.0, 2.5, 3.0)
FLOORS = (0.0, 0.05, 0.1, 0.2, 0.3)


def load(paths, keep):
    data = []
    for path in paths:
        for line in open(path):
            r = json.loads(line)
            if keep(r):
                # the records hold H^-1 (covariance_scale 1) and the floor of one cell
                data.append((np.array(r["error"]), np.array(r["covariance"]), np.array(r["floor"])))
    return data


def table(name, data):
    n = len(data)
    lo, hi = stats.chi2.ppf(0.025, 3 * n) / n, stats.chi2.ppf(0.975, 3 * n) / n
    print(f"{name}: {n} matches, band of the mean NEES {lo:.2f}-{hi:.2f}; rows s, columns the floor in cells")
    found = []
    for s in SCALES:
        cells = []
        for floor in FLOORS:
            nees = float(np.mean([e @ np.linalg.solve(s * c + floor**2 * f, e) for e, c, f in data]))
            cells.append(f"{floor:.2f}: {nees:6.2f}")
            if lo <= nees <= hi:
                found.append((s, floor, round(nees, 2)))
        print(f"  s = {s:.1f}   " + "   ".join(cells))
    return found


def main():
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("crops", nargs="+", help="records of bench/real_maps.py --records")
    parser.add_argument("--submaps", help="records of bench/submaps.py --records")
    args = parser.parse_args()
    crops = load(args.crops, lambda r: r["correct"] and r["degenerate"] == 0)
    found = table("real-map crops (exact truth)", crops)
    print(f"  in band: {found}")
    if args.submaps:
        table("laser-built submaps against the reference trajectories (good guesses, consecutive and loop)",
              load([args.submaps], lambda r: r["correct"] and r["guess"] == "good" and r["pair"] != "disjoint"
                   and r["degenerate"] == 0))
    print(f"published: s = {tm.CALIBRATED_COVARIANCE_SCALE}, floor = {FLOOR_CELLS} cells")


if __name__ == "__main__":
    main()
