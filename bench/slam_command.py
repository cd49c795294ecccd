"""The whole command, as a user runs it: `taichi-match slam LOG --out DIR` in a fresh process per log.

`bench/slam.py` times the mapping loop inside one process that has already run (its kernels loaded):
what a long-running node sees. The issue's 25 ms a scan is for the whole command, which also starts
Python, imports the package, starts Taichi, loads each kernel variant on its first use (from
Taichi's offline cache: about 0.1 s each, the Python frontend still runs), reads the log and
writes the outputs. Per log, `--rounds` times, alternating logs: the command's wall time, per
scan; the loop's own time as the command reports it ("N scans in X s"); the first match (the
command's "first match ... compiles Taichi's kernels" figure); and the rest (start-up, reading,
writing). Medians over the rounds.

With `--baseline REVISION` each command runs also with the package at REVISION (`git archive`),
the two sides alternating (which goes first alternates too), and the table gives both sides'
ms per scan and the median of the paired ratios (this tree / REVISION): the machine's speed moves
by a quarter from hour to hour, the ratio of commands run side by side far less.

    python bench/slam_command.py --out bench/SLAM_COMMAND.md
    python bench/slam_command.py --logs orebro fhw --rounds 1
    python bench/slam_command.py --baseline bff2d1d --out bench/SLAM_COMMAND.md
"""

import argparse
import datetime
import glob
import os
import re
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from taichi_match.reproduce import git_revision

sys.path.insert(0, str(Path(__file__).resolve().parent))
from ab_front_end import extract_package  # noqa: E402
from slam import LOGS  # noqa: E402
from yardstick import corridor_median_ms  # noqa: E402


def command(log, out, tree=None):
    """(wall seconds, scans, the loop's seconds, the first match's seconds) of one command, with the
    package in folder ``tree`` (None: the installed one, this tree's), run from a scratch folder."""
    env = None if tree is None else dict(os.environ, PYTHONPATH=str(tree))
    start = time.perf_counter()
    done = subprocess.run([sys.executable, "-m", "taichi_match.cli", "slam", log, "--out", out, "--force"],
                          capture_output=True, text=True, env=env, cwd=tempfile.gettempdir())
    wall = time.perf_counter() - start
    if done.returncode != 0:
        raise RuntimeError(f"{log}: exit {done.returncode}: {done.stderr[-500:]}")
    loop = re.search(r"(\d+) scans in ([\d.]+) s", done.stdout)
    first = re.search(r"compiles Taichi's kernels in a new process: (\d+) ms", done.stdout)
    return wall, int(loop.group(1)), float(loop.group(2)), (int(first.group(1)) / 1e3 if first else float("nan"))


def main():
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--logs", nargs="*", help="shared logs (default: all)")
    parser.add_argument("--rounds", type=int, default=2)
    parser.add_argument("--baseline", metavar="REVISION", help="also run the package at this git revision, alternating")
    parser.add_argument("--out", help="also write the table to this markdown file")
    args = parser.parse_args()
    names = args.logs if args.logs is not None else sorted(p.name for p in LOGS.iterdir() if p.is_dir())
    yard = corridor_median_ms()
    runs = {name: [] for name in names}
    base = {name: [] for name in names}
    with tempfile.TemporaryDirectory() as scratch:
        if args.baseline:
            extract_package(args.baseline, scratch)
        for round_ in range(args.rounds):
            for number, name in enumerate(names):
                log = glob.glob(str(LOGS / name / f"{name}.log*"))[0]
                sides = [(runs, None)] + ([(base, scratch)] if args.baseline else [])
                for table, tree in sides if (round_ + number) % 2 == 0 else sides[::-1]:
                    table[name].append(command(log, str(Path(scratch) / "out" / name), tree))
    lines = ["| log | scans | the command, s | ms per scan, the command | ms per scan, the loop as the command "
             "reports it | of the loop, the first match (kernels loaded), s | outside the loop, s |"
             + (f" ms per scan, the command at {args.baseline} | this tree / {args.baseline}, median of the pairs |"
                if args.baseline else ""),
             "|---|---|---|---|---|---|---|" + ("---|---|" if args.baseline else "")]
    for name, rows in runs.items():
        wall, scans, loop, first = (statistics.median(r[i] for r in rows) for i in range(4))
        line = (f"| {name} | {scans:.0f} | {wall:.2f} | {1e3 * wall / scans:.1f} | {1e3 * loop / scans:.1f} | "
                f"{first:.2f} | {wall - loop:.2f} |")
        if args.baseline:
            before = statistics.median(r[0] for r in base[name])
            ratio = statistics.median(r[0] / b[0] for r, b in zip(rows, base[name]))
            line += f" {1e3 * before / scans:.1f} | {ratio:.3f} |"
        lines.append(line)
        print(lines[-1], flush=True)
    header = (f"`python bench/slam_command.py{' ' + ' '.join(sys.argv[1:]) if len(sys.argv) > 1 else ''}` at revision "
              f"{git_revision()}, {datetime.date.today()}: `taichi-match slam LOG --out DIR` in a fresh process, "
              f"{args.rounds} rounds over the logs in turn, medians; Taichi's offline cache warm; the machine's "
              f"speed (`bench/yardstick.py`) {yard:.1f} ms before, {corridor_median_ms():.1f} ms after.")
    print(header)
    if args.out:
        title = "# The whole command, a fresh process per log"
        Path(args.out).write_text(f"{title}\n\n{header}\n\n" + "\n".join(lines) + "\n")


if __name__ == "__main__":
    main()
