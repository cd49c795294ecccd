"""The mapping loop on every log of ``../shared/logs`` against its reference trajectory (issue 12).

For each log: ``taichi_match.slam.Slam`` at default options on the CARMEN log (odometry in the
FLASER lines), then against ``NAME.reference.tum``:

- ATE after one rigid SE(2) alignment and RPE over 10 scans, metres and degrees, beside the
  odometry's (``taichi_match.evaluation``, checked against evo in the tests);
- loop closures tried / accepted by the verdict / in the graph (also consistent with their
  neighbours) / wrong (in the graph, and the relative pose of the two nodes it joins differs from
  the reference's by more than 0.2 m or 1 degree, Cartographer's criterion; with
  ``submap_frames`` a frame node's reference pose is the one that best carries its scans' cast
  poses onto their reference poses); and of
  the wrong ones, how many fit the raw beam endpoints of the two submaps better than the
  reference's poses do (``ours_fits_better``): the references are themselves a SLAM result;
- the map's misfit (``map_misfit``): the mean distance from each beam endpoint to the nearest
  endpoint of another scan, capped at 0.2 m, at our poses and at the reference's;
- scan-to-submap matches accepted; wall time per scan, per stage; the front-end match's median
  (preparing the new submap and scan included), and in parts;
- scan by scan, as on a robot (the logs are fed to ``Slam.add`` one scan at a time, the same run
  bit for bit as ``Slam.run``): the ATE of each scan's pose as it was when the scan came, and the
  wall time of each ``add`` (median, 99th percentile, max; the share over 25 ms);
- a picture per log: the trajectory and the reference over the map (``--plots DIR``);
- the machine's speed before and after the runs (``bench/yardstick.py``: the corridor's match
  median), to set the times beside another run's;
- with ``--jitter N``: N more runs per log with every odometry pose moved by about a micrometre
  and a microradian (seeded noise, far below any sensor's resolution), and the spread of ATE,
  RPE and wrong loops over the N + 1 runs. The loop is chaotic (a grazing beam counted in the
  neighbouring cell moved one log's ATE threefold): one run per log cannot rank small changes,
  and five cannot rank changes under about 0.03 m (two sets of five runs of the defaults gave
  medians 0.078 and 0.096 m on aces, 0.120 and 0.148 on orebro: docs/slam.md).

    python bench/slam.py                                   # table to stdout
    python bench/slam.py --out bench/SLAM.md --plots bench/slam
    python bench/slam.py --logs aces csail
    python bench/slam.py --simulated                       # the simulated run of the README too (first row)
    python bench/slam.py --simulated --logs                # only the simulated run
    python bench/slam.py --logs orebro csail --jitter 2     # the spread over three runs per log
    python bench/slam.py --logs orebro --jitter 19 --first-seed 100    # another twenty: other seeds
    python bench/slam.py --set target_refresh=5            # options other than the defaults
    python bench/slam.py --set scan_matcher.levels=3 --set scan_matcher.interpolation=nearest
                                                           # the front end's MatchOptions before 2026-12-06
    python bench/slam.py --simulated --logs --laps 12 --set loop_ties=5 --set solver=isam2
                                                           # a long run: the simulated ring 12 times round
"""

import argparse
import ast
import dataclasses
import datetime
import math
import os
import sys
import time
from pathlib import Path

import numpy as np

from taichi_match import compose, inverse, wrap_angle
from taichi_match.evaluation import align_se2, frame_reference, trajectory_errors
from taichi_match.logs import read_carmen, read_tum
from taichi_match.slam import Slam, SlamOptions

sys.path.insert(0, str(Path(__file__).resolve().parent))
from yardstick import corridor_median_ms  # noqa: E402

LOGS = Path(__file__).resolve().parents[2] / "shared" / "logs"
TARGETS = {"ate_m": 0.10, "ate_deg": 1.0, "rpe_m": 0.03, "rpe_deg": 0.3}


def loop_error(loop, reference):
    """(metres, degrees): a loop closure's relative pose against the reference's relative pose of
    the two nodes its edge joins: a scan's reference pose where a submap's frame is its first
    scan's node, ``evaluation.frame_reference`` where it is a node of its own (``submap_frames``,
    the default)."""
    fa, fb = (reference[key] if key < len(reference) else frame_reference(*m, reference)
              for key, m in zip(loop["frames"], loop["members"]))
    e = compose(inverse(compose(inverse(fa), fb)), loop["pose"])
    return float(np.hypot(e[0], e[1])), float(np.degrees(wrap_angle(e[2])))


def wrong_loops(loops, reference):
    """Loop closures in the graph whose relative pose is off the reference's by > 0.2 m or > 1 degree."""
    return [loop for loop in loops
            if loop["edge"] and (lambda m, d: m > 0.2 or abs(d) > 1.0)(*loop_error(loop, reference))]


def _endpoints(log, scans, poses, max_range=20.0):
    """The beam endpoints (returns within ``max_range``) of ``scans`` placed at ``poses``: (N, 2)."""
    out = []
    for j, pose in zip(scans, poses):
        scan = log.scans[j]
        ok = np.isfinite(scan.ranges) & (scan.ranges > 0.05) & (scan.ranges < min(scan.max_range - 0.01, max_range))
        x, y = scan.ranges[ok] * np.cos(scan.angles[ok]), scan.ranges[ok] * np.sin(scan.angles[ok])
        c, s = math.cos(pose[2]), math.sin(pose[2])
        out.append(np.column_stack([pose[0] + c * x - s * y, pose[1] + s * x + c * y]))
    return np.concatenate(out)


def _misfit(a, b, cap=0.2):
    """The mean distance of ``b``'s points to their nearest point of ``a``, each capped at ``cap`` m."""
    from scipy.spatial import cKDTree

    d, _ = cKDTree(a).query(b, distance_upper_bound=cap)
    return float(np.mean(np.minimum(d, cap)))


def map_misfit(log, poses, cap=0.2, k=8):
    """The mean distance, metres, from each beam endpoint of the scans at ``poses`` to the nearest
    endpoint of another scan, capped at ``cap``: how crisp the map is, whatever made the poses."""
    from scipy.spatial import cKDTree

    clouds = [_endpoints(log, [j], [p]) for j, p in enumerate(poses)]
    points = np.concatenate(clouds)
    label = np.repeat(np.arange(len(clouds)), [len(c) for c in clouds])
    d, i = cKDTree(points).query(points, k=k, distance_upper_bound=cap)
    other = label[np.minimum(i, len(points) - 1)] != label[:, None]
    return float(np.mean(np.min(np.where(other & np.isfinite(d), d, cap), axis=1)))


def ours_fits_better(loop, log, reference):
    """Whether the raw beam endpoints of a loop closure's two submaps fit each other better as the
    loop closure places them (each submap's scans as cast, B's by the loop's pose) than at the
    reference poses: a judge of a "wrong" loop closure independent of both the matcher and the
    reference (on the simulated run, whose truth is exact, the truth fits better in 9 of 11)."""
    (scans_a, poses_a), (scans_b, poses_b) = loop["members"]
    ours = _misfit(_endpoints(log, scans_a, poses_a),
                   _endpoints(log, scans_b, [compose(loop["pose"], p) for p in poses_b]))
    theirs = _misfit(_endpoints(log, scans_a, reference[scans_a]), _endpoints(log, scans_b, reference[scans_b]))
    return ours < theirs


def run_one(name, log, reference, plots=None, options=None):
    mapper = Slam(**(options or {}))
    started = time.perf_counter()
    live = np.array([mapper.add(scan) for scan in log.scans])     # as on a robot: scan by scan
    result = mapper.finish()
    wall = time.perf_counter() - started
    errors = trajectory_errors(result.poses, reference)
    online = trajectory_errors(live, reference)
    wrong = wrong_loops(result.loops, reference)
    misfit = (map_misfit(log, result.poses), map_misfit(log, reference))
    odometry = trajectory_errors(log.poses, reference)
    row = dict(log=name, scans=len(log), **errors, **{f"odo_{k}": v for k, v in odometry.items()},
               scan_accepted=result.scan_matches[0], scan_tried=result.scan_matches[1],
               loops_tried=len(result.loops), loops_accepted=sum(lp["accepted"] for lp in result.loops),
               loops_edges=sum(lp["edge"] for lp in result.loops),
               loops_wrong=len(wrong), loops_wrong_ours=sum(ours_fits_better(lp, log, reference) for lp in wrong),
               misfit=misfit, ms_per_scan=1e3 * wall / len(log),
               match_ms=1e3 * float(np.median(result.match_seconds)),
               match_parts_ms=1e3 * np.median(result.match_parts, axis=0),
               stages={k: 1e3 * v / len(log) for k, v in result.seconds.items()},
               live_ate_m=online["ate_m"], live_ate_deg=online["ate_deg"],
               add_ms=1e3 * np.percentile(result.add_seconds[2:], [50, 99, 100]),    # after the first match
               finish_ms=1e3 * (wall - result.add_seconds.sum()),
               late=float(np.mean(result.add_seconds > 0.025)),
               disagreements=None if result.disagreements is None else
               (len(result.disagreements), sum(p["repaired"] for p in result.disagreements)))
    if plots:
        picture(Path(plots) / f"{name}.png", name, result, log, reference)
    return row


def jittered(log, seed, size=1e-6):
    """``log`` with every scan's odometry pose moved by N(0, ``size``) in x, y (metres) and theta
    (radians), seeded."""
    rng = np.random.default_rng(seed)
    scans = tuple(dataclasses.replace(scan, pose=scan.pose + rng.normal(0.0, size, 3)) for scan in log.scans)
    return dataclasses.replace(log, scans=scans)


def spread_table(spreads):
    audited = all(r.get("disagreements") is not None for rows in spreads.values() for r in rows)
    lines = ["| log | runs | ATE m (min / median / max) | ATE deg | RPE10 m | RPE10 deg | wrong loops "
             "| runs within the ATE target (0.10 m and 1 deg) | map misfit cm (no reference) |"
             + (" audit: disagreeing submap pairs (min / median / max), runs with a repair |" if audited else ""),
             "|---|---|---|---|---|---|---|---|---|" + ("---|" if audited else "")]
    for name, rows in spreads.items():
        cell = lambda key, fmt: " / ".join(format(v, fmt) for v in np.percentile([r[key] for r in rows], [0, 50, 100]))  # noqa: E731
        within = sum(r["ate_m"] <= 0.10 and r["ate_deg"] <= 1.0 for r in rows)
        audit = ""
        if audited:
            pairs = " / ".join(f"{v:.0f}" for v in np.percentile([r["disagreements"][0] for r in rows], [0, 50, 100]))
            audit = f" {pairs}, {sum(r['disagreements'][1] > 0 for r in rows)} |"
        misfit = " / ".join(f"{100 * v:.3f}" for v in np.percentile([r["misfit"][0] for r in rows], [0, 50, 100]))
        lines.append(f"| {name} | {len(rows)} | {cell('ate_m', '.3f')} | {cell('ate_deg', '.2f')} "
                     f"| {cell('rpe_m', '.3f')} | {cell('rpe_deg', '.2f')} | {cell('loops_wrong', '.0f')} "
                     f"| {within} | {misfit} |" + audit)
    return "\n".join(lines)


def picture(path, name, result, log, reference):
    from taichi_match.plots import save_trajectories

    path.parent.mkdir(parents=True, exist_ok=True)
    save_trajectories(path, result.map, {
        "odometry": (align_se2(log.poses, result.poses), "tab:orange", "-"),
        "reference": (align_se2(reference, result.poses), "tab:green", "-"),      # in the map's frame
        "taichi-match slam": (result.poses, "tab:red", "--")}, title=name)


def table(rows):
    def flag(row, key):
        return "" if row[key] <= TARGETS[key] else " *"
    lines = ["| log | scans | ATE m | ATE deg | RPE10 m | RPE10 deg | odometry ATE m / deg | odometry RPE10 m / deg "
             "| ATE / odometry ATE | scan matches accepted "
             "| loops tried / accepted / in the graph / wrong (fit ours better) "
             "| map misfit cm, ours / reference | ms per scan "
             "| front-end match median ms |",
             "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        lines.append(
            f"| {r['log']} | {r['scans']} | {r['ate_m']:.3f}{flag(r, 'ate_m')} "
            f"| {r['ate_deg']:.2f}{flag(r, 'ate_deg')} "
            f"| {r['rpe_m']:.3f}{flag(r, 'rpe_m')} | {r['rpe_deg']:.2f}{flag(r, 'rpe_deg')} "
            f"| {r['odo_ate_m']:.2f} / {r['odo_ate_deg']:.1f} | {r['odo_rpe_m']:.3f} / {r['odo_rpe_deg']:.2f} "
            f"| {r['ate_m'] / r['odo_ate_m']:.3f} | {r['scan_accepted']}/{r['scan_tried']} "
            f"| {r['loops_tried']} / {r['loops_accepted']} / {r['loops_edges']} "
            f"/ {r['loops_wrong']} ({r['loops_wrong_ours']}) "
            f"| {100 * r['misfit'][0]:.2f} / {100 * r['misfit'][1]:.2f} | {r['ms_per_scan']:.0f} "
            f"| {r['match_ms']:.1f} |")
    stages = list(rows[0]["stages"])
    lines += ["", "Wall time per scan by stage (ms), and the machine's speed just before the log's first run (the "
              "yardstick, `bench/yardstick.py`: it moves by half from hour to hour on this shared machine, and every "
              "time in these tables with it):", "",
              "| log | " + " | ".join(stages) + " | yardstick ms |", "|---|" + "---|" * (len(stages) + 1)]
    lines += [f"| {r['log']} | " + " | ".join(f"{r['stages'][s]:.1f}" for s in stages)
              + f" | {r.get('yardstick_ms', float('nan')):.1f} |" for r in rows]
    lines += ["", "The front-end match in parts, median ms: preparing its target (the older open submap, cast "
              "anew for each scan), preparing the scan, and matching the two prepared maps:", "",
              "| log | target preparation | scan preparation | match | whole (median of the sums) |",
              "|---|---|---|---|---|"]
    lines += [f"| {r['log']} | " + " | ".join(f"{v:.1f}" for v in r["match_parts_ms"]) + f" | {r['match_ms']:.1f} |"
              for r in rows]
    lines += ["", "Scan by scan, as on a robot (`Slam.add` for each scan, then `Slam.finish`): the ATE of the pose "
              "each scan was given when it came (before later loop closures moved it), the wall time of each "
              "`add` after the first match (which in a new process compiles Taichi's kernels; a scan that completes "
              "a submap waits for its loop closures and an optimisation), the share of scans over 25 ms (a 40 Hz "
              "laser's period), and `finish` (the last submap's closures, a last optimisation, the audit and the "
              "global map):", "",
              "| log | ATE m / deg when each scan came | ATE m / deg at the end | add ms: median / 99 % / max "
              "| scans over 25 ms | finish s |", "|---|---|---|---|---|---|"]
    lines += [f"| {r['log']} | {r['live_ate_m']:.3f} / {r['live_ate_deg']:.2f} | {r['ate_m']:.3f} / {r['ate_deg']:.2f} "
              f"| {' / '.join(f'{v:.1f}' for v in r['add_ms'])} | {100 * r['late']:.1f} % "
              f"| {r['finish_ms'] / 1e3:.2f} |"
              for r in rows]
    return "\n".join(lines)


def main():
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--logs", nargs="*", help="log names (default: all in ../shared/logs)")
    parser.add_argument("--simulated", action="store_true", help="also the simulated run (taichi_match.simulate)")
    parser.add_argument("--laps", type=float, default=2.0, help="times round the simulated ring (default 2)")
    parser.add_argument("--out", help="also write the table (markdown) here")
    parser.add_argument("--plots", help="folder for one picture per log")
    parser.add_argument("--jitter", type=int, default=0, metavar="N",
                        help="N more runs per log with the odometry moved by about 1e-6 (seeded): the spread")
    parser.add_argument("--first-seed", type=int, default=0, metavar="K",
                        help="the jittered runs' seeds K .. K + N - 1 (default 0): another sample of the spread")
    parser.add_argument("--set", action="append", default=[], metavar="NAME=VALUE",
                        help="a SlamOptions field other than the default (a Python literal, or a word taken as a "
                             "string), e.g. target_refresh=5, solver=isam2, scan_matcher.levels=3")
    args = parser.parse_args()
    options = {}
    for item in args.set:
        name, _, value = item.partition("=")
        try:
            value = ast.literal_eval(value)
        except (ValueError, SyntaxError):
            pass
        field, _, inner = name.partition(".")        # "scan_matcher.levels": a MatchOptions field
        if inner:
            value = options.get(field, getattr(SlamOptions(), field)).replace(**{inner: value})
        options[field] = value
    from taichi_match.reproduce import git_revision

    started = time.perf_counter()
    yardstick = [corridor_median_ms()]          # the machine's speed, before and after the runs
    rows, spreads = [], {}

    def jitter_runs(name, log, reference):
        if args.jitter > 0:
            spreads[name] = [rows[-1]] + [run_one(name, jittered(log, seed), reference, options=options)
                                          for seed in range(args.first_seed, args.first_seed + args.jitter)]

    if args.simulated:
        from taichi_match.simulate import simulate_log

        run = simulate_log(0, laps=args.laps)
        speed = corridor_median_ms()
        rows.append(run_one("simulated", run.log, run.truth, args.plots, options))
        rows[-1]["yardstick_ms"] = speed
        jitter_runs("simulated", run.log, run.truth)
    if args.logs != []:
        if not LOGS.is_dir():
            raise SystemExit(f"{LOGS} not found: the laser logs live in ../shared/logs")
        for name in args.logs or sorted(p.name for p in LOGS.iterdir() if p.is_dir()):
            log = read_carmen(LOGS / name / f"{name}.log.gz")
            _, reference = read_tum(LOGS / name / f"{name}.reference.tum")
            speed = corridor_median_ms()                # the machine's speed just before this log's timed run
            rows.append(run_one(name, log, reference, args.plots, options))
            rows[-1]["yardstick_ms"] = speed
            jitter_runs(name, log, reference)
            shown = {k: (round(v, 4) if isinstance(v, float) else v) for k, v in rows[-1].items()
                     if k not in ("stages", "match_parts_ms", "add_ms", "yardstick_ms")}
            print(name, shown, flush=True)
    yardstick.append(corridor_median_ms())
    text = ["# The mapping loop on real laser logs", "",
            f"`python bench/slam.py {' '.join(sys.argv[1:])}` at revision {git_revision()}, {datetime.date.today()}, "
            f"{os.cpu_count()}-core machine, {time.perf_counter() - started:.0f} s. "
            f"{'Options: ' + ', '.join(args.set) if args.set else 'Default options'}. Targets: ATE <= "
            f"0.10 m and 1 deg, RPE over 10 scans <= 0.03 m and 0.3 deg, ATE <= odometry's / 10, no wrong loop "
            f"closure, <= 25 ms per scan; * marks a miss. The machine's speed (`bench/yardstick.py`: the paper's "
            f"corridor matched, median): {yardstick[0]:.1f} ms before the runs, {yardstick[1]:.1f} ms after.",
            "", table(rows)]
    if spreads:
        text += ["", f"The same logs with every odometry pose moved by about 1e-6 m and 1e-6 rad (seeded), "
                     f"{args.jitter} more runs each: the spread over all runs.", "", spread_table(spreads)]
    print("\n".join(text))
    if args.out:
        Path(args.out).write_text("\n".join(text) + "\n")


if __name__ == "__main__":
    main()
