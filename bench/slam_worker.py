"""The mapping loop in a worker process (``slam_worker.SlamWorker``), fed as a 40 Hz laser would feed it.

For each log: a plain run (``Slam.run``, whose ``add_seconds`` say how long a caller of
``Slam.add`` would wait for each scan), then a ``SlamWorker`` run whose scans this thread submits
on a 25 ms schedule in real time (sleeping until each one's turn), as a driver's callback would.
Per log: how late the submits were against the schedule (the caller's thread kept its period while
the worker mapped, or not), each scan's delay from its submit to its pose, the longest backlog,
how long after the last scan's arrival the run finished (``finish``: the last closures, the audit,
the global map), and whether the poses are those of the plain run, bit for bit.

    python bench/slam_worker.py --out bench/SLAM_WORKER.md
    python bench/slam_worker.py --logs aces fhw --hz 20
"""

import argparse
import datetime
import glob
import sys
import time
from pathlib import Path

import numpy as np

from taichi_match.logs import read_carmen
from taichi_match.reproduce import git_revision
from taichi_match.simulate import simulate_log
from taichi_match.slam import Slam
from taichi_match.slam_worker import SlamWorker

sys.path.insert(0, str(Path(__file__).resolve().parent))
from slam import LOGS  # noqa: E402
from yardstick import corridor_median_ms  # noqa: E402


def fed(log, period):
    """A SlamWorker run with ``log``'s scans submitted every ``period`` seconds: (result, submit
    lateness (S,), delays (S,), longest backlog, seconds from the last arrival to the result)."""
    mapper = SlamWorker()
    assert len(mapper.poses) == 0                       # waits until its process has started
    late, backlog = [], 0
    start = time.perf_counter()
    for k, scan in enumerate(log.scans):
        due = start + k * period
        wait = due - time.perf_counter()
        if wait > 0:
            time.sleep(wait)
        late.append(time.perf_counter() - due)
        mapper.submit(scan)
        backlog = max(backlog, mapper.backlog)
    last = start + (len(log.scans) - 1) * period
    result = mapper.finish()
    return result, np.array(late), mapper.delays, backlog, time.perf_counter() - last


def main():
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--logs", nargs="*", help="shared logs (default: all)")
    parser.add_argument("--hz", type=float, default=40.0, help="the laser's rate (default 40)")
    parser.add_argument("--no-simulated", action="store_true", help="leave out the simulated run")
    parser.add_argument("--out", help="also write the table to this markdown file")
    args = parser.parse_args()
    names = args.logs if args.logs is not None else sorted(p.name for p in LOGS.iterdir() if p.is_dir())
    runs = ([] if args.no_simulated else [("simulated", simulate_log(0).log)]) + [
        (name, read_carmen(glob.glob(str(LOGS / name / f"{name}.log*"))[0])) for name in names]
    period = 1.0 / args.hz
    yard = corridor_median_ms()
    Slam().run(runs[0][1])                              # compile the kernels outside the figures
    lines = ["| log | scans | plain run: ms per scan / `add` 99 % / max ms | submits late, ms: median / max "
             "| delay to the pose, ms: median / 99 % / max | longest backlog, scans | finish after the last "
             "scan, s | poses as the plain run's |", "|---|---|---|---|---|---|---|---|"]
    for name, log in runs:
        plain = Slam().run(log)
        waits = np.asarray(plain.add_seconds)[1:]
        result, late, delays, backlog, tail = fed(log, period)
        same = bool(np.array_equal(plain.poses, result.poses))
        lines.append(f"| {name} | {len(log.scans)} | {1e3 * sum(plain.seconds.values()) / len(log.scans):.1f} / "
                     f"{1e3 * np.percentile(waits, 99):.0f} / {1e3 * waits.max():.0f} | {1e3 * np.median(late):.1f} / "
                     f"{1e3 * late.max():.1f} | {1e3 * np.median(delays):.0f} / {1e3 * np.percentile(delays, 99):.0f} "
                     f"/ {1e3 * delays.max():.0f} | {backlog} | {tail:.2f} | {'yes' if same else 'NO'} |")
        print(lines[-1], flush=True)
    header = (f"`python bench/slam_worker.py{' ' + ' '.join(sys.argv[1:]) if len(sys.argv) > 1 else ''}` at revision "
              f"{git_revision()}, {datetime.date.today()}, the scans submitted at {args.hz:g} Hz in real time; the "
              f"machine's speed (`bench/yardstick.py`) {yard:.1f} ms before, {corridor_median_ms():.1f} ms after. "
              f"Each worker's process was started (and its kernels compiled) before its first scan was due.")
    print(header)
    if args.out:
        title = "# The mapping loop in a worker process, fed at the laser's rate"
        Path(args.out).write_text(f"{title}\n\n{header}\n\n" + "\n".join(lines) + "\n")


if __name__ == "__main__":
    main()
