"""Fit the covariance model published as ``taichi_match.CALIBRATED_COVARIANCE_SCALE`` and
``taichi_match._covariance.FLOOR_CELLS``: ``s H(e)^-1 + floor``, the floor being FLOOR_CELLS
cells of A at B's centroid along x and y and the rotation that moves a typical cell of B as far.

It reads the records ``bench/submaps.py --records FILE`` writes (laser-built submaps of every log
in shared/logs), keeps the correct matches from good guesses on consecutive and loop pairs whose
covariance flags no degenerate direction, and prints the mean NEES for a grid of (s, floor)
(3 is consistent; the chi-square 95 % band of the mean is printed too), then the pair nearest 3
with the smallest floor.

    python bench/submaps.py --records /tmp/submaps.jsonl
    python bench/calibrate_covariance.py /tmp/submaps.jsonl
"""

import argparse
import json

import numpy as np
from scipy import stats

import taichi_match as tm
from taichi_match._covariance import FLOOR_CELLS


def main():
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("records")
    args = parser.parse_args()
    rows = [json.loads(line) for line in open(args.records)]
    data = []
    for r in rows:
        if r["correct"] and r["guess"] == "good" and r["pair"] != "disjoint" and r["degenerate"] == 0:
            # the records hold H^-1 (covariance_scale 1) and the floor of one cell
            data.append((np.array(r["error"]), np.array(r["covariance"]), np.array(r["floor"])))
    n = len(data)
    lo, hi = stats.chi2.ppf(0.025, 3 * n) / n, stats.chi2.ppf(0.975, 3 * n) / n
    print(f"{n} correct matches from good guesses; band of the mean NEES {lo:.2f}-{hi:.2f}")
    best = None
    for s in (1.0, 1.5, 2.0, 3.0, 4.0):
        line = []
        for cells in (0.0, 0.1, 0.2, 0.25, 0.3, 0.35, 0.4):
            nees = np.mean([e @ np.linalg.solve(s * c + cells**2 * f, e) for e, c, f in data])
            line.append(f"{cells:.2f}: {nees:6.2f}")
            if lo <= nees <= hi and (best is None or cells < best[1]):
                best = (s, cells, nees)
        print(f"s = {s:.1f}   " + "   ".join(line))
    print(f"published: s = {tm.CALIBRATED_COVARIANCE_SCALE}, floor = {FLOOR_CELLS} cells; "
          f"in band with the smallest floor: {best}")


if __name__ == "__main__":
    main()
