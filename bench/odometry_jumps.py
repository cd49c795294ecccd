"""Odometry jumps planted into the mapping loop's input, with and without ``SlamOptions.jump_check``.

A jump moves the odometry from scan k on by a rigid motion about scan k - 1's odometry pose (a
reset: every later reading moved), or only scan k's reading (a spike: one bad reading), at a
third and at half of the run. Each jump is run with the check off (``jump_check=None``) and on
(the default); the table gives the ATE against the truth (the simulated run) or the reference
(the shared logs), the scans the check searched at, and those where it found a jump (J) or took
the next scan's step from the readings around a spike (S). The jumps stay under
``max_ray_length`` (20 m), beyond which the loop refuses the log before any work.

    python bench/odometry_jumps.py                          # the simulated run, aces, seattle, orebro
    python bench/odometry_jumps.py --logs fhw --out bench/ODOMETRY_JUMPS.md
"""

import argparse
import dataclasses
import datetime
import subprocess
from pathlib import Path

import numpy as np

from taichi_match import compose, inverse
from taichi_match.evaluation import trajectory_errors
from taichi_match.logs import LaserLog, read_carmen, read_tum
from taichi_match.simulate import simulate_log
from taichi_match.slam import Slam

LOGS = Path(__file__).resolve().parents[2] / "shared" / "logs"
JUMPS = ((18.0, 0.0, 0.0), (0.0, 0.0, 1.0), (3.0, -2.0, 0.3))      # (x m, y m, theta rad) in scan k - 1's frame


def planted(log, k, jump, spike):
    """``log`` with the odometry moved by ``jump`` about scan ``k - 1``'s pose, from scan ``k`` on
    (or at ``k`` only, a ``spike``)."""
    about = log.scans[k - 1].pose
    motion = compose(about, compose(np.array(jump), inverse(about)))
    return LaserLog(tuple(dataclasses.replace(s, pose=compose(motion, s.pose)) if j == k or (j > k and not spike)
                          else s for j, s in enumerate(log.scans)), log.odometry)


def checks(result):
    """The scans the check searched at, a jump found marked J, a spike's next scan S."""
    marks = [f"{c['scan']}{'J' if c['jump'] else 'S' if c['spike'] else ''}" for c in result.jump_checks]
    return " ".join(marks) or "-"


def main():
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--logs", nargs="*", default=["aces", "seattle", "orebro"], help="shared logs (default: "
                        "aces seattle orebro)")
    parser.add_argument("--out", help="also write the table (markdown) here")
    args = parser.parse_args()
    runs = [("simulated", *(lambda r: (r.log, r.truth))(simulate_log(0)))]
    for name in args.logs:
        runs.append((name, read_carmen(LOGS / name / f"{name}.log.gz"),
                     read_tum(LOGS / name / f"{name}.reference.tum")[1]))
    lines = ["| run | at scan | kind | jump (x m, y m, theta rad) | ATE m / deg, no check | ATE m / deg, "
             "jump_check | checks (J: jump found, S: spike's next scan) |", "|---|---|---|---|---|---|---|"]
    print("\n".join(lines), flush=True)
    for name, log, truth in runs:
        plain = trajectory_errors(Slam().run(log).poses, truth)
        row = f"| {name} | - | as it is | - | | {plain['ate_m']:.3f} / {plain['ate_deg']:.2f} | |"
        lines.append(row)
        print(row, flush=True)
        for k in (len(log) // 3, len(log) // 2):
            for spike in (False, True):
                for jump in JUMPS:
                    moved = planted(log, k, jump, spike)
                    off, on = (Slam(jump_check=check).run(moved) for check in (None, 3.0))
                    e_off, e_on = trajectory_errors(off.poses, truth), trajectory_errors(on.poses, truth)
                    row = (f"| {name} | {k} | {'spike' if spike else 'reset'} | {jump} | {e_off['ate_m']:.3f} / "
                           f"{e_off['ate_deg']:.2f} | {e_on['ate_m']:.3f} / {e_on['ate_deg']:.2f} | {checks(on)} |")
                    lines.append(row)
                    print(row, flush=True)
    if args.out:
        revision = subprocess.run(["git", "-C", str(Path(__file__).parent), "rev-parse", "--short", "HEAD"],
                                  capture_output=True, text=True).stdout.strip()
        head = ["# Odometry jumps planted into the mapping loop", "",
                f"`python bench/odometry_jumps.py --logs {' '.join(args.logs)} --out {args.out}` at revision "
                f"{revision}, {datetime.date.today()}. A reset moves the odometry from the scan on by the "
                f"jump about the previous scan's odometry pose; a spike moves that scan's reading only. The "
                f"ATE is against the simulated truth or the log's reference.", ""]
        Path(args.out).write_text("\n".join(head + lines) + "\n")


if __name__ == "__main__":
    main()
