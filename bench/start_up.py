"""What a process pays once for the mapping loop, this tree against an older revision, in fresh processes.

`bench/slam_command.py` times the whole command, whose run-to-run spread on this shared machine
(about a second) hides start-up changes of a few tenths. Here each round maps one log in a fresh
interpreter per side (this tree, and the package at REVISION from `git archive`; the side that goes
first alternates), timing apart: importing what the command imports (the package's CLI and
mapping loop, gtsam), starting Taichi, the first call of every kernel variant the run uses (Taichi's
Python frontend plus its load of the compiled code, from its offline cache, which the first round
warms; the first launch's own run included, a few ms), the run (the kernels' first calls within
it) and all of it (total: from the first import to the run's end, reading the log included).
Prints the medians per side, the median of the paired ratios (this tree / REVISION), and whether
both sides gave the same poses, bit for bit.

    python bench/start_up.py dbeb3df
    python bench/start_up.py dbeb3df --log csail --rounds 7 --out bench/START_UP.md
"""

import argparse
import datetime
import glob
import json
import os
import statistics
import subprocess
import sys
import tempfile
from pathlib import Path

from taichi_match.reproduce import git_revision

sys.path.insert(0, str(Path(__file__).resolve().parent))
from ab_front_end import extract_package  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
LOGS = ROOT.parent / "shared" / "logs"

# run in each fresh interpreter: the log's path is argv[1]; prints one JSON line
CHILD = r"""
import hashlib, json, sys, time
t0 = time.perf_counter()
import gtsam, taichi_match.cli, taichi_match.slam
t1 = time.perf_counter()
from taichi_match import _taichi
_taichi.taichi()
t2 = time.perf_counter()
from taichi.lang import kernel_impl
first = {"seconds": 0.0, "variants": 0}
materialize, launch_kernel, seen = kernel_impl.Kernel.materialize, kernel_impl.Kernel.launch_kernel, set()
def timed_materialize(self, *args, **kwargs):
    start = time.perf_counter()
    try:
        return materialize(self, *args, **kwargs)
    finally:
        first["seconds"] += time.perf_counter() - start
def timed_launch(self, t_kernel, *args):
    if id(t_kernel) in seen:
        return launch_kernel(self, t_kernel, *args)
    seen.add(id(t_kernel))
    first["variants"] += 1
    start = time.perf_counter()
    try:
        return launch_kernel(self, t_kernel, *args)
    finally:
        first["seconds"] += time.perf_counter() - start
kernel_impl.Kernel.materialize, kernel_impl.Kernel.launch_kernel = timed_materialize, timed_launch
from taichi_match.logs import read_carmen
log = read_carmen(sys.argv[1])
t3 = time.perf_counter()
poses = taichi_match.slam.Slam().run(log).poses
t4 = time.perf_counter()
print(json.dumps(dict(imports=t1 - t0, taichi=t2 - t1, kernels=first["seconds"], variants=first["variants"],
                      run=t4 - t3, total=t4 - t0, poses=hashlib.sha1(poses.tobytes()).hexdigest())))
"""


def one(tree, log):
    env = dict(os.environ, PYTHONPATH=str(tree))
    done = subprocess.run([sys.executable, "-c", CHILD, log], capture_output=True, text=True, env=env,
                          cwd=tempfile.gettempdir())
    if done.returncode != 0:
        raise RuntimeError(f"{tree}: exit {done.returncode}: {done.stderr[-800:]}")
    return json.loads(done.stdout.strip().splitlines()[-1])


def main():
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("revision")
    parser.add_argument("--log", default="orebro", help="a shared log (default: orebro, the shortest)")
    parser.add_argument("--rounds", type=int, default=5)
    parser.add_argument("--out", help="also write the lines to this markdown file")
    args = parser.parse_args()
    found = glob.glob(str(LOGS / args.log / f"{args.log}.log*"))
    if not found:
        sys.exit(f"no log {args.log!r} in {LOGS}")
    log = found[0]
    with tempfile.TemporaryDirectory() as folder:
        extract_package(args.revision, folder)
        trees = {args.revision: Path(folder), "this tree": ROOT}
        for tree in trees.values():                    # warm Taichi's offline cache for both
            one(tree, log)
        runs = {name: [] for name in trees}
        for r in range(args.rounds):
            for name in (list(trees) if r % 2 == 0 else list(trees)[::-1]):
                runs[name].append(one(trees[name], log))
    old, new = runs[args.revision], runs["this tree"]
    lines = [f"{args.log}, {args.rounds} rounds, medians in seconds:", ""]
    for field in ("imports", "taichi", "kernels", "run", "total"):
        a, b = statistics.median(x[field] for x in old), statistics.median(x[field] for x in new)
        ratio = statistics.median(y[field] / x[field] for x, y in zip(old, new))
        lines.append(f"- {field}: {args.revision} {a:.3f}, this tree {b:.3f}, paired ratio (median) {ratio:.3f}")
    lines.append(f"- kernel variants: {args.revision} {old[0]['variants']}, this tree {new[0]['variants']}")
    lines.append(f"- the same poses, bit for bit: {len({x['poses'] for x in old + new}) == 1}")
    print("\n".join(lines))
    if args.out:
        command = " ".join(["python bench/start_up.py", *sys.argv[1:]])
        Path(args.out).write_text(f"# Start-up, {git_revision()} against {args.revision}\n\n`{command}`, "
                                  f"{datetime.date.today()}\n\n" + "\n".join(lines) + "\n")

if __name__ == "__main__":
    main()
