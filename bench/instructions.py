"""Instructions per corridor match, counted by valgrind's callgrind: a cost that the machine's
other tenants do not move (wall-clock medians here vary 2x from hour to hour).

Runs ``valgrind --tool=callgrind`` on a process that warms a matcher up and then matches the
paper's corridor from N seeded wide-row guesses, for N = 0 and N = ``--matches``; the difference
divided by N is the instructions of one full match (Python, NumPy and the Taichi kernels, all
threads). Each process takes about a minute (valgrind runs the program some 50x slower).

    python bench/instructions.py                               # this checkout
    python bench/instructions.py --other ../old-checkout       # and another one, for a ratio

Measured on 2026-11-29 against ec852f7: 28.8 and 27.8 M instructions per match against 25.0 and
24.8 M in two runs (ratios 1.15 and 1.12; the counts still move by a few per cent from run to
run), the cost of the finer levels' 8 launches (``refine_xtol``).
"""

import argparse
import os
import re
import shutil
import subprocess
import sys
import tempfile
import textwrap
from pathlib import Path

# One allowed CPU: Taichi then starts one worker thread, and no thread spins waiting for another
# (with two, the counts moved by a few per cent between runs).
PIN = ["taskset", "-c", "0"] if shutil.which("taskset") else []

WORKLOAD = textwrap.dedent("""
    import sys
    import numpy as np
    import taichi_match as tm
    from taichi_match.scenes import corridor
    g = corridor()
    m = tm.Matcher()
    m.match(g, g, [0.1, 0.1, 0.1])
    m.match(g, g, [0.3, -0.2, 0.05])
    rng = np.random.default_rng(0)
    for _ in range(int(sys.argv[1])):
        m.match(g, g, rng.uniform(-1.5, 1.5, 3) * [1, 1, 0.25])
""")


def instructions(checkout, matches, folder):
    """Instructions of the workload with ``matches`` matches, ``checkout``'s package first on the path."""
    script = Path(folder) / "workload.py"
    script.write_text(WORKLOAD)
    env = dict(os.environ, PYTHONPATH=str(checkout), TAICHI_MATCH_PIN_THREADS="0")
    out = subprocess.run(PIN + ["valgrind", "--tool=callgrind", f"--callgrind-out-file={folder}/callgrind.out",
                                sys.executable, str(script), str(matches)], capture_output=True, text=True, env=env,
                         check=True)
    return int(re.search(r"I\s+refs:\s+([\d,]+)", out.stderr).group(1).replace(",", ""))


def per_match(checkout, matches):
    with tempfile.TemporaryDirectory() as folder:
        # first without valgrind, so that both counted runs find the kernels in Taichi's offline
        # cache (its key includes the thread count: a compile in one run alone would count)
        (Path(folder) / "workload.py").write_text(WORKLOAD)
        subprocess.run(PIN + [sys.executable, f"{folder}/workload.py", "1"],
                       env=dict(os.environ, PYTHONPATH=str(checkout)), check=True, capture_output=True)
        return (instructions(checkout, matches, folder) - instructions(checkout, 0, folder)) / matches


def main():
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--matches", type=int, default=20)
    parser.add_argument("--other", help="another checkout of taichi_match to compare with")
    args = parser.parse_args()
    if shutil.which("valgrind") is None:
        raise SystemExit("valgrind not found (Debian: apt install valgrind)")
    here = per_match(Path(__file__).resolve().parents[1], args.matches)
    print(f"this checkout: {here / 1e6:.1f} M instructions per corridor match")
    if args.other:
        other = per_match(Path(args.other).resolve(), args.matches)
        print(f"{args.other}: {other / 1e6:.1f} M instructions per match; ratio {here / other:.3f}")


if __name__ == "__main__":
    main()
