"""The front end's bias: a lone scan matched against the scans before it, started at the truth.

For every third scan k of each log, the scans k-7 .. k-1 are cast at the reference poses (the
mapping loop's submap model, ``SlamOptions.free_margin`` as given) and scan k alone (``slam``'s
``SCAN_MODEL``), in the scan matcher's evidence, and matched from the reference's relative pose;
accepted matches (``scan_accepted``) give the error in scan k's own frame: forward (the laser's
axis), lateral, heading. A match without bias has mean errors near 0; the standard error (se) is
the spread over the root of the count.

    python bench/front_end_bias.py                              # the simulated run and every log
    python bench/front_end_bias.py --margins 0 0.1 0.15 --logs seattle edmonton
"""

import argparse
import sys
from dataclasses import replace
from pathlib import Path

import numpy as np

from taichi_match import Matcher, compose, inverse
from taichi_match.logs import read_carmen, read_tum
from taichi_match.scans import BeamCounts, SensorModel, scans_to_grid
from taichi_match.slam import SCAN_MODEL, SlamOptions, scan_accepted

LOGS = Path(__file__).resolve().parents[2] / "shared" / "logs"
MEMBERS, EVERY = 7, 3


def errors(log, reference, margin, options=None):
    """(N, 3) accepted matches' errors (forward m, lateral m, heading rad) in the scan's frame."""
    options = options or SlamOptions()
    matcher = Matcher(options.scan_matcher)
    evidence = options.scan_matcher.evidence
    map_model = SensorModel(max_ray_length=options.max_ray_length, free_margin=margin)
    scan_model = replace(SCAN_MODEL, max_ray_length=options.max_ray_length)
    out = []
    for k in range(MEMBERS, len(log.scans), EVERY):
        members = range(k - MEMBERS, k)
        origin = inverse(reference[k - MEMBERS])
        counts = BeamCounts(resolution=options.resolution, model=map_model)
        counts.add([log.scans[j] for j in members], np.array([compose(origin, reference[j]) for j in members]))
        scan = scans_to_grid([log.scans[k]], np.zeros((1, 3)), resolution=options.resolution, model=scan_model,
                             evidence=evidence)
        truth = compose(origin, reference[k])
        result = matcher.match(counts.grid(evidence=evidence), scan, truth)
        if scan_accepted(result):
            out.append(compose(inverse(truth), result.pose))
    return np.array(out).reshape(-1, 3)


def row(name, margin, e):
    se = e.std(axis=0) / np.sqrt(len(e))
    return (f"| {name} | {margin:g} | {len(e)} | {1e3 * e[:, 0].mean():+.1f} ({1e3 * se[0]:.1f}) | "
            f"{1e3 * e[:, 1].mean():+.1f} ({1e3 * se[1]:.1f}) | {np.degrees(e[:, 2].mean()):+.3f} | "
            f"{1e3 * np.median(np.hypot(e[:, 0], e[:, 1])):.1f} | {np.degrees(np.median(np.abs(e[:, 2]))):.3f} |")


def main():
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--logs", nargs="*", help="log names (default: all in ../shared/logs)")
    parser.add_argument("--margins", nargs="+", type=float, default=[0.0, SlamOptions().free_margin],
                        help="free margins to compare, metres (default: 0 and the loop's default)")
    parser.add_argument("--no-simulated", action="store_true", help="leave out the simulated run")
    args = parser.parse_args()
    runs = []
    if not args.no_simulated:
        from taichi_match.simulate import simulate_log

        sim = simulate_log(0)
        runs.append(("simulated", sim.log, sim.truth))
    if args.logs != []:
        if not LOGS.is_dir():
            print(f"{LOGS} not found: the laser logs live in ../shared/logs; the simulated run only", file=sys.stderr)
        else:
            for name in args.logs or sorted(p.name for p in LOGS.iterdir() if p.is_dir()):
                runs.append((name, read_carmen(LOGS / name / f"{name}.log.gz"),
                             read_tum(LOGS / name / f"{name}.reference.tum")[1]))
    print("| log | free margin m | matches | forward mean mm (se) | lateral mean mm (se) | heading mean deg | "
          "median position error mm | median heading error deg |")
    print("|---|---|---|---|---|---|---|---|")
    for name, log, reference in runs:
        for margin in args.margins:
            print(row(name, margin, errors(log, reference, margin)), flush=True)


if __name__ == "__main__":
    main()
