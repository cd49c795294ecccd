"""Throughput (issue 14): preparing and matching laser submaps, a large map, beside the targets.

    python bench/throughput.py                              # table to stdout
    python bench/throughput.py --out bench/THROUGHPUT.md

For each log of ``../shared/logs``: submaps of 40 scans at 0.05 m cast at the reference poses,
one every 20 scans (issue 14's measure: about 1000 x 1000 cells), then

- **preparation**: a new map prepared as a match needs it (``Matcher.prepare``: its pyramid's
  levels, the verdict's wall distances, its known rows): median ms per submap over ``REPEATS``
  passes;
- **prepared match**: consecutive submaps, both prepared before, matched from the reference's
  relative pose moved by (0.1 m, -0.1 m, 0.05 rad): median ms;
- **new pairs per second**: the same pairs with neither prepared (a new matcher per pair: both
  preparations and the match), over all of the log's pairs.

Then, every figure beside its target:

- a 4000 x 4000 map (gdc_3 tiled) prepared, in a spawned process of its own: seconds (the median
  of nine new maps, and the first), and how much the peak resident memory grew for the first;
- ``match_many`` against a serial loop of ``Matcher.match`` on the same tasks in the same run
  (every log's consecutive pairs, new maps: preparation included), in this process and on 1 and
  2 spawned worker processes (a pool started and warmed first, as a fleet keeps it; its start
  reported apart), and on a Dask ``LocalCluster`` of 2 spawned worker processes (with the optional
  ``distributed``), the poses compared; each way in a block of its own, ``REPEATS`` runs of it and of
  the serial loop in turn, its median against the block's serial median;
- an all-pairs candidate check: 50 submaps of one log (fhw, one every 9 scans), all 1,225 pairs
  from the reference's relative poses moved by the offset above, serially and on 2 workers: the
  time (medians of ``REPEATS`` runs each way in turn), the pairs accepted and how many of those are
  right (within 0.1 m and 1 degree);
- resident memory over 10,000 matches with the maps replaced every 10 matches;
- the paper's corridor: median full match (target 5 ms).
"""

import argparse
import datetime
import importlib.util
import multiprocessing
import os
import sys
import time
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

import numpy as np

import taichi_match as tm
from taichi_match.logs import read_tum
from taichi_match.scenes import corridor

sys.path.insert(0, str(Path(__file__).resolve().parent))
import real_maps  # noqa: E402
import submaps  # noqa: E402
from yardstick import corridor_median_ms  # noqa: E402

SCANS, STRIDE = 40, 20
REPEATS = 5                     # runs of each way in turn, for the medians of match_many's figures
OFFSET = np.array([0.1, -0.1, 0.05])


def prepare_fully(matcher, grid):
    """The preparation a match of ``grid`` uses (``Matcher.prepare``: every pyramid level, the
    verdict's distances, the known rows and their moments)."""
    return matcher.prepare(grid)


def status_mb(field):
    """A memory field of /proc/self/status (VmHWM: peak resident, VmRSS: resident), MB."""
    with open("/proc/self/status") as f:
        for line in f:
            if line.startswith(field + ":"):
                return int(line.split()[1]) / 1024.0
    return float("nan")


def log_figures(name):
    built = [grid for _, grid in submaps.build_submaps(name, SCANS, STRIDE)]
    _, reference = read_tum(submaps.LOGS / name / f"{name}.reference.tum")
    middles = [reference[start + SCANS // 2] for start in range(0, len(reference) - SCANS + 1, STRIDE)]
    truths = [tm.compose(tm.inverse(middles[k]), middles[k + 1]) for k in range(len(built) - 1)]
    matcher = tm.Matcher()
    prepare = []
    for _ in range(REPEATS):
        for grid in built:
            copy = grid.with_prob(grid.prob)             # a map the matcher has not seen
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


def large_map_figures(side=4000, maps=9):
    """A ``side`` x ``side`` map (gdc_3 tiled) prepared in a spawned process of its own, so that
    its peak resident memory is the preparation's and not what this process held before: (the
    first map's seconds, the median seconds of ``maps`` new maps, the peak resident memory's
    growth over the first preparation in GB)."""
    with ProcessPoolExecutor(1, mp_context=multiprocessing.get_context("spawn")) as pool:
        return pool.submit(_large_map_figures, side, maps).result()


def _large_map_figures(side, maps):
    gdc = real_maps.load_maps()["gdc_3"]
    reps = (-(-side // gdc.shape[0]), -(-side // gdc.shape[1]))
    prob = np.tile(gdc.prob, reps)[:side, :side]
    tm.Matcher().prepare(tm.GridMap(prob[:500, :500], gdc.resolution))      # compile the kernels
    seconds = []
    for k in range(maps):
        grid = tm.GridMap(prob, gdc.resolution)                             # a map the matcher has not seen
        before = status_mb("VmHWM")
        t0 = time.perf_counter()
        prepared = prepare_fully(tm.Matcher(), grid)
        seconds.append(time.perf_counter() - t0)
        if k == 0:
            grown = (status_mb("VmHWM") - before) / 1024.0
        del prepared, grid
    return seconds[0], float(np.median(seconds)), grown


def consecutive_tasks(name):
    """The log's consecutive submap pairs, from the reference's relative pose moved by OFFSET."""
    built = submaps.build_submaps(name, SCANS, STRIDE)
    return [(a, b, np.asarray(tm.compose(tm.inverse(ma), mb)) + OFFSET) for (ma, a), (mb, b) in zip(built, built[1:])]


def fresh(tasks):
    """The tasks on copies of their maps, shared as in the originals (nothing prepared yet)."""
    copies = {}
    for a, b, _ in tasks:
        for grid in (a, b):
            copies.setdefault(id(grid), grid.with_prob(grid.prob))
    return [(copies[id(a)], copies[id(b)], guess) for a, b, guess in tasks]


def timed(run, tasks):
    """(seconds, results) of ``run`` on fresh copies of the tasks' maps (made before the clock)."""
    copies = fresh(tasks)
    t0 = time.perf_counter()
    results = run(copies)
    return time.perf_counter() - t0, results


def serial_loop(tasks):
    matcher = tm.Matcher()
    return [matcher.match(a, b, guess) for a, b, guess in tasks]


def worst_difference(results, reference):
    return max(float(np.max(np.abs(r.pose - e.pose))) for r, e in zip(results, reference))


def spawn_pool(workers, tasks):
    """A pool of spawned workers, started (the seconds it takes to start and match a corridor on
    each) and warmed on ``tasks`` once, as a fleet's pool is after its first batch."""
    t0 = time.perf_counter()
    pool = ProcessPoolExecutor(workers, mp_context=multiprocessing.get_context("spawn"))
    grid = corridor(size=4.0, resolution=0.05, width=2.0)
    tm.match_many([(grid, grid, (0.05, 0.0, 0.0))] * (4 * workers), executor=pool, chunk_size=1)
    start = time.perf_counter() - t0
    tm.match_many(fresh(tasks), executor=pool)
    return pool, start


class _DaskPool:
    """A Dask ``LocalCluster`` of 2 worker processes (spawned by their nannies, a thread each) and
    its client's executor, shut down together."""

    def __init__(self):
        import distributed

        self.cluster = distributed.LocalCluster(n_workers=2, threads_per_worker=1, processes=True,
                                                dashboard_address=None, worker_class=distributed.Nanny)
        self.client = distributed.Client(self.cluster)
        self.executor = self.client.get_executor()

    def shutdown(self):
        self.client.close()
        self.cluster.close()


def dask_pool(tasks):
    """(executor, the seconds its cluster took to start and match a corridor on each worker),
    warmed on ``tasks`` once; the executor's ``shutdown`` closes the cluster."""
    t0 = time.perf_counter()
    pool = _DaskPool()
    grid = corridor(size=4.0, resolution=0.05, width=2.0)
    tm.match_many([(grid, grid, (0.05, 0.0, 0.0))] * 8, executor=pool.executor, chunk_size=1)
    start = time.perf_counter() - t0
    tm.match_many(fresh(tasks), executor=pool.executor)
    pool.executor.shutdown = pool.shutdown
    return pool.executor, start


def many_figures(tasks, repeats=REPEATS):
    """match_many against the serial loop on ``tasks``: rows of the table (median seconds, the
    ratio to the serial loop's median in the same block), the serial loop's median over all
    blocks. Each way of running has a block of its own, ``repeats`` runs of it and of the serial
    loop in turn (the machine's speed drifts from minute to minute), its pool started for the
    block and shut down after it, so that no other pool sits beside it. A first serial run warms
    this process's memory (fresh memory's first touch is slow on some machines: the first of
    identical runs took 2x here)."""
    serial_loop(fresh(tasks))
    reference = serial_loop(fresh(tasks))
    ways = [("`match_many`, this process", None), ("`match_many`, 1 spawned worker", 1),
            ("`match_many`, 2 spawned workers", 2)]
    if importlib.util.find_spec("distributed") is not None:
        ways.append(("`match_many`, Dask `LocalCluster` of 2 spawned workers", "dask"))
    rows, serial_all = [], []
    for how, workers in ways:
        pool, start = (dask_pool(tasks) if workers == "dask" else spawn_pool(workers, tasks) if workers
                       else (None, None))
        try:
            run = (lambda t: tm.match_many(t, executor=pool)) if pool else tm.match_many
            serial, seconds, difference = [], [], 0.0
            for k in range(repeats):
                for way in (("serial", "run") if k % 2 == 0 else ("run", "serial")):
                    sec, results = timed(serial_loop if way == "serial" else run, tasks)
                    (serial if way == "serial" else seconds).append(sec)
                    difference = max(difference, worst_difference(results, reference))
        finally:
            if pool:
                pool.shutdown()
        serial_all += serial
        rows.append((how, float(np.median(seconds)), float(np.median(serial)) / float(np.median(seconds)),
                     difference, f"pool start {start:.1f} s" if pool else ""))
    serial_s = float(np.median(serial_all))
    return [("serial loop of `Matcher.match`", serial_s, 1.0, 0.0, "")] + rows, serial_s


def all_pairs_figures(name="fhw", count=50, stride=9, repeats=REPEATS):
    built = submaps.build_submaps(name, SCANS, stride)[:count]
    tasks, truths = [], []
    for i in range(len(built)):
        for j in range(i + 1, len(built)):
            truth = np.asarray(tm.compose(tm.inverse(built[i][0]), built[j][0]))
            tasks.append((built[i][1], built[j][1], truth + OFFSET))
            truths.append(truth)
    serial_loop(fresh(tasks))
    pool, _ = spawn_pool(2, tasks)
    serial, parallel = [], []
    with pool:
        for _ in range(repeats):
            serial_s, results = timed(serial_loop, tasks)
            parallel_s, in_parallel = timed(lambda t: tm.match_many(t, executor=pool), tasks)
            serial.append(serial_s)
            parallel.append(parallel_s)
    accepted = [k for k, r in enumerate(results) if r.accepted]
    right = sum(np.hypot(*(results[k].pose[:2] - truths[k][:2])) <= 0.1
                and abs(tm.wrap_angle(results[k].pose[2] - truths[k][2])) <= np.radians(1.0) for k in accepted)
    return {"submaps": len(built), "pairs": len(tasks), "serial_s": float(np.median(serial)),
            "parallel_s": float(np.median(parallel)), "accepted": len(accepted), "right": right,
            "difference": worst_difference(in_parallel, results)}


def memory_figures(tasks, matches=10_000, every=10):
    """Resident memory over ``matches`` matches of ``tasks`` in turn, their maps copied anew every
    ``every`` matches (the old copies dropped): the growth after the first tenth."""
    matcher = tm.Matcher()
    samples = []
    current = fresh(tasks)
    for k in range(matches):
        if k % every == 0:
            current = fresh(tasks)
        a, b, guess = current[k % len(current)]
        matcher.match(a, b, guess)
        if (k + 1) % (matches // 10) == 0:
            samples.append(status_mb("VmRSS"))
    return samples


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
    first_s, seconds, grown = large_map_figures() if real_maps.MAPS.is_dir() else (float("nan"),) * 3
    tasks = [task for name in names for task in consecutive_tasks(name)]
    many_rows, serial_s = many_figures(tasks)
    print("match_many done", flush=True)
    check = all_pairs_figures()
    print("all pairs done", flush=True)
    memory = memory_figures(tasks[:20])
    corridor_ms = corridor_median_ms()
    text = ["# Throughput", "",
            f"`python bench/throughput.py {' '.join(sys.argv[1:])}` at revision {git_revision()}, "
            f"{datetime.date.today()}, {os.cpu_count()}-core machine, {time.perf_counter() - started:.0f} s. "
            f"Submaps of {SCANS} scans at 0.05 m, one every {STRIDE} scans, at the reference poses; default "
            f"`MatchOptions`.", "",
            "| log | submaps | median shape | median known cells | preparation ms (target 10) | "
            "prepared match ms (target 5) | new pairs per second |",
            "|---|---|---|---|---|---|---|", *rows, "",
            f"A 4000 x 4000 map (gdc_3 tiled), in a spawned process of its own: prepared in {seconds:.2f} s "
            f"(target 0.3; median of 9 new maps, the first {first_s:.2f} s), the process's peak resident memory "
            f"{grown:.2f} GB higher for the first (target 0.5).", "",
            "## Many pairs per call", "",
            f"Every log's consecutive pairs ({len(tasks)} tasks, new maps: each prepared once however many tasks "
            f"name it), the same tasks in the same run: each way in a block of its own, {REPEATS} runs of it and of "
            f"the serial loop in turn, its median seconds and its ratio to the block's serial median. "
            f"Target: `match_many` at least 1.5x the serial loop's pairs per second, the same poses within 1e-6.",
            "",
            "| how | seconds | pairs per second | x the serial loop | largest pose difference | |",
            "|---|---|---|---|---|---|",
            *[f"| {how} | {sec:.2f} | {len(tasks) / sec:.0f} | {ratio:.2f} | {diff:.1e} | {note} |"
              for how, sec, ratio, diff, note in many_rows], "",
            f"All-pairs candidate check: {check['submaps']} submaps of fhw (one every 9 scans), all "
            f"{check['pairs']} pairs from the reference's relative poses moved by {OFFSET.tolist()}: "
            f"{check['serial_s']:.1f} s serially, {check['parallel_s']:.1f} s on 2 spawned workers (medians of "
            f"{REPEATS} runs each way in turn; {check['serial_s'] / check['parallel_s']:.2f}x; poses within "
            f"{check['difference']:.1e}); "
            f"{check['accepted']} pairs accepted, {check['right']} of them within 0.1 m and 1 degree of the "
            f"reference.", "",
            f"Resident memory over 10,000 matches, the maps replaced every 10 matches: "
            f"{' -> '.join(f'{m:.0f}' for m in memory)} MB at each tenth (growth after the first tenth "
            f"{memory[-1] - memory[0]:+.0f} MB; target: flat).", "",
            f"The paper's corridor, a full match from Table 1-like guesses: median {corridor_ms:.1f} ms (target 5)."]
    print("\n".join(text))
    if args.out:
        Path(args.out).write_text("\n".join(text) + "\n")


if __name__ == "__main__":
    main()
