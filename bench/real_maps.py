"""Real-map evaluation: taichi_match against OpenCV's ECC on pairs cut from robot-built maps.

From each map in ``../shared/maps`` (ROS map_server files; see its SOURCES.md) the script cuts
overlapping pairs with a known relative pose:

- A: an axis-aligned square crop of the map (its frame is the map's frame);
- B: a smaller square resampled from the map (nearest cell) at a random rotation and offset
  inside A, in B's own frame centred on the crop; then a fraction of its known cells is flipped
  (p -> 1 - p) and another turned unknown. The truth r_A2B is the crop's centre and rotation.

Each pair is matched from initial guesses perturbed by up to 0.5 m in x and y and 0.2 rad in theta.
Success: translation error below two cells and rotation error below one degree. The same pairs
and initial guesses go through ``cv2.findTransformECC`` (Euclidean motion, masked to B's known
cells, the peer a Python user would otherwise use) in the same run. OpenCV is optional and only
needed here: ``pip install opencv-python-headless``.

Beyond success: the mean NEES of ``calibrated_covariance`` over the correct matches (consistent:
3; the chi-square 95 % band of the mean is printed), and the verdict (``accepted``): its
precision (accepted results that are correct) and recall (correct results that are accepted)
over these guesses and as many bad ones (1.5 to 3 m and 20 to 40 degrees off).

    python bench/real_maps.py                        # 8 pairs x 3 guesses per map
    python bench/real_maps.py --pairs 20 --guesses 5 --seed 1
    python bench/real_maps.py --out bench/REAL_MAPS.md                      # also write the table
    python bench/real_maps.py --no-ecc --option interpolation=bilinear --out bench/REAL_MAPS.md --append
"""

import argparse
import datetime
import os
import sys
import time
from pathlib import Path

import numpy as np

import taichi_match as tm
from taichi_match import io
from taichi_match.merge import sample

MAPS = Path(__file__).resolve().parents[2] / "shared" / "maps"
# Documented quirks (SOURCES.md): willow_2010's walls are anti-aliased grey, so its occupied
# threshold is lowered to read them as walls.
OVERRIDES = {"willow_2010": {"occupied_thresh": 0.25}}


def load_maps():
    out = {}
    for folder in sorted(p for p in MAPS.iterdir() if p.is_dir()):
        yaml = next(folder.glob("*.yaml"))
        out[folder.name] = io.read_ros_map(yaml, **OVERRIDES.get(folder.name, {}))
    return out


def crop(grid, centre, size):
    """Axis-aligned square crop of ``size`` metres around ``centre`` (map frame), same cells."""
    res = grid.resolution
    n = int(round(size / res))
    j0 = int(np.floor((centre[0] - grid.origin[0]) / res)) - n // 2
    i0 = int(np.floor((centre[1] - grid.origin[1]) / res)) - n // 2
    rows, cols = grid.shape
    prob = np.full((n, n), np.nan)
    ri, rj = slice(max(i0, 0), min(i0 + n, rows)), slice(max(j0, 0), min(j0 + n, cols))
    prob[ri.start - i0:ri.stop - i0, rj.start - j0:rj.stop - j0] = grid.prob[ri, rj]
    return tm.GridMap(prob, res, (grid.origin[0] + j0 * res, grid.origin[1] + i0 * res))


def resampled(grid, pose, size, rng, flip, drop):
    """B: ``size`` metres square in its own frame (centred), placed in the map by ``pose``."""
    res = grid.resolution
    n = int(round(size / res))
    local = tm.GridMap(np.zeros((n, n)), res, (-n * res / 2, -n * res / 2))
    prob = sample(grid, tm.transform_points(pose, local.cell_centres())).reshape(n, n)
    known = np.flatnonzero(~np.isnan(prob))
    picks = rng.permutation(known)
    n_flip, n_drop = int(flip * known.size), int(drop * known.size)
    flat = prob.reshape(-1)
    flat[picks[:n_flip]] = 1.0 - flat[picks[:n_flip]]
    flat[picks[n_flip:n_flip + n_drop]] = np.nan
    return local.with_prob(prob)


def make_pairs(grid, count, rng, *, size_a=16.0, size_b=10.0, min_known=0.35, flip=0.002, drop=0.05):
    pairs = []
    x0, x1, y0, y1 = grid.extent
    attempts = 0
    while len(pairs) < count and attempts < 2000:
        attempts += 1
        centre = rng.uniform([x0 + size_a / 2, y0 + size_a / 2], [x1 - size_a / 2, y1 - size_a / 2])
        a = crop(grid, centre, size_a)
        occupied = np.nan_to_num(a.prob) > 0.5
        if a.known.mean() < min_known or occupied.mean() < 0.01:
            continue
        offset = rng.uniform(-1.5, 1.5, 2)
        truth = np.array([centre[0] + offset[0], centre[1] + offset[1], rng.uniform(-np.pi, np.pi)])
        b = resampled(grid, truth, size_b, rng, flip, drop)
        if b.known.mean() < min_known:
            continue
        pairs.append((a, b, truth))
    return pairs


def ecc_match(a, b, r0):
    """cv2.findTransformECC (Euclidean), template A, input B masked to B's known cells."""
    import cv2

    res = a.resolution
    img_a = np.nan_to_num(a.prob, nan=0.5).astype(np.float32)
    img_b = np.nan_to_num(b.prob, nan=0.5).astype(np.float32)
    mask_b = b.known.astype(np.uint8)
    oa, ob = np.array(a.origin), np.array(b.origin)

    # pixel (col, row) of A -> pixel of B:  pix_b = R^T pix_a + c  (both grids share the resolution)
    def warp_from_pose(pose):
        c, s = np.cos(pose[2]), np.sin(pose[2])
        rt = np.array([[c, s], [-s, c]])
        shift = rt @ (0.5 * res + oa - pose[:2]) / res - ob / res - 0.5
        return np.hstack([rt, shift[:, None]]).astype(np.float32)

    def pose_from_warp(w):
        theta = np.arctan2(w[0, 1], w[0, 0])
        c, s = np.cos(theta), np.sin(theta)
        r = np.array([[c, -s], [s, c]])
        t = 0.5 * res + oa - r @ (res * (w[:, 2] + 0.5) + ob)
        return np.array([t[0], t[1], theta])

    criteria = (cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, 200, 1e-6)
    start = time.perf_counter()
    try:
        _, w = cv2.findTransformECC(img_a, img_b, warp_from_pose(np.asarray(r0, float)), cv2.MOTION_EUCLIDEAN,
                                    criteria, mask_b, 5)
        pose = pose_from_warp(w)
    except cv2.error:
        pose = np.full(3, np.nan)
    return pose, time.perf_counter() - start


def errors(pose, truth):
    d = pose[:2] - truth[:2]
    dt = (pose[2] - truth[2] + np.pi) % (2 * np.pi) - np.pi
    return float(np.hypot(*d)), float(abs(dt))


def main():
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--pairs", type=int, default=8, help="pairs per map")
    parser.add_argument("--guesses", type=int, default=3, help="initial guesses per pair")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--no-ecc", action="store_true", help="skip OpenCV")
    parser.add_argument("--option", action="append", default=[], metavar="NAME=VALUE",
                        help="a MatchOptions field for taichi_match, e.g. --option prior_weight=30")
    parser.add_argument("--out", help="also write the table (markdown) to this file")
    parser.add_argument("--append", action="store_true", help="append to --out instead of replacing it")
    parser.add_argument("--records", help="write one JSON line per match from a good guess here (for "
                                          "bench/calibrate_covariance.py)")
    args = parser.parse_args()
    options = {}
    for item in args.option:
        key, _, value = item.partition("=")
        if key in ("blur_kind", "optimizer", "interpolation", "engine"):
            options[key] = value
        else:
            options[key] = int(value) if key in ("levels", "max_iterations", "refine_iterations") else float(value)
    if not MAPS.is_dir():
        raise SystemExit(f"{MAPS} not found: the real maps live in ../shared/maps")
    try:
        import cv2  # noqa: F401
        have_cv2 = not args.no_ecc
    except ImportError:
        have_cv2 = False
        print("OpenCV not installed: ECC skipped (pip install opencv-python-headless)")
    rng = np.random.default_rng(args.seed)
    matcher = tm.Matcher(**options)
    rows, totals = [], {"ours": [], "ecc": []}
    verdicts, nees_all, records = [], [], []
    bad_rng = np.random.default_rng(args.seed + 1000)
    for name, grid in load_maps().items():
        stats = {"ours": [], "ecc": []}
        for a, b, truth in make_pairs(grid, args.pairs, rng):
            for _ in range(args.guesses):
                r0 = truth + np.concatenate([rng.uniform(-0.5, 0.5, 2), rng.uniform(-0.2, 0.2, 1)])
                res = matcher.match(a, b, r0)
                stats["ours"].append((*errors(res.pose, truth), res.seconds))
                e_t, e_r = errors(res.pose, truth)
                ok = e_t < 2 * grid.resolution and e_r < np.radians(1.0)
                verdicts.append((ok, res.accepted))
                error = [float(res.pose[0] - truth[0]), float(res.pose[1] - truth[1]),
                         float((res.pose[2] - truth[2] + np.pi) % (2 * np.pi) - np.pi)]
                records.append(dict(map=name, correct=bool(ok), accepted=bool(res.accepted), error=error,
                                    degenerate=len(res.degenerate), covariance=res.covariance.tolist(),
                                    floor=res.covariance_floor.tolist(), residual=res.residual))
                if ok and not len(res.degenerate):
                    err = np.array([res.pose[0] - truth[0], res.pose[1] - truth[1],
                                    (res.pose[2] - truth[2] + np.pi) % (2 * np.pi) - np.pi])
                    nees_all.append(float(err @ np.linalg.solve(res.calibrated_covariance, err)))
                # bad guesses from their own generator: the pairs and good guesses stay those of a run
                # without them
                phi = bad_rng.uniform(0, 2 * np.pi)
                bad = truth + np.concatenate([bad_rng.uniform(1.5, 3.0) * np.array([np.cos(phi), np.sin(phi)]),
                                              [np.radians(bad_rng.uniform(20, 40)) * bad_rng.choice([-1, 1])]])
                res_bad = matcher.match(a, b, bad)
                e_t, e_r = errors(res_bad.pose, truth)
                verdicts.append((e_t < 2 * grid.resolution and e_r < np.radians(1.0), res_bad.accepted))
                if have_cv2:
                    pose, sec = ecc_match(a, b, r0)
                    stats["ecc"].append((*errors(pose, truth), sec) if np.all(np.isfinite(pose))
                                        else (np.inf, np.inf, sec))
        cell = grid.resolution
        line = [name, f"{cell:g}", str(len(stats["ours"]))]
        for who in ("ours", "ecc"):
            s = np.array(stats[who]) if stats[who] else np.zeros((0, 3))
            totals[who] += [(e_t < 2 * cell) and (e_r < np.radians(1.0)) for e_t, e_r, _ in s]
            if len(s):
                ok = (s[:, 0] < 2 * cell) & (s[:, 1] < np.radians(1.0))
                fin = np.isfinite(s[:, 0])
                line += [f"{100 * ok.mean():.0f}", f"{100 * np.median(s[fin, 0]) if fin.any() else np.nan:.1f}",
                         f"{np.degrees(np.median(s[fin, 1])) if fin.any() else np.nan:.2f}",
                         f"{1e3 * np.median(s[:, 2]):.1f}"]
            else:
                line += ["-"] * 4
        rows.append(line)
        print(" | ".join(line), flush=True)
    from taichi_match.reproduce import git_revision

    ecc = f"OpenCV {cv2.__version__}" if have_cv2 else "ECC not run"
    text = [f"## taichi_match options: {args.option or 'defaults'}", "",
            f"`python bench/real_maps.py {' '.join(sys.argv[1:])}` at revision {git_revision()}, "
            f"{datetime.date.today()}, {os.cpu_count()}-core machine, {ecc}: {args.pairs} pairs x {args.guesses} "
            f"initial guesses per map, seed {args.seed}; success = error below 2 cells and 1 degree.", "",
            "| map | cell m | matches | ours success % | ours median err cm | ours median err deg | ours median ms "
            "| ECC success % | ECC median err cm | ECC median err deg | ECC median ms |",
            "|---|---|---|---|---|---|---|---|---|---|---|"]
    text += ["| " + " | ".join(line) + " |" for line in rows]
    text.append("")
    for who in ("ours", "ecc"):
        if totals[who]:
            text.append(f"{who}: {100 * np.mean(totals[who]):.1f} % success over {len(totals[who])} matches  ")
    from scipy import stats as sps

    n = len(nees_all)
    if n:
        lo, hi = sps.chi2.ppf(0.025, 3 * n) / n, sps.chi2.ppf(0.975, 3 * n) / n
        text.append(f"ours: mean NEES of calibrated_covariance {np.mean(nees_all):.2f} over {n} correct matches "
                    f"(band {lo:.2f}-{hi:.2f}); median {np.median(nees_all):.2f}  ")
    accepted = [ok for ok, acc in verdicts if acc]
    correct = [acc for ok, acc in verdicts if ok]
    text.append(f"ours: verdict precision {100 * np.mean(accepted) if accepted else float('nan'):.1f} % "
                f"({sum(accepted)}/{len(accepted)} accepted are correct), recall "
                f"{100 * np.mean(correct) if correct else float('nan'):.1f} % ({sum(correct)}/{len(correct)} correct "
                f"are accepted), over {len(verdicts)} matches with as many bad guesses (1.5-3 m, 20-40 deg)  ")
    print()
    print("\n".join(text))
    if args.records:
        import json

        with open(args.records, "w") as f:
            for r in records:
                f.write(json.dumps(r) + "\n")
    if args.out:
        out = Path(args.out)
        head = "" if args.append and out.exists() else ("# Real-map evaluation\n\nSee the docstring of "
                                                        "bench/real_maps.py for the protocol.\n\n")
        with out.open("a" if args.append else "w") as f:
            f.write(head + "\n".join(text) + "\n\n")


if __name__ == "__main__":
    main()
