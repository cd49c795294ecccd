"""Long run: many matches in one process, resident memory sampled along the way.

    python bench/long_run.py                 # 10,000 matches, mixed pairs
    python bench/long_run.py --matches 2000

Matches cycle through 20 different pairs (noisy copies of a corridor, so prepared-map caches fill
and empty as maps come and go) from seeded initial poses; it prints the resident set size (VmRSS)
at 10 % steps and its growth from the 10 % mark to the end (the target: within 5 %).
"""

import argparse
import gc
import time

import numpy as np

import taichi_match as tm
from taichi_match.scenes import corridor, noisy_copy


def rss_mb():
    with open("/proc/self/status") as f:
        return next(int(line.split()[1]) for line in f if line.startswith("VmRSS:")) / 1024.0


def main():
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--matches", type=int, default=10_000)
    args = parser.parse_args()
    grid = corridor(size=6.0, resolution=0.05, width=3.0)
    rng = np.random.default_rng(0)
    matcher = tm.Matcher()
    samples = []
    start = time.perf_counter()
    pairs = None
    for k in range(args.matches):
        if k % 500 == 0:                          # new maps: the old ones leave the weak cache
            pairs = [noisy_copy(grid, flip=0.001, drop=0.05, rng=rng) for _ in range(20)]
            gc.collect()
        matcher.match(grid, pairs[k % 20], rng.uniform(-1, 1, 3) * (0.3, 0.3, 0.1))
        if (k + 1) % max(args.matches // 10, 1) == 0:
            samples.append((k + 1, rss_mb()))
            print(f"{k + 1:>7} matches  {samples[-1][1]:8.1f} MB  {time.perf_counter() - start:7.1f} s", flush=True)
    growth = 100.0 * (samples[-1][1] / samples[0][1] - 1.0)
    print(f"resident memory from {samples[0][0]} to {samples[-1][0]} matches: {samples[0][1]:.1f} -> "
          f"{samples[-1][1]:.1f} MB ({growth:+.1f} %)")


if __name__ == "__main__":
    main()
