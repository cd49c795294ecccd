"""How far the logs' reference trajectories are from what their scans say, measured without our
matcher: a plain point-to-line ICP between scans (a measuring tool here, not part of the
package; scipy's cKDTree for the neighbours).

For scans k, k+1, k+2 (every third k) ICP finds the relative poses k->k+1, k+1->k+2 and k->k+2,
each started from the reference's. Reported per log, medians:

- ICP against the reference's relative pose of consecutive scans (translation and rotation);
- ICP's own cycle error, k->k+1->k+2 against k->k+2: how consistent ICP is with itself.

When ICP closes its cycles to a few millimetres but disagrees with the reference's consecutive
poses by centimetres, the reference (a SLAM result, shared/logs/SOURCES.md) carries that error,
and no trajectory can score an RPE against it much below that.

With ``--trajectory``, also the RPE over 10 scans (as ``bench/slam.py`` scores it) of a trajectory
that follows the scans: a pose graph (gtsam) with ICP between every scan and the three after it
(started from the reference; results more than 0.3 m or 3 degrees from it dropped; 1.5 cm and
0.15 degree, under a Cauchy kernel) and each pose held to the reference by a loose prior (0.2 m,
2 degrees), so that the shape comes from the scans and the drift from the reference. Its RPE
against the reference is how far the reference is, over 10 scans, from what the scans say (plus
ICP's own error, which ``--simulated`` shows on the simulated run against its exact truth).

With ``--global``, a trajectory from the scans alone: ICP between every scan and the three after
it and between revisits (scans at least 10 apart whose reference poses lie within 2 m and 60
degrees; at most 3 per scan), the reference only as the starting point (and a 5 m / 30 degree
prior per pose, which fixes nothing but the gauge). Its ATE against the reference, beside both
trajectories' map misfit (``bench/slam.py``): where the scans' own trajectory is as crisp as the
reference or crisper and still lies centimetres from it, the reference cannot rank trajectories
whose ATE differs by less.

    python bench/reference_check.py [--logs aces csail] [--trajectory [--simulated]]
    python bench/reference_check.py --global [--simulated]
"""

import argparse
from pathlib import Path

import numpy as np
from scipy.spatial import cKDTree

from taichi_match import compose, inverse, wrap_angle
from taichi_match.logs import read_carmen, read_tum

LOGS = Path(__file__).resolve().parents[2] / "shared" / "logs"


def points(scan, max_range=20.0):
    r, a = np.asarray(scan.ranges), np.asarray(scan.angles)
    with np.errstate(invalid="ignore"):
        ok = np.isfinite(r) & (r > 0.1) & (r < min(scan.max_range - 0.01, max_range))
    return np.column_stack([r[ok] * np.cos(a[ok]), r[ok] * np.sin(a[ok])])


def normals(p, tree):
    """Unit normals from the 6 nearest points' scatter."""
    _, idx = tree.query(p, k=6)
    out = np.empty_like(p)
    for i, neighbours in enumerate(idx):
        q = p[neighbours] - p[neighbours].mean(axis=0)
        out[i] = np.linalg.eigh(q.T @ q)[1][:, 0]
    return out


def icp(a, b, start, iterations=40):
    """Pose (x, y, theta) of b's frame in a's minimising the point-to-line distances; None if
    fewer than 20 pairs remain."""
    tree = cKDTree(a)
    n_a = normals(a, tree)
    x = np.array(start, dtype=float)
    for it in range(iterations):
        c, s = np.cos(x[2]), np.sin(x[2])
        moved = b @ np.array([[c, s], [-s, c]]) + x[:2]
        d, i = tree.query(moved)
        keep = d < max(0.3 * 0.8**it, 0.05)                   # the gate shrinks to 5 cm
        if keep.sum() < 20:
            return None
        n, rel = n_a[i[keep]], moved[keep] - x[:2]
        r = np.sum((moved[keep] - a[i[keep]]) * n, axis=1)
        jac = np.column_stack([n[:, 0], n[:, 1], -n[:, 0] * rel[:, 1] + n[:, 1] * rel[:, 0]])
        step = np.linalg.lstsq(jac, -r, rcond=None)[0]
        x += step
        if np.linalg.norm(step) < 1e-6:
            break
    return x


def check(name):
    log = read_carmen(LOGS / name / f"{name}.log.gz")
    _, ref = read_tum(LOGS / name / f"{name}.reference.tum")
    to_ref, cycles = [], []
    for k in range(0, len(log) - 2, 3):
        p = [points(log.scans[k + j]) for j in range(3)]
        truth = [compose(inverse(ref[k]), ref[k + 1]), compose(inverse(ref[k + 1]), ref[k + 2]),
                 compose(inverse(ref[k]), ref[k + 2])]
        x01, x12, x02 = icp(p[0], p[1], truth[0]), icp(p[1], p[2], truth[1]), icp(p[0], p[2], truth[2])
        if x01 is None or x12 is None or x02 is None:
            continue
        e = compose(inverse(truth[0]), x01)
        to_ref.append((np.hypot(e[0], e[1]), abs(np.degrees(wrap_angle(e[2])))))
        c = compose(inverse(x02), compose(x01, x12))
        cycles.append((np.hypot(c[0], c[1]), abs(np.degrees(wrap_angle(c[2])))))
    to_ref, cycles = np.array(to_ref), np.array(cycles)
    return len(to_ref), np.median(to_ref, axis=0), np.median(cycles, axis=0)


def revisits(ref, gap=10, radius=2.0, per_scan=3):
    """Pairs (k, j), j >= k + ``gap``, whose reference positions lie within ``radius`` metres and
    headings within 60 degrees: the scans' own loop closures, at most ``per_scan`` per k, nearest
    first."""
    from scipy.spatial import cKDTree

    tree = cKDTree(ref[:, :2])
    out = []
    for k in range(len(ref)):
        near = [j for j in tree.query_ball_point(ref[k, :2], radius) if j >= k + gap
                and abs(wrap_angle(ref[j, 2] - ref[k, 2])) <= np.radians(60.0)]
        near.sort(key=lambda j: np.hypot(*(ref[j, :2] - ref[k, :2])))
        out += [(k, j) for j in near[:per_scan]]
    return out


def scan_trajectory(log, ref, reach=3, prior_sd=(0.2, 2.0), loops=False):
    """The trajectory that follows ICP between every scan and the ``reach`` after it (and, with
    ``loops``, the ``revisits`` pairs), each pose held to ``ref`` by a prior of ``prior_sd`` (metres,
    degrees) (see the module docstring): (N, 3) poses."""
    import gtsam

    pts = [points(scan) for scan in log.scans]
    graph, values = gtsam.NonlinearFactorGraph(), gtsam.Values()
    prior = gtsam.noiseModel.Diagonal.Sigmas(np.array([prior_sd[0], prior_sd[0], np.radians(prior_sd[1])]))
    edge = gtsam.noiseModel.Robust.Create(gtsam.noiseModel.mEstimator.Cauchy.Create(2.0),
                                          gtsam.noiseModel.Diagonal.Sigmas(np.array([0.015, 0.015, np.radians(0.15)])))
    graph.add(gtsam.PriorFactorPose2(0, gtsam.Pose2(*ref[0]), gtsam.noiseModel.Diagonal.Sigmas(np.full(3, 1e-6))))
    for k, pose in enumerate(ref):
        graph.add(gtsam.PriorFactorPose2(k, gtsam.Pose2(*pose), prior))
        values.insert(k, gtsam.Pose2(*pose))
    pairs = [(k, k + d) for k in range(len(ref)) for d in range(1, reach + 1) if k + d < len(ref)]
    for k, j in pairs + (revisits(ref) if loops else []):
        if len(pts[k]) < 20 or len(pts[j]) < 20:
            continue
        start = compose(inverse(ref[k]), ref[j])
        x = icp(pts[k], pts[j], start)
        if x is None:
            continue
        e = compose(inverse(start), x)
        if np.hypot(e[0], e[1]) <= 0.3 and abs(e[2]) <= np.radians(3.0):
            graph.add(gtsam.BetweenFactorPose2(k, j, gtsam.Pose2(*x), edge))
    out = gtsam.LevenbergMarquardtOptimizer(graph, values, gtsam.LevenbergMarquardtParams()).optimize()
    return np.array([[out.atPose2(k).x(), out.atPose2(k).y(), out.atPose2(k).theta()] for k in range(len(ref))])


def global_check(log, ref):
    """(ATE m, ATE deg, map misfit cm of the ICP graph, of ``ref``): a trajectory from the scans
    alone (ICP between every scan and the three after it and between revisits, the reference only
    as the starting point and a 5 m / 30 degree prior per pose), against ``ref``."""
    from slam import map_misfit

    from taichi_match.evaluation import trajectory_errors

    poses = scan_trajectory(log, ref, prior_sd=(5.0, 30.0), loops=True)
    e = trajectory_errors(poses, ref)
    return e["ate_m"], e["ate_deg"], 100 * map_misfit(log, poses), 100 * map_misfit(log, ref)


def rpe10(poses, ref):
    """(rms m, rms deg, median m, median deg) of the relative error over 10 scans."""
    from taichi_match.evaluation import trajectory_errors

    a = np.array([compose(inverse(p), q) for p, q in zip(poses[:-10], poses[10:])])
    b = np.array([compose(inverse(p), q) for p, q in zip(ref[:-10], ref[10:])])
    e = np.array([compose(inverse(y), x) for x, y in zip(a, b)])
    rms = trajectory_errors(poses, ref)
    return rms["rpe_m"], rms["rpe_deg"], float(np.median(np.hypot(e[:, 0], e[:, 1]))), \
        float(np.degrees(np.median(np.abs(wrap_angle(e[:, 2])))))


def main():
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--logs", nargs="*")
    parser.add_argument("--trajectory", action="store_true",
                        help="also the RPE over 10 scans of a trajectory that follows the scans (ICP pose graph)")
    parser.add_argument("--global", dest="whole", action="store_true",
                        help="only the ATE of a trajectory from the scans alone (ICP graph with revisits) against "
                             "the reference, and both maps' misfit")
    parser.add_argument("--simulated", action="store_true",
                        help="with --trajectory or --global: also the simulated run")
    args = parser.parse_args()
    names = args.logs or sorted(p.name for p in LOGS.iterdir() if p.is_dir())
    if args.whole:
        print("| log | ICP graph vs reference, ATE m / deg | map misfit cm, ICP graph / reference |")
        print("|---|---|---|")
        runs = []
        if args.simulated:
            from taichi_match.simulate import simulate_log

            run = simulate_log(0)
            runs.append(("simulated (exact truth)", run.log, run.truth))
        for name in names:
            runs.append((name, read_carmen(LOGS / name / f"{name}.log.gz"),
                         read_tum(LOGS / name / f"{name}.reference.tum")[1]))
        for name, log, ref in runs:
            ate_m, ate_deg, ours, theirs = global_check(log, ref)
            print(f"| {name} | {ate_m:.3f} / {ate_deg:.2f} | {ours:.2f} / {theirs:.2f} |", flush=True)
        return
    head = ("| log | triplets | ICP vs reference, consecutive scans (median mm / deg) "
            "| ICP cycle error (median mm / deg) |")
    rule = "|---|---|---|---|"
    if args.trajectory:
        head += " scan-following trajectory vs reference, RPE10 rms m / deg (median m / deg) |"
        rule += "---|"
    print(head)
    print(rule)
    if args.trajectory and args.simulated:
        from taichi_match.simulate import simulate_log

        run = simulate_log(0)
        r = rpe10(scan_trajectory(run.log, run.truth), run.truth)
        print("| simulated (exact truth) | - | - | - "
              f"| {r[0]:.3f} / {r[1]:.2f} ({r[2]:.3f} / {r[3]:.2f}) |", flush=True)
    for name in names:
        n, to_ref, cycle = check(name)
        row = f"| {name} | {n} | {1e3 * to_ref[0]:.1f} / {to_ref[1]:.3f} | {1e3 * cycle[0]:.1f} / {cycle[1]:.3f} |"
        if args.trajectory:
            log = read_carmen(LOGS / name / f"{name}.log.gz")
            _, ref = read_tum(LOGS / name / f"{name}.reference.tum")
            r = rpe10(scan_trajectory(log, ref), ref)
            row += f" {r[0]:.3f} / {r[1]:.2f} ({r[2]:.3f} / {r[3]:.2f}) |"
        print(row, flush=True)


if __name__ == "__main__":
    main()
