"""Measure the paper's corridor experiments over a grid of blur width, K and L.

This is the measurement behind the defaults of ``MatchOptions`` (blur, prior_weight,
rotation_scale): for each setting it runs the paper's protocol (100 seeded initial poses per row)
for Table 1 (both rows) and Table 2 (parallel corridors), and prints the success rates in the
paper's accuracy bands, the median time per match and the mean iterations.

    python bench/tune_defaults.py                  # the full grid (several minutes)
    python bench/tune_defaults.py --trials 30 --blur 1.5 --prior-weight 100 --rotation-scale 3
"""

import argparse
import itertools
import time

import numpy as np

import taichi_match as tm
from taichi_match.scenes import corridor

# (name, initial-pose ranges (x, y, theta), centre y, accuracy bands (|dy|, |theta|))
ROWS = (
    ("T1 +-0.5", (0.5, 0.5, 0.5), 0.0, ((0.025, 0.045),)),
    ("T1 +-1.5", (1.5, 1.5, 0.38), 0.0, ((0.025, 0.045),)),
    ("T2 y~5", (1.5, 1.5, 0.38), 5.0, ((0.025, 0.045), (0.05, 0.09), (0.2, 0.16))),
)


def run_row(matcher, grid, ranges, centre_y, bands, trials, seed, wall):
    rng = np.random.default_rng(seed)
    target_y = 0.0 if centre_y == 0.0 else 6.0 + wall       # parallel corridors share a wall
    errors, seconds, iterations = [], [], []
    for _ in range(trials):
        r0 = rng.uniform(-1.0, 1.0, 3) * ranges + (0.0, centre_y, 0.0)
        res = matcher.match(grid, grid, r0)
        errors.append((abs(res.pose[1] - target_y), abs(res.pose[2])))
        seconds.append(res.seconds)
        iterations.append(res.iterations)
    errors = np.array(errors)
    rates = [100.0 * np.mean((errors[:, 0] < dy) & (errors[:, 1] < dt)) for dy, dt in bands]
    return rates, float(np.median(seconds)), float(np.mean(iterations))


def main():
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--trials", type=int, default=100)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--blur", type=float, nargs="+", default=[0.5, 1.0, 1.5, 2.0])
    parser.add_argument("--prior-weight", type=float, nargs="+", default=[10.0, 100.0, 1000.0])
    parser.add_argument("--rotation-scale", type=float, nargs="+", default=[1.0, 3.0])
    args = parser.parse_args()
    wall = 0.05
    grid = corridor(wall=wall)
    tm.Matcher().match(grid, grid, (0.0, 0.0, 0.0))             # compile outside the timings
    print(f"{args.trials} trials per row, seed {args.seed}; success % in the paper's bands")
    print("| blur m | K | L m/rad | T1 +-0.5 | T1 +-1.5 | T2 (3 bands) | median ms | mean it |")
    print("|---|---|---|---|---|---|---|---|")
    for blur, k, ell in itertools.product(args.blur, args.prior_weight, args.rotation_scale):
        matcher = tm.Matcher(blur=blur, prior_weight=k, rotation_scale=ell)
        t0 = time.perf_counter()
        cells, times, its = [], [], []
        for i, (name, ranges, cy, bands) in enumerate(ROWS):
            rates, sec, it = run_row(matcher, grid, np.array(ranges), cy, bands, args.trials, args.seed + i, wall)
            cells.append(" / ".join(f"{r:.0f}" for r in rates))
            times.append(sec)
            its.append(it)
        print(f"| {blur} | {k:g} | {ell:g} | {cells[0]} | {cells[1]} | {cells[2]} | "
              f"{1e3 * np.median(times):.1f} | {np.mean(its):.1f} |", flush=True)
        del t0


if __name__ == "__main__":
    main()
