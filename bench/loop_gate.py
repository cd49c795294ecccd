"""The loop gate (``SlamOptions.loop_gate``), paired run by run.

The gate acts last: after the final optimisation (and the audit's repairs) it takes out of the
graph the loop closures the optimised graph contradicts and optimises once more. The poses it
starts from are those of a run without it, bit for bit, so one run gives both: each log's twenty
runs of ``bench/slam.py --jitter 19`` (the log as it is, then the odometry moved by about a
micrometre, seeds 0-18), and for each the ATE before and after the gate against the reference,
and the loop closures in the graph wrong against it (0.2 m or 1 degree off) before and after.

    python bench/loop_gate.py --out bench/LOOP_GATE.md
    python bench/loop_gate.py --logs csail fhw --runs 5
    python bench/loop_gate.py --simulated --logs          # the simulated run only
"""

import argparse
import sys
from pathlib import Path

import numpy as np

import taichi_match.slam as slam_module
from taichi_match.evaluation import trajectory_errors
from taichi_match.logs import read_carmen, read_tum

sys.path.insert(0, str(Path(__file__).resolve().parent))
from slam import LOGS, jittered, loop_error  # noqa: E402


def _wrong(loop, reference) -> bool:
    metres, degrees = loop_error(loop, reference)
    return metres > 0.2 or abs(degrees) > 1.0


def paired_run(log, reference) -> dict:
    """One run at default options: the ATE and the wrong loop closures before the gate and after."""
    before = {}
    gate = slam_module.Slam._gate_loops

    def watched(self, m):
        before["poses"] = np.array(m.est[:len(m.scans)])
        before["wrong"] = sum(_wrong(loop, reference) for loop in m.loops if loop["edge"])
        return gate(self, m)

    slam_module.Slam._gate_loops = watched
    try:
        result = slam_module.Slam().run(log)
    finally:
        slam_module.Slam._gate_loops = gate
    was, now = trajectory_errors(before["poses"], reference), trajectory_errors(result.poses, reference)
    wrong = sum(_wrong(loop, reference) for loop in result.loops if loop["edge"])
    gated = sum(bool(loop.get("gated")) for loop in result.loops)
    return dict(ate_before=was["ate_m"], ate_after=now["ate_m"], deg_before=was["ate_deg"], deg_after=now["ate_deg"],
                wrong_before=before["wrong"], wrong_after=wrong, gated=gated)


def row(name, runs) -> str:
    before, after = (np.array([r[k] for r in runs]) for k in ("ate_before", "ate_after"))
    delta = 1e3 * (after - before)
    inside = [sum(r[f"ate_{w}"] <= 0.10 and r[f"deg_{w}"] <= 1.0 for r in runs) for w in ("before", "after")]
    wrong = [np.median([r[f"wrong_{w}"] for r in runs]) for w in ("before", "after")]
    return (f"| {name} | {len(runs)} | {np.median(before):.4f} / {np.median(after):.4f} | {delta.min():+.1f} / "
            f"{np.median(delta):+.1f} / {delta.max():+.1f} | {int((delta < 0).sum())} / {int((delta > 0).sum())} | "
            f"{inside[0]} / {inside[1]} | {wrong[0]:.0f} / {wrong[1]:.0f} | "
            f"{np.median([r['gated'] for r in runs]):.0f} |")


def main():
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--logs", nargs="*", help="log names (default: all in ../shared/logs)")
    parser.add_argument("--simulated", action="store_true", help="also the simulated run (taichi_match.simulate)")
    parser.add_argument("--runs", type=int, default=20, help="runs per log, the first unjittered (default 20)")
    parser.add_argument("--out", help="also write the table (markdown) here")
    args = parser.parse_args()
    cases = []
    if args.simulated:
        from taichi_match.simulate import simulate_log

        run = simulate_log(0)
        cases.append(("simulated", run.log, run.truth))
    if args.logs != []:
        if not LOGS.is_dir():
            raise SystemExit(f"{LOGS} not found: the laser logs live in ../shared/logs")
        for name in args.logs or sorted(p.name for p in LOGS.iterdir() if p.is_dir()):
            _, reference = read_tum(LOGS / name / f"{name}.reference.tum")
            cases.append((name, read_carmen(LOGS / name / f"{name}.log.gz"), reference))
    lines = ["| log | runs | median ATE m, before / after the gate | ATE change mm (min / median / max) | runs "
             "lower / higher | runs within the ATE target, before / after | wrong loop closures in the graph "
             "(median), before / after | closures taken out (median) |", "|---|---|---|---|---|---|---|---|"]
    print("\n".join(lines), flush=True)
    for name, log, reference in cases:
        runs = [paired_run(log if seed < 0 else jittered(log, seed), reference) for seed in range(-1, args.runs - 1)]
        lines.append(row(name, runs))
        print(lines[-1], flush=True)
    if args.out:
        from taichi_match.reproduce import git_revision

        Path(args.out).write_text(f"# The loop gate, paired run by run\n\n`python bench/loop_gate.py` at revision "
                                  f"{git_revision()}: each run's ATE (and its loop closures wrong against the "
                                  f"reference) before the gate and after; see the script's docstring.\n\n"
                                  + "\n".join(lines) + "\n", encoding="utf-8")


if __name__ == "__main__":
    main()
