"""Throughput (issue 14): preparing and matching laser submaps, a large map, beside the targets.

    python bench/throughput.py                              # table to stdout
    python bench/throughput.py --out bench/THROUGHPUT.md

For each log of ``../shared/logs``: submaps of 40 scans at 0.05 m cast at the reference poses,
one every 20 scans (issue 14's measure: about 1000 x 1000 cells), then

- **preparation**: a new map prepared as a match needs it (``Matcher.prepare``: its pyramid's
  levels, the verdict's wall distances, its known rows): median ms per submap;
- **prepared match**: consecutive submaps, both prepared before, matched from the reference's
  relative pose moved by (0.1 m, -0.1 m, 0.05 rad): median ms;
- **new pairs per second**: the same pairs with neither prepared (a new matcher per pair: both
  preparations and the match), over all of the log's pairs.

Then a 4000 x 4000 map (gdc_3 tiled) prepared: seconds, and the growth of the process's peak
resident memory. Each median beside its target (preparation <= 10 ms, prepared match <= 5 ms,
4000 x 4000 within 0.3 s and 0.5 GB). Not built yet, so not measured: ``match_many``, workers,
the all-pairs check of 50 submaps, memory over 10,000 matches.
"""

import argparse
import datetime
import os
import sys
import time
from pathlib import Path

import numpy as np

import taichi_match as tm
from taichi_match.logs import read_tum
from taichi_match.scenes import corridor

sys.path.insert(0, str(Path(__file__).resolve().parent))
import real_maps  # noqa: E402
import submaps  # noqa: E402

SCANS, STRIDE = 40, 20
OFFSET = np.array([0.1, -0.1, 0.05])


def prepare_fully(matcher, grid):
    """The preparation a match of ``grid`` uses (``Matcher.prepare``: every pyramid level, the
    verdict's distances, the known rows and their moments)."""
    return matcher.prepare(grid)


def peak_rss_mb():
    with open("/proc/self/status") as f:
        for line in f:
            if line.startswith("VmHWM:"):
                return int(line.split()[1]) / 1024.0
    return float("nan")


def log_figures(name):
    built = [grid for _, grid in submaps.build_submaps(name, SCANS, STRIDE)]
    _, reference = read_tum(submaps.LOGS / name / f"{name}.reference.tum")
    middles = [reference[start + SCANS // 2] for start in range(0, len(reference) - SCANS + 1, STRIDE)]
    truths = [tm.compose(tm.inverse(middles[k]), middles[k + 1]) for k in range(len(built) - 1)]
    matcher = tm.Matcher()
    prepare = []
    for grid in built:
        copy = grid.with_prob(grid.prob)                 # a map the matcher has not seen
        t0 = time.perf_counter()
        prepare_fully(matcher, copy)
        prepare.append(time.perf_counter() - t0)
    for grid in built:
        prepare_fully(matcher, grid)
    prepared = []
    for k, truth in enumerate(truths):
        t0 = time.perf_counter()
        matcher.match(built[k], built[k + 1], np.asarray(truth) + OFFSET)
        prepared.append(time.perf_counter() - t0)
    t0 = time.perf_counter()
    for k, truth in enumerate(truths):
        tm.Matcher().match(built[k].with_prob(built[k].prob), built[k + 1].with_prob(built[k + 1].prob),
                           np.asarray(truth) + OFFSET)
    rate = len(truths) / (time.perf_counter() - t0)
    shape = np.median([g.shape for g in built], axis=0).astype(int)
    known = int(np.median([np.count_nonzero(g.known) for g in built]))
    return (f"| {name} | {len(built)} | {shape[0]} x {shape[1]} | {known // 1000}k | "
            f"{1e3 * np.median(prepare):.1f} | {1e3 * np.median(prepared):.1f} | {rate:.0f} |")


def large_map_figures(side=4000):
    gdc = real_maps.load_maps()["gdc_3"]
    reps = (-(-side // gdc.shape[0]), -(-side // gdc.shape[1]))
    grid = tm.GridMap(np.tile(gdc.prob, reps)[:side, :side], gdc.resolution)
    before = peak_rss_mb()
    t0 = time.perf_counter()
    prepared = prepare_fully(tm.Matcher(), grid)
    seconds = time.perf_counter() - t0
    grown = peak_rss_mb() - before
    del prepared
    return seconds, grown


def main():
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--logs", nargs="*", help="only these logs (default: every log)")
    parser.add_argument("--out", help="also write the tables (markdown) here")
    args = parser.parse_args()
    if not submaps.LOGS.is_dir():
        raise SystemExit(f"no logs at {submaps.LOGS}: this benchmark needs ../shared/logs")
    from taichi_match.reproduce import git_revision

    started = time.perf_counter()
    tm.match(corridor(), corridor(), (0.1, 0.1, 0.01))           # compile the kernels
    names = args.logs or sorted(p.name for p in submaps.LOGS.iterdir() if p.is_dir())
    rows = []
    for name in names:
        rows.append(log_figures(name))
        print(rows[-1], flush=True)
    seconds, grown = large_map_figures() if real_maps.MAPS.is_dir() else (float("nan"), float("nan"))
    text = ["# Throughput", "",
            f"`python bench/throughput.py {' '.join(sys.argv[1:])}` at revision {git_revision()}, "
            f"{datetime.date.today()}, {os.cpu_count()}-core machine, {time.perf_counter() - started:.0f} s. "
            f"Submaps of {SCANS} scans at 0.05 m, one every {STRIDE} scans, at the reference poses; default "
            f"`MatchOptions`.", "",
            "| log | submaps | median shape | median known cells | preparation ms (target 10) | "
            "prepared match ms (target 5) | new pairs per second |",
            "|---|---|---|---|---|---|---|", *rows, "",
            f"A 4000 x 4000 map (gdc_3 tiled) prepared in {seconds:.2f} s (target 0.3), peak resident memory "
            f"{grown / 1024:.2f} GB higher (target 0.5).", "",
            "Not built yet, so not measured: `match_many` against a serial loop, 1 and 2 workers, the all-pairs "
            "check of 50 submaps, memory over 10,000 matches with maps replaced."]
    print("\n".join(text))
    if args.out:
        Path(args.out).write_text("\n".join(text) + "\n")


if __name__ == "__main__":
    main()
