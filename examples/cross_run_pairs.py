"""Align the cross-run map pairs of ../shared/maps and draw them (the README's real-map pictures).

The pairs are two maps of the same building from different runs, without a ground-truth pose.
taichi_match is a local method: it needs a rough initial guess. This script makes one with a
brute-force search on coarse copies of the maps (cells of 0.4 m; every 3 degrees; translations
every 0.4 m; the score is the discrepancy per compared cell, with at least a third of B's known
cells compared), evaluated by the same batched kernel, then refines it with ``taichi_match.match``
at full resolution and writes ``docs/cross_run/<pair>.png``.

    python examples/cross_run_pairs.py [--out docs/cross_run]
"""

import argparse
import os
import time
from pathlib import Path

import numpy as np

import taichi_match as tm
from taichi_match import io, plots
from taichi_match._prepared import PreparedMap, make_engine

MAPS = Path(__file__).resolve().parents[2] / "shared" / "maps"
# (A, overrides, B, overrides): quirks from SOURCES.md
PAIRS = (
    ("gdc_3", {}, "gdc_3ne", {}),
    ("avz5floor_open", {}, "avz5floor_closed", {}),
    ("willow_full", {}, "willow_2010", {"occupied_thresh": 0.25}),        # anti-aliased grey walls
    ("intel_gondsm", {}, "intel_bwi", {"resolution": 0.05}),              # same pixel scale as gondsm
)


def load(name, overrides):
    return io.read_ros_map(next((MAPS / name).glob("*.yaml")), **overrides)


def coarse(grid, cell=0.4):
    """Block mean of the known cells (unknown where a block has none)."""
    k = max(1, int(round(cell / grid.resolution)))
    rows, cols = (s // k * k for s in grid.shape)
    p = grid.prob[:rows, :cols].reshape(rows // k, k, cols // k, k)
    known = (~np.isnan(p)).sum(axis=(1, 3))
    total = np.nansum(p, axis=(1, 3))
    prob = np.where(known > 0, total / np.maximum(known, 1), np.nan)
    return tm.GridMap(prob, grid.resolution * k, grid.corner_pose)


def rough_guess(a, b, *, angle_step=3.0, cell=0.4):
    ca, cb = coarse(a, cell), coarse(b, cell)
    engine = make_engine("taichi", PreparedMap(ca, 0.0), PreparedMap(cb, 0.0))
    need = cb.known.sum() / 3
    x0, x1, y0, y1 = ca.extent
    bx = cb.cell_centres()[cb.known].mean(axis=0)                 # B's centre of known cells, B frame
    best = (np.inf, None)
    for theta in np.radians(np.arange(0.0, 360.0, angle_step)):
        c, s = np.cos(theta), np.sin(theta)
        centre = np.array([c * bx[0] - s * bx[1], s * bx[0] + c * bx[1]])
        xs = np.arange(x0, x1, cell) - centre[0]
        ys = np.arange(y0, y1, cell) - centre[1]
        gx, gy = np.meshgrid(xs, ys)
        poses = np.column_stack([gx.ravel(), gy.ravel(), np.full(gx.size, theta)])
        e, n = engine(poses)
        score = np.where(n >= need, e / np.maximum(n, 1), np.inf)
        k = int(np.argmin(score))
        if score[k] < best[0]:
            best = (score[k], poses[k])
    return best[1]


def main():
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--out", default=str(Path(__file__).resolve().parents[1] / "docs" / "cross_run"))
    args = parser.parse_args()
    os.makedirs(args.out, exist_ok=True)
    print("| pair | rough guess (x, y, theta) | matched pose | status | overlap | search s | match ms |")
    print("|---|---|---|---|---|---|---|")
    for name_a, over_a, name_b, over_b in PAIRS:
        a, b = load(name_a, over_a), load(name_b, over_b)
        t0 = time.perf_counter()
        guess = rough_guess(a, b)
        search = time.perf_counter() - t0
        res = tm.match(a, b, guess)
        name = f"{name_a}__{name_b}"
        plots.save_overlay(os.path.join(args.out, name + ".png"), a, b, guess, res, title=f"A = {name_a}, B = {name_b}")
        g = ", ".join(f"{v:.2f}" for v in guess)
        p = ", ".join(f"{v:.3f}" for v in res.pose)
        print(f"| {name_a} / {name_b} | {g} | {p} | {res.status.name} | {res.overlap} | {search:.1f} "
              f"| {1e3 * res.seconds:.0f} |", flush=True)


if __name__ == "__main__":
    main()
