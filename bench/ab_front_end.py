"""The mapping loop's front-end match, this tree against an older revision, in one process.

Pairs as the front end meets them (a submap of 6 scans cast at their odometry poses, and the next
scan alone, from the odometry's guess, both in the front end's evidence) from four shared logs;
each pair matched by the old and the new package in turn with the front end's options
(``SlamOptions().scan_matcher``), on fresh maps (nothing cached), so the machine's load falls on
both alike. Prints both medians, the median of the per-pair time ratios (new / old), and whether every
pose and calibrated covariance is bit-identical.

    python bench/ab_front_end.py 7e54b6b            # against that revision (git archive into a temp dir)
    python bench/ab_front_end.py 7e54b6b --rounds 5

With ``--loop``, the whole mapping loop instead (``slam`` on each named log, default options,
the old and the new package in turn, ``--rounds`` times): per log the front-end match's median
(``SlamResult.match_seconds``) and its parts' medians (target preparation, scan preparation,
match) both ways, the median ms a scan and of it the loop closing's, and whether the trajectories
are bit-identical.

    python bench/ab_front_end.py 9fb02c9 --loop edmonton seattle --rounds 2

With ``--captured``, the front end's own pairs instead: the loop runs once on each named log with
this tree, keeping every ``--every``-th of its front-end matches (the target as cast, the scan, the
guess); each kept pair is then prepared and matched by the old and the new package in turn, from
maps of the same form (a map the loop made from its trinary code is given to both so), ``--rounds``
times. Per log: the medians of the three parts (target preparation, scan preparation, match) both
ways, the median per-pair ratio of each and of their sum, and whether every pose, calibrated
covariance and verdict is bit-identical. Steadier than the loop, closer to it than the pairs.

    python bench/ab_front_end.py b2d6744 --captured edmonton seattle aces --rounds 3
"""

import argparse
import glob
import subprocess
import sys
import tempfile
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
LOGS = ROOT.parent / "shared" / "logs"


def extract_package(revision, folder):
    """The package at git ``revision`` written into ``folder`` (as ``folder/taichi_match``)."""
    archive = subprocess.run(["git", "-C", str(ROOT), "archive", revision, "taichi_match"], check=True,
                             capture_output=True).stdout
    subprocess.run(["tar", "-x", "-C", str(folder)], input=archive, check=True)


def old_package(revision, folder):
    """The package at ``revision`` importable as ``taichi_match_base`` from ``folder``."""
    extract_package(revision, folder)
    (Path(folder) / "taichi_match").rename(Path(folder) / "taichi_match_base")
    sys.path.insert(0, str(folder))
    import taichi_match_base

    return taichi_match_base


def pairs():
    from taichi_match import compose, inverse
    from taichi_match.logs import read_carmen
    from taichi_match.scans import SensorModel, scans_to_grid
    from taichi_match.slam import SCAN_MODEL, SlamOptions

    evidence = SlamOptions().scan_matcher.evidence

    out = []
    for name in ("aces", "csail", "edmonton", "fhw"):
        log = read_carmen(glob.glob(str(LOGS / name / f"{name}.log*"))[0])
        odo = log.poses
        for k0 in range(20, 300, 40):
            idx = list(range(k0, k0 + 6))
            origin = inverse(odo[k0])
            poses = np.array([compose(origin, odo[j]) for j in idx])
            a = scans_to_grid([log.scans[j] for j in idx], poses, resolution=0.05, model=SensorModel(max_ray_length=20),
                              evidence=evidence)
            b = scans_to_grid([log.scans[k0 + 6]], np.zeros((1, 3)), resolution=0.05,
                              model=replace(SCAN_MODEL, max_ray_length=20), evidence=evidence)
            out.append((a, b, compose(origin, odo[k0 + 6])))
    return out


def main():
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("revision", help="the older revision (git)")
    parser.add_argument("--rounds", type=int, default=3, help="times over the pairs (or the logs)")
    parser.add_argument("--loop", nargs="+", metavar="LOG", help="the whole mapping loop on these logs instead")
    parser.add_argument("--captured", nargs="+", metavar="LOG", help="the loop's own front-end pairs on these logs")
    parser.add_argument("--every", type=int, default=6, help="with --captured: keep every N-th front-end match")
    args = parser.parse_args()
    if not LOGS.is_dir():
        raise SystemExit(f"{LOGS} not found: the laser logs live in ../shared/logs")
    if args.loop:
        return loops(args.revision, args.loop, args.rounds)
    if args.captured:
        return captured(args.revision, args.captured, args.rounds, args.every)
    import taichi_match as new

    with tempfile.TemporaryDirectory() as folder:
        base = old_package(args.revision, folder)
        work = pairs()
        from taichi_match.slam import SlamOptions

        options = SlamOptions().scan_matcher
        front_end = dict(levels=options.levels, interpolation=options.interpolation)
        matchers = {"old": (base, base.Matcher(**front_end)), "new": (new, new.Matcher(**front_end))}
        times = {"old": [], "new": []}
        same = True
        for _ in range(args.rounds):
            for a, b, guess in work:
                results = {}
                for key, (package, matcher) in matchers.items():
                    fresh_a = package.GridMap(a.prob.copy(), a.resolution, a.corner_pose)
                    fresh_b = package.GridMap(b.prob.copy(), b.resolution, b.corner_pose)
                    started = time.perf_counter()
                    results[key] = matcher.match(fresh_a, fresh_b, guess)
                    times[key].append(time.perf_counter() - started)
                same &= bool(np.array_equal(results["old"].pose, results["new"].pose) and np.array_equal(
                    results["old"].calibrated_covariance, results["new"].calibrated_covariance))
    old, now = np.array(times["old"]), np.array(times["new"])
    print(f"{len(work)} pairs x {args.rounds}: {args.revision} median {1e3 * np.median(old):.2f} ms, this tree "
          f"{1e3 * np.median(now):.2f} ms, median ratio {np.median(now / old):.3f}; poses and covariances "
          f"bit-identical: {same}")


def loops(revision, names, rounds):
    """The mapping loop on each log, the old and the new package in turn (see the module docstring)."""
    import taichi_match.logs as new_logs
    import taichi_match.slam as new

    with tempfile.TemporaryDirectory() as folder:
        base = old_package(revision, folder)
        import taichi_match_base.logs as old_logs
        import taichi_match_base.slam as old

        for name in names:
            path = glob.glob(str(LOGS / name / f"{name}.log*"))[0]
            logs = {"old": old_logs.read_carmen(path), "new": new_logs.read_carmen(path)}   # each its own LaserLog
            runs = {"old": [], "new": []}
            for k in range(rounds):
                for key, package in (("old", old), ("new", new)) if k % 2 == 0 else (("new", new), ("old", old)):
                    started = time.perf_counter()
                    result = package.slam(logs[key])
                    runs[key].append((result, (time.perf_counter() - started) / len(logs[key].scans)))
            same = all(np.array_equal(a.poses, b.poses) for (a, _), (b, _) in zip(runs["old"], runs["new"]))
            for key in ("old", "new"):
                whole = np.median(np.concatenate([r.match_seconds for r, _ in runs[key]]))
                parts = np.median(np.vstack([r.match_parts for r, _ in runs[key]]), axis=0)
                per_scan = np.median([t for _, t in runs[key]])
                closing = np.median([r.seconds["loop closing"] / len(r.poses) for r, _ in runs[key]])
                print(f"{name:13s} {key} ({revision if key == 'old' else 'this tree'}): front-end match median "
                      f"{1e3 * whole:.2f} ms (target {1e3 * parts[0]:.2f}, scan {1e3 * parts[1]:.2f}, match "
                      f"{1e3 * parts[2]:.2f}), {1e3 * per_scan:.1f} ms a scan (loop closing {1e3 * closing:.1f})")
            print(f"{name:13s} trajectories bit-identical: {same}", flush=True)
    del base


def captured(revision, names, rounds, every):
    """The loop's own front-end pairs, prepared and matched by each package in turn (see the module
    docstring)."""
    import taichi_match as new
    import taichi_match.slam as new_slam
    from taichi_match.logs import read_carmen

    options = new_slam.SlamOptions().scan_matcher
    with tempfile.TemporaryDirectory() as folder:
        base = old_package(revision, folder)
        packages = {"old": base, "new": new}

        def same_form(grid, package):
            if grid._code is not None:               # as the loop made it: from its trinary code
                return package._grid._from_code(grid._code.copy(), grid.resolution, grid.corner_pose)
            return package.GridMap(grid.prob.copy(), grid.resolution, grid.corner_pose)

        for name in names:
            mapper, kept = new_slam.Slam(), []
            matcher = mapper._scan_matcher
            match = matcher.match

            def keep(a, b, guess, **overrides):
                if keep.calls % every == 0:
                    kept.append((a, b, np.array(guess, dtype=np.float64)))
                keep.calls += 1
                return match(a, b, guess, **overrides)

            keep.calls = 0
            matcher.match = keep
            mapper.run(read_carmen(glob.glob(str(LOGS / name / f"{name}.log*"))[0]))
            times, same = {"old": [], "new": []}, True
            for k in range(rounds):
                for i, (a, b, guess) in enumerate(kept):
                    results = {}
                    for key in ("old", "new") if (i + k) % 2 == 0 else ("new", "old"):
                        package = packages[key]
                        m = package.Matcher(package.MatchOptions(**options.__dict__))
                        fresh_a, fresh_b = same_form(a, package), same_form(b, package)
                        t0 = time.perf_counter()
                        m.prepare(fresh_a)
                        t1 = time.perf_counter()
                        m.prepare(fresh_b)
                        t2 = time.perf_counter()
                        results[key] = m.match(fresh_a, fresh_b, guess)
                        times[key].append((t1 - t0, t2 - t1, time.perf_counter() - t2))
                    same &= bool(np.array_equal(results["old"].pose, results["new"].pose)
                                 and np.array_equal(results["old"].calibrated_covariance,
                                                    results["new"].calibrated_covariance)
                                 and results["old"].accepted == results["new"].accepted)
            old, now = np.array(times["old"]), np.array(times["new"])
            ratios = np.median(now / old, axis=0)
            print(f"{name:13s} {len(kept)} pairs x {rounds}: {revision} {1e3 * np.median(old.sum(axis=1)):.2f} ms "
                  f"(target {1e3 * np.median(old[:, 0]):.2f}, scan {1e3 * np.median(old[:, 1]):.2f}, match "
                  f"{1e3 * np.median(old[:, 2]):.2f}), this tree {1e3 * np.median(now.sum(axis=1)):.2f} ms "
                  f"(target {1e3 * np.median(now[:, 0]):.2f}, scan {1e3 * np.median(now[:, 1]):.2f}, match "
                  f"{1e3 * np.median(now[:, 2]):.2f}); median ratios: target {ratios[0]:.3f}, scan {ratios[1]:.3f}, "
                  f"match {ratios[2]:.3f}, the pair {np.median(now.sum(axis=1) / old.sum(axis=1)):.3f}; "
                  f"bit-identical: {same}", flush=True)


if __name__ == "__main__":
    main()
