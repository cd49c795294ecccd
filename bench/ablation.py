"""What each speed-up of the real-time issue buys, measured one at a time (an ablation).

Each configuration runs the paper's corridor rows of bench/tune_defaults.py (Table 1 both rows,
Table 2, Table 1 against a noisy B; 100 seeded trials each) and the real-map pairs of
bench/realtime.py, and reports success, the median time per match on Table 1's wide row, kernel
launches per match and the ratio of that median to the default's, all in one run.

    python bench/ablation.py                 # writes bench/ABLATION.md (about 10 minutes)
    python bench/ablation.py --trials 30 --out /tmp/ablation.md
"""

import argparse
import contextlib
import datetime
import os
import platform
import sys
from pathlib import Path

import numpy as np

import taichi_match as tm
from taichi_match import _launch
from taichi_match.reproduce import git_revision
from taichi_match.scenes import corridor, noisy_copy, parallel_corridors_y

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))
import realtime  # noqa: E402
from tune_defaults import ROWS  # noqa: E402


@contextlib.contextmanager
def switched(direct_launch=True):
    """The direct launch path (``_launch``) on or off, through its own switch."""
    _launch.use_direct_launch(direct_launch)
    try:
        yield
    finally:
        _launch.use_direct_launch(True)


CONFIGS = (
    # (the gradient fallback, the trust region entering the given maps and the stencil kernel were
    # ablated at 295b64a, bench/ABLATION.md; the stencil kernel measured 1.00x and was removed)
    ("default: Newton, 3 levels, direct launch", {}, {}),
    ("- direct launch (Taichi's own call)", {}, dict(direct_launch=False)),
    ("xtol 0.5 steps (default 0.25)", dict(xtol=0.5), {}),
    ("Newton, 1 level (no pyramid)", dict(levels=1), {}),
    ("Newton, 2 levels", dict(levels=2), {}),
    ("Newton, 4 levels", dict(levels=4), {}),
    ("BFGS + compass polish, 3 levels (previous default)", dict(optimizer="bfgs"), {}),
    ("BFGS, 1 level (the paper's algorithm)", dict(optimizer="bfgs", levels=1), {}),
    ("bilinear A, BFGS (its default; analytic gradient, 1 pose per launch)", dict(interpolation="bilinear"), {}),
    ("bilinear A, Newton (analytic gradient; Hessian from 7 poses)",
     dict(interpolation="bilinear", optimizer="newton"), {}),
)


def success_rows(matcher, grid, trials, seed):
    cells = []
    for i, (_name, ranges, centre_y, bands, noise) in enumerate(ROWS):
        rng = np.random.default_rng(seed + i)
        target_y = 0.0 if centre_y == 0.0 else parallel_corridors_y()
        errors = []
        for _ in range(trials):
            r0 = rng.uniform(-1.0, 1.0, 3) * ranges + (0.0, centre_y, 0.0)
            b = grid if noise is None else noisy_copy(grid, rng=rng, **noise)
            res = matcher.match(grid, b, r0)
            errors.append((abs(res.pose[1] - target_y), abs(res.pose[2])))
        errors = np.array(errors)
        cells.append(" / ".join(f"{100 * np.mean((errors[:, 0] < dy) & (errors[:, 1] < dt)):.0f}"
                                for dy, dt in bands))
    return cells


def interleaved_times(configs, grid, trials, seed):
    """Per configuration, the times and launches of Table 1's wide row, the configurations taking
    turns on each initial pose so that the machine's load falls on all of them alike."""
    r0s = np.random.default_rng(seed).uniform(-1.0, 1.0, (trials, 3)) * (1.5, 1.5, 0.38)
    matchers = []
    for _, options, switches in configs:
        with switched(**switches):
            matchers.append(tm.Matcher(**options))
            matchers[-1].match(grid, grid, (0.1, 0.1, 0.0))          # compile outside the timings
    times = [[] for _ in configs]
    launches = [[] for _ in configs]
    for r0 in r0s:
        for k, (_, _, switches) in enumerate(configs):
            with switched(**switches):
                res = matchers[k].match(grid, grid, r0)
            times[k].append(res.seconds)
            launches[k].append(res.launches)
    return [(1e3 * np.median(t), 1e3 * np.percentile(t, 95), np.mean(n)) for t, n in zip(times, launches)]


def main():
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--trials", type=int, default=100)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--out", default=str(HERE / "ABLATION.md"))
    parser.add_argument("--only", nargs="+", type=int, metavar="ROW", help="run only these rows (0 = default)")
    args = parser.parse_args()
    grid = corridor()
    configs = [c for k, c in enumerate(CONFIGS) if args.only is None or k in args.only]
    lines = ["# Ablation of the real-time speed-ups", "",
             f"`python bench/ablation.py` at revision {git_revision()} on {datetime.date.today()}: "
             f"{platform.machine()}, {os.cpu_count()} cores, Python {platform.python_version()}. "
             f"{args.trials} trials per corridor row (success % in the paper's bands, as in bench/TUNING.md); "
             "real maps as in bench/realtime.py (8 pairs x 3 guesses per map). Times are per match on "
             "Table 1's wide row (x, y in +-1.5 m, theta in +-0.38 rad), all configurations taking turns "
             "on each initial pose; the last column is the ratio of medians to the first row's.", "",
             "| configuration | T1 +-0.5 | T1 +-1.5 | T2 (3 bands) | T1 +-0.5 noisy (2 bands) | real maps | "
             "median ms | p95 ms | launches | time / default |",
             "|---|---|---|---|---|---|---|---|---|---|"]
    print("\n".join(lines), flush=True)
    timing = interleaved_times(configs, grid, args.trials, args.seed + 100)
    for (label, options, switches), (median, p95, launches) in zip(configs, timing):
        with switched(**switches):
            matcher = tm.Matcher(**options)
            cells = success_rows(matcher, grid, args.trials, args.seed)
            real = realtime.real_map_figures(8, matcher=matcher)
        line = (f"| {label} | {' | '.join(cells)} | {real['success']:.1f} % | {median:.1f} | {p95:.1f} | "
                f"{launches:.1f} | {median / timing[0][0]:.2f} |")
        print(line, flush=True)
        lines.append(line)
    Path(args.out).write_text("\n".join(lines) + "\n")
    print(f"\nwrote {args.out}")


if __name__ == "__main__":
    main()
