"""Submaps built from real laser scans: taichi_match (default options) against OpenCV's ECC.

For every log in ``../shared/logs`` (CARMEN logs with a reference trajectory; see its SOURCES.md):

- Submaps: ``--scans`` consecutive scans each (default 20), a new one every ``--stride`` scans
  (default 10: each scan goes into two submaps, as in Cartographer's submaps), built with the
  reference poses by ``taichi_match.scans.scans_to_grid`` (0.05 m, the default hit/miss model),
  each in the frame of its middle scan. Probability grids as built, and trinary grids as ROS
  map_saver writes them (p > 0.65 occupied, p < 0.196 free).
- Pairs: consecutive submaps (i, i + 1), which share half their scans; disjoint neighbours
  (i, i + 2), which share none and overlap only where the robot's views meet; loop-closure pairs
  (j >= i + 3 with the middle scans' positions within 3 m). The truth r_A2B is the reference
  pose of B's middle scan in A's.
- Guesses per pair and grid type: "good" (translation error uniform in a 0.3 m disc, rotation in
  +-0.1 rad), "wide" (0.5 m, 0.2 rad) and "bad" (1.5 to 3 m and 20 to 40 degrees off, either sign).
- A match is correct within 0.1 m and 1 degree; along a direction the result flags as degenerate
  the translation error is judged by the covariance instead (within 3 standard deviations).

Reported per log and over all: success from good and wide guesses per pair kind; the mean NEES of
``calibrated_covariance`` over correct good and wide matches (consistent: 3, with the chi-square
95 % band of the mean for that many matches); the verdict's precision (accepted results that are
correct) and recall (correct results that are accepted) over all guesses, bad ones included; the
median time per match; ECC's success from the same good guesses. Then a check of the covariance
that does not trust the reference: ``cycle_nees`` over triplets of submaps (i, i+1, i+2).

    python bench/submaps.py                         # all logs, table to stdout
    python bench/submaps.py --out bench/SUBMAPS.md --records /tmp/submaps.jsonl
    python bench/submaps.py --logs aces csail --no-ecc
    python bench/submaps.py --protocol-table /tmp/submaps.jsonl >> bench/SUBMAPS.md   # per log, issue protocol
"""

import argparse
import datetime
import json
import os
import sys
import time
from pathlib import Path

import numpy as np
from scipy import stats

import taichi_match as tm
from taichi_match import compose, inverse, wrap_angle
from taichi_match.logs import read_carmen, read_tum
from taichi_match.scans import scans_to_grid, trinary

sys.path.insert(0, str(Path(__file__).resolve().parent))
from real_maps import ecc_match  # noqa: E402

LOGS = Path(__file__).resolve().parents[2] / "shared" / "logs"
GUESSES = {"good": (0.3, 0.1), "wide": (0.5, 0.2)}
# The reference trajectories are SLAM results, "a few centimetres and a few tenths of a degree"
# off (shared/logs/SOURCES.md). The NEES against them is printed as it is, and with this much
# relative error of the reference added to our covariance (an assumption of the evaluation, not
# fitted per run; with 1 cm it is 3.4 instead of 2.7 on the run of bench/TUNING.md).
REFERENCE_SD = (0.015, np.radians(0.1))


def build_submaps(name, scans_per_submap, stride, resolution=0.05):
    """[(middle reference pose, probability grid)] for the log ``name``."""
    folder = LOGS / name
    log = read_carmen(folder / f"{name}.log.gz")
    _, reference = read_tum(folder / f"{name}.reference.tum")
    if len(reference) != len(log):
        raise SystemExit(f"{name}: {len(log)} scans but {len(reference)} reference poses")
    out = []
    for start in range(0, len(log) - scans_per_submap + 1, stride):
        idx = range(start, start + scans_per_submap)
        middle = reference[start + scans_per_submap // 2]
        poses = np.array([compose(inverse(middle), reference[k]) for k in idx])
        out.append((middle, scans_to_grid([log.scans[k] for k in idx], poses, resolution=resolution)))
    return out


def make_pairs(submaps, stride, scans_per_submap):
    """[(i, j, kind, truth)]: consecutive, disjoint neighbours and loop closures."""
    apart = -(-scans_per_submap // stride)          # the first j whose scans do not overlap i's
    pairs = []
    for i in range(len(submaps)):
        for j in range(i + 1, len(submaps)):
            near = np.hypot(*(submaps[i][0][:2] - submaps[j][0][:2])) < 3.0
            if j == i + 1:
                kind = "consecutive"
            elif j == i + apart:
                kind = "disjoint"
            elif j >= i + 3 and j > i + apart and near:
                kind = "loop"
            else:
                continue
            pairs.append((i, j, kind, compose(inverse(submaps[i][0]), submaps[j][0])))
    return pairs


def guess(truth, rng, kind):
    if kind == "bad":
        distance, angle = rng.uniform(1.5, 3.0), np.radians(rng.uniform(20.0, 40.0)) * rng.choice([-1, 1])
    else:
        radius, angle_range = GUESSES[kind]
        distance, angle = radius * np.sqrt(rng.uniform()), rng.uniform(-angle_range, angle_range)
    direction = rng.uniform(0, 2 * np.pi)
    return truth + np.array([distance * np.cos(direction), distance * np.sin(direction), angle])


def judge(res, truth):
    """(correct, translation error m, rotation error rad, NEES or None, NEES with the reference's own
    error added (``REFERENCE_SD``) or None); None along degenerate directions."""
    err = np.array([res.pose[0] - truth[0], res.pose[1] - truth[1], wrap_angle(res.pose[2] - truth[2])])
    rot_ok = abs(err[2]) < np.radians(1.0)
    cov = res.calibrated_covariance
    if len(res.degenerate):
        # translation judged by the covariance along degenerate directions, by 0.1 m across them
        dirs = res.degenerate[:, :2]
        dirs = dirs[np.linalg.norm(dirs, axis=1) > 0.5]
        along = [float(d @ err[:2] / np.linalg.norm(d)) for d in dirs]
        sds = [float(np.sqrt(d @ cov[:2, :2] @ d / (d @ d))) for d in dirs]
        across = err[:2] - sum(a * d / np.linalg.norm(d) for a, d in zip(along, dirs)) if dirs.size else err[:2]
        trans_ok = np.hypot(*across) < 0.1 and all(abs(a) <= 3 * s for a, s in zip(along, sds))
    else:
        trans_ok = np.hypot(*err[:2]) < 0.1
    if len(res.degenerate):
        return bool(rot_ok and trans_ok), float(np.hypot(*err[:2])), float(abs(err[2])), None, None
    reference = np.diag([REFERENCE_SD[0] ** 2, REFERENCE_SD[0] ** 2, REFERENCE_SD[1] ** 2])
    nees = float(err @ np.linalg.solve(cov, err))
    nees_ref = float(err @ np.linalg.solve(cov + reference, err))
    return bool(rot_ok and trans_ok), float(np.hypot(*err[:2])), float(abs(err[2])), nees, nees_ref


def nees_band(n, dof=3):
    """The chi-square 95 % band of the mean NEES of n consistent samples."""
    return stats.chi2.ppf(0.025, dof * n) / n, stats.chi2.ppf(0.975, dof * n) / n


def summarise(records, ecc):
    """One table row's numbers from match records (dicts) and ECC records."""
    out = {}
    for kind in ("consecutive", "disjoint", "loop"):
        for guess_kind in GUESSES:
            ok = [r["correct"] for r in records if r["pair"] == kind and r["guess"] == guess_kind]
            out[kind, guess_kind] = (sum(ok), len(ok))
    for key in ("nees", "nees_ref"):
        nees = [r[key] for r in records if r["correct"] and r["guess"] in GUESSES and r[key] is not None]
        out[key] = (float(np.mean(nees)) if nees else float("nan"), len(nees))
    accepted = [r for r in records if r["accepted"]]
    correct = [r for r in records if r["correct"]]
    out["precision"] = (sum(r["correct"] for r in accepted), len(accepted))
    out["recall"] = (sum(r["accepted"] for r in correct), len(correct))
    out["ms"] = 1e3 * float(np.median([r["seconds"] for r in records])) if records else float("nan")
    out["ecc"] = (sum(e["correct"] for e in ecc), len(ecc))
    return out


def cycle_nees(records):
    """The reference-free check of the covariance: for submaps i, i+1, i+2 whose three matches from
    good guesses (two consecutive pairs and the disjoint one) are all accepted, correct and without
    a degenerate direction, the pose of i+2 in i by way of i+1 against the direct one. Their
    difference involves no reference pose; its NEES under the three calibrated covariances
    (propagated to first order, as independent) averages 3 when they are consistent.
    Returns (mean NEES, n)."""
    def loop(x):
        d = compose(inverse(x[6:]), compose(x[:3], x[3:6]))
        return np.array([d[0], d[1], wrap_angle(d[2])])

    done = {(r["log"], r["grids"], r["i"], r["j"]): r for r in records if r["guess"] == "good"}
    nees = []
    for (log, grids, i, j), first in done.items():
        legs = [first, done.get((log, grids, j, j + 1)), done.get((log, grids, i, j + 1))]
        if j != i + 1 or not all(r and r["correct"] and r["accepted"] and not r["degenerate"] for r in legs):
            continue
        x = np.concatenate([r["pose"] for r in legs])
        jac = np.empty((3, 9))
        for k in range(9):
            h = np.zeros(9)
            h[k] = 1e-6
            jac[:, k] = (loop(x + h) - loop(x - h)) / 2e-6
        cov = np.zeros((9, 9))
        for k, r in enumerate(legs):
            cov[3 * k:3 * k + 3, 3 * k:3 * k + 3] = r["calibrated"]
        d = loop(x)
        nees.append(float(d @ np.linalg.solve(jac @ cov @ jac.T, d)))
    return (float(np.mean(nees)) if nees else float("nan")), len(nees)


def pct(pair):
    k, n = pair
    return f"{100.0 * k / n:.1f} ({k}/{n})" if n else "-"


def protocol_table(path):
    """Per log and grid type, on consecutive and loop pairs only (the issue's protocol), from the
    records of a run: verdict precision and recall over all guesses, mean NEES (as it is and with
    the reference's error) over correct good and wide matches; and the reference-free
    ``cycle_nees`` of the log's triplets (which also use the disjoint pairs i, i+2)."""
    everything = [json.loads(line) for line in open(path)]
    records = [r for r in everything if r["pair"] != "disjoint"]
    keys = sorted({(r["log"], r["grids"]) for r in records}) + [("all", "both")]
    lines = ["", f"## Consecutive and loop pairs per log (the issue's protocol), from `{Path(path).name}`", "",
             "| log | grids | good, correct | precision | recall | mean NEES (band, n) | with the reference's error "
             "| cycle NEES, no reference (band, n) |",
             "|---|---|---|---|---|---|---|---|"]

    def with_band(mean, n):
        lo, hi = nees_band(n) if n else (float("nan"), float("nan"))
        return f"{mean:.2f} ({lo:.2f}-{hi:.2f}, {n})"

    for log, grids in keys:
        def mine(r):
            return log == "all" or (r["log"] == log and r["grids"] == grids)
        rows = [r for r in records if mine(r)]
        s = summarise(rows, [])
        good = [r["correct"] for r in rows if r["guess"] == "good"]
        lines.append(f"| {log} | {grids} | {pct((sum(good), len(good)))} | {pct(s['precision'])} | {pct(s['recall'])} "
                     f"| {with_band(*s['nees'])} | {s['nees_ref'][0]:.2f} "
                     f"| {with_band(*cycle_nees([r for r in everything if mine(r)]))} |")
    return "\n".join(lines)


def main():
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--logs", nargs="*", help="log names (default: all in ../shared/logs)")
    parser.add_argument("--scans", type=int, default=20, help="scans per submap")
    parser.add_argument("--stride", type=int, default=10, help="scans between the starts of two submaps")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--no-ecc", action="store_true")
    parser.add_argument("--out", help="also write the table (markdown) here")
    parser.add_argument("--records", help="write one JSON line per match here")
    parser.add_argument("--option", action="append", default=[], metavar="NAME=VALUE",
                        help="a MatchOptions field, e.g. --option unknown_cost=0")
    parser.add_argument("--protocol-table", metavar="RECORDS",
                        help="only print the per-log table of the issue's protocol from a run's records")
    args = parser.parse_args()
    if args.protocol_table:
        print(protocol_table(args.protocol_table))
        return
    if not LOGS.is_dir():
        raise SystemExit(f"{LOGS} not found: the laser logs live in ../shared/logs")
    options = {}
    for item in args.option:
        key, _, value = item.partition("=")
        try:
            options[key] = int(value) if key in ("levels", "max_iterations", "refine_iterations") else float(value)
        except ValueError:
            options[key] = value
    try:
        import cv2
        have_ecc = not args.no_ecc
    except ImportError:
        have_ecc = False
        print("OpenCV not installed: ECC skipped (pip install opencv-python-headless)")
    names = args.logs or sorted(p.name for p in LOGS.iterdir() if p.is_dir())
    matcher = tm.Matcher(**options)
    rng = np.random.default_rng(args.seed)
    all_records, all_ecc, rows = [], [], []
    started = time.perf_counter()
    record_file = open(args.records, "w") if args.records else None
    for name in names:
        submaps = build_submaps(name, args.scans, args.stride)
        grids = {"probability": [g for _, g in submaps], "trinary": [trinary(g) for _, g in submaps]}
        pairs = make_pairs(submaps, args.stride, args.scans)
        for grid_kind, gs in grids.items():
            records, ecc = [], []
            for i, j, pair_kind, truth in pairs:
                for guess_kind in ("good", "wide", "bad"):
                    r0 = guess(truth, rng, guess_kind)
                    res = matcher.match(gs[i], gs[j], r0)
                    correct, et, er, nees, nees_ref = judge(res, truth)
                    ev = res.evidence
                    records.append(dict(log=name, grids=grid_kind, pair=pair_kind, i=i, j=j, guess=guess_kind,
                                        correct=correct, accepted=res.accepted, err_m=et, err_deg=np.degrees(er),
                                        nees=nees, nees_ref=nees_ref, status=res.status.name,
                                        seconds=res.seconds,
                                        walls=ev.walls_compared, agreement=ev.wall_agreement,
                                        conflict=ev.wall_conflict, uncertainty=ev.uncertainty,
                                        degenerate=len(res.degenerate), covariance=res.covariance.tolist(),
                                        floor=res.covariance_floor.tolist(), residual=res.residual,
                                        calibrated=res.calibrated_covariance.tolist(),
                                        error=[float(res.pose[0] - truth[0]), float(res.pose[1] - truth[1]),
                                               float(wrap_angle(res.pose[2] - truth[2]))],
                                        pose=res.pose.tolist()))
                    if have_ecc and guess_kind == "good":
                        pose, sec = ecc_match(gs[i], gs[j], r0)
                        ok = bool(np.all(np.isfinite(pose)) and np.hypot(*(pose[:2] - truth[:2])) < 0.1
                                  and abs(wrap_angle(pose[2] - truth[2])) < np.radians(1.0))
                        ecc.append(dict(log=name, grids=grid_kind, pair=pair_kind, correct=ok, seconds=sec))
            if record_file:
                for r in records:
                    record_file.write(json.dumps(r) + "\n")
                record_file.flush()
            rows.append((name, grid_kind, summarise(records, ecc)))
            all_records += records
            all_ecc += ecc
            print(name, grid_kind, rows[-1][2], flush=True)
    for grid_kind in ("probability", "trinary"):
        rows.append(("all", grid_kind, summarise([r for r in all_records if r["grids"] == grid_kind],
                                                 [e for e in all_ecc if e["grids"] == grid_kind])))
    rows.append(("all", "both", summarise(all_records, all_ecc)))
    rows.append(("all, consecutive + loop", "both", summarise([r for r in all_records if r["pair"] != "disjoint"],
                                                              [e for e in all_ecc if e["pair"] != "disjoint"])))
    if record_file:
        record_file.close()
    from taichi_match.reproduce import git_revision

    ecc_note = f"OpenCV {cv2.__version__} ECC" if have_ecc else "ECC not run"
    text = ["# Laser-built submaps", "",
            f"`python bench/submaps.py {' '.join(sys.argv[1:])}` at revision {git_revision()}, "
            f"{datetime.date.today()}, {os.cpu_count()}-core machine, {ecc_note}; options: "
            f"{args.option or 'defaults'}; submaps of {args.scans} scans every {args.stride} scans, seed {args.seed}; "
            f"{time.perf_counter() - started:.0f} s. Protocol: the docstring of bench/submaps.py.", "",
            "Success (%) from good (0.3 m / 0.1 rad) and wide (0.5 m / 0.2 rad) guesses; NEES of "
            "`calibrated_covariance` over the correct good and wide matches (band: chi-square 95 % of the "
            "mean), as it is and with the reference trajectory's own error added (1.5 cm, 0.1 deg: "
            "REFERENCE_SD in bench/submaps.py); verdict precision and recall over good, wide and bad "
            "(1.5-3 m, 20-40 deg) guesses; "
            "'all, consecutive + loop' is the issue's protocol (disjoint neighbours left out).", "",
            "| log | grids | consecutive, good | consecutive, wide | loop, good | loop, wide | disjoint, good "
            "| disjoint, wide | mean NEES (band, n) | with the reference's error | precision | recall | median ms "
            "| ECC, good |",
            "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for name, grid_kind, s in rows:
        mean, n = s["nees"]
        lo, hi = nees_band(n) if n else (float("nan"), float("nan"))
        cells = " | ".join(pct(s[kind, g]) for kind, g in (("consecutive", "good"), ("consecutive", "wide"),
                                                            ("loop", "good"), ("loop", "wide"), ("disjoint", "good"),
                                                            ("disjoint", "wide")))
        text.append(f"| {name} | {grid_kind} | {cells} | {mean:.2f} ({lo:.2f}-{hi:.2f}, {n}) | {s['nees_ref'][0]:.2f} "
                    f"| {pct(s['precision'])} "
                    f"| {pct(s['recall'])} | {s['ms']:.1f} | {pct(s['ecc'])} |")
    mean, n = cycle_nees(all_records)
    lo, hi = nees_band(n) if n else (float("nan"), float("nan"))
    text += ["", f"Reference-free check of the covariance (``cycle_nees``: submaps i, i+1, i+2, the pose of i+2 in i "
                 f"by way of i+1 against the direct match, good guesses, all three accepted and correct): mean NEES "
                 f"{mean:.2f} over {n} triplets (band {lo:.2f}-{hi:.2f})."]
    print()
    print("\n".join(text))
    if args.records:
        text.append(protocol_table(args.records))
        print(text[-1])
    if args.out:
        Path(args.out).write_text("\n".join(text) + "\n")


if __name__ == "__main__":
    main()
