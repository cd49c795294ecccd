"""Benchmark: the full match on the paper's corridor case, Taichi engine vs the NumPy baseline.

Both engines run the same algorithm (same blur, cost, stencils, optimiser and Hessian) from the
same seeded initial poses, interleaved in one run so that machine load hits both alike, for the
paper's algorithm (BFGS on the given maps) and for the default (trust-region Newton, coarse to
fine). Prints median times end to end (a whole match, covariance included) and kernel only (one
batched evaluation of the 13 gradient-stencil poses, and of the 25 Hessian poses), and the ratios.

    python bench/bench_match.py                  # 100 Taichi matches, 20 of them also on NumPy
    python bench/bench_match.py --trials 50 --numpy-trials 10

The speed-up is taken on the trials both engines ran (same initial poses), as the ratio of the
median times; the Taichi row also reports all its trials.
"""

import argparse
import datetime
import os
import platform
import time

import numpy as np

import taichi_match as tm
from taichi_match._cost import gradient_stencil, hessian_stencil
from taichi_match._engines import make_engine
from taichi_match.reproduce import git_revision
from taichi_match.scenes import corridor


def median_time(fn, repeats):
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return float(np.median(times))


def main():
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--trials", type=int, default=100, help="Taichi matches (default 100)")
    parser.add_argument("--numpy-trials", type=int, default=20, help="of those, also on NumPy (default 20)")
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()

    grid = corridor()
    rng = np.random.default_rng(args.seed)
    initial = rng.uniform(-1.0, 1.0, (args.trials, 3)) * (1.5, 1.5, 0.38)     # Table 1, second row
    prepared = tm.Matcher().prepare(grid)
    engines = {name: make_engine(name, prepared, prepared) for name in ("taichi", "numpy")}
    pose, steps = np.array([0.3, 0.2, 0.05]), np.array([grid.resolution, grid.resolution, 0.01])
    kernel = {}
    for name, engine in engines.items():
        reps = 51 if name == "taichi" else 7
        kernel[name] = (median_time(lambda: engine(gradient_stencil(pose, steps)), reps),
                        median_time(lambda: engine(hessian_stencil(pose, steps)), reps))

    def summary(res):
        sec = np.array([r.seconds for r in res])
        ok = np.mean([abs(r.pose[1]) < 0.025 and abs(r.pose[2]) < 0.045 for r in res]) * 100
        return np.median(sec), np.percentile(sec, 95), np.mean([r.iterations for r in res]), \
            np.mean([r.launches for r in res]), ok

    print("# taichi_match benchmark: corridor 480x480 @ 0.025 m, B = A, r0 in +-1.5 m, +-0.38 rad")
    print(f"date {datetime.datetime.now().isoformat(timespec='seconds')}, revision {git_revision()}, "
          f"{platform.processor() or platform.machine()}, {os.cpu_count()} cores, Python {platform.python_version()}")
    print()
    print("| algorithm | engine | matches | median ms | p95 ms | mean iterations | mean launches | success % |")
    print("|---|---|---|---|---|---|---|---|")
    ratios = []
    for label, options in (("the paper's (BFGS, levels=1)", dict(optimizer="bfgs", levels=1)),
                           ("default (Newton, levels=3)", {})):
        fast, slow = tm.Matcher(**options), tm.Matcher(engine="numpy", **options)
        fast.match(grid, grid, initial[0])
        results = {"taichi": [], "numpy": []}
        for k, r0 in enumerate(initial):
            results["taichi"].append(fast.match(grid, grid, r0))
            if k < args.numpy_trials:
                results["numpy"].append(slow.match(grid, grid, r0))
        shared = results["taichi"][:args.numpy_trials]
        for name, res in (("taichi", results["taichi"]), ("taichi, shared trials", shared),
                          ("numpy, shared trials", results["numpy"])):
            st = summary(res)
            print(f"| {label} | {name} | {len(res)} | {1e3 * st[0]:.1f} | {1e3 * st[1]:.1f} | {st[2]:.1f} | "
                  f"{st[3]:.1f} | {st[4]:.0f} |")
        same = [np.allclose(a.pose[1:], b.pose[1:], atol=0.01) for a, b in zip(shared, results["numpy"])]
        ratios.append((label, summary(results["numpy"])[0] / summary(shared)[0], sum(same), len(same)))
    print()
    print("| kernel only (one launch) | taichi ms | numpy ms | speed-up |")
    print("|---|---|---|---|")
    for i, label in enumerate(("13 poses (centre + gradient stencil)",
                               "25 poses (Hessian stencil; taichi: stencil kernel)")):
        print(f"| {label} | {1e3 * kernel['taichi'][i]:.2f} | {1e3 * kernel['numpy'][i]:.2f} "
              f"| {kernel['numpy'][i] / kernel['taichi'][i]:.1f}x |")
    print()
    for label, ratio, same, n in ratios:
        print(f"{label}: full match speed-up over NumPy on the {n} shared trials (ratio of medians) {ratio:.1f}x; "
              f"same answer (|dy|, |dtheta| <= 0.01) on {same}/{n}")


if __name__ == "__main__":
    main()
