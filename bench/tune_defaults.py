"""Measure the paper's corridor experiments over a grid of blur width, K and L.

This is the measurement behind the defaults of ``MatchOptions`` (blur_kind, blur, prior_weight,
rotation_scale): for each setting it runs the paper's protocol (100 seeded initial poses per row)
for Table 1 (both rows) and Table 2 (parallel corridors), plus Table 1's first row against a noisy
copy of B, and prints the success rates in the paper's accuracy bands, the median time per match
and the mean iterations.

    python bench/tune_defaults.py                  # the full grid (several minutes)
    python bench/tune_defaults.py --trials 30 --blur-kind gaussian --blur 0.5 --prior-weight 100 --rotation-scale 3
"""

import argparse
import itertools

import numpy as np

import taichi_match as tm
from taichi_match.scenes import corridor, noisy_copy, parallel_corridors_y

# (name, initial-pose ranges (x, y, theta), centre y, accuracy bands (|dy|, |theta|), noise of B)
NOISE = dict(flip=0.002, drop=0.1)
ROWS = (
    ("T1 +-0.5", (0.5, 0.5, 0.5), 0.0, ((0.025, 0.045),), None),
    ("T1 +-1.5", (1.5, 1.5, 0.38), 0.0, ((0.025, 0.045),), None),
    ("T2 y~5", (1.5, 1.5, 0.38), 5.0, ((0.025, 0.045), (0.05, 0.09), (0.2, 0.16)), None),
    ("T1 +-0.5, noisy B", (0.5, 0.5, 0.5), 0.0, ((0.025, 0.045), (0.05, 0.09)), NOISE),
)


def run_row(matcher, grid, ranges, centre_y, bands, noise, trials, seed):
    rng = np.random.default_rng(seed)
    target_y = 0.0 if centre_y == 0.0 else parallel_corridors_y()
    errors, seconds, iterations = [], [], []
    for _ in range(trials):
        r0 = rng.uniform(-1.0, 1.0, 3) * ranges + (0.0, centre_y, 0.0)
        b = grid if noise is None else noisy_copy(grid, rng=rng, **noise)
        res = matcher.match(grid, b, r0)
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
    parser.add_argument("--blur-kind", nargs="+", default=["gaussian", "ramp"])
    parser.add_argument("--blur", type=float, nargs="+", default=[0.25, 0.5, 1.0])
    parser.add_argument("--prior-weight", type=float, nargs="+", default=[30.0, 100.0, 300.0])
    parser.add_argument("--rotation-scale", type=float, nargs="+", default=[2.0, 3.0])
    args = parser.parse_args()
    grid = corridor()
    tm.Matcher().match(grid, grid, (0.0, 0.0, 0.0))             # compile outside the timings
    print(f"{args.trials} trials per row, seed {args.seed}; success % in the paper's bands; the noisy row "
          f"flips {NOISE['flip']:.1%} of B's known cells and drops {NOISE['drop']:.0%} to unknown")
    print("| blur kind | blur m | K | L m/rad | T1 +-0.5 | T1 +-1.5 | T2 (3 bands) | T1 +-0.5 noisy (2 bands) "
          "| median ms | mean it |")
    print("|---|---|---|---|---|---|---|---|---|---|")
    for kind, blur, k, ell in itertools.product(args.blur_kind, args.blur, args.prior_weight, args.rotation_scale):
        matcher = tm.Matcher(blur_kind=kind, blur=blur, prior_weight=k, rotation_scale=ell)
        cells, times, its = [], [], []
        for i, (_name, ranges, cy, bands, noise) in enumerate(ROWS):
            rates, sec, it = run_row(matcher, grid, np.array(ranges), cy, bands, noise, args.trials, args.seed + i)
            cells.append(" / ".join(f"{r:.0f}" for r in rates))
            times.append(sec)
            its.append(it)
        print(f"| {kind} | {blur} | {k:g} | {ell:g} | {' | '.join(cells)} | "
              f"{1e3 * np.median(times):.1f} | {np.mean(its):.1f} |", flush=True)


if __name__ == "__main__":
    main()
