"""Align the cross-run map pairs of ../shared/maps and draw them (the README's real-map pictures).

The pairs are two maps of the same building from different runs, without a ground-truth pose.
``taichi_match.match`` without a guess searches every pose where the maps overlap, refines the
best, and lists the distinct runner-ups; this script prints them and writes
``docs/cross_run/<pair>.png`` (the maps overlaid at the search's pose and at the matched one) and,
for an accepted match, ``docs/cross_run/<pair>_merged.png`` (A, B and B merged into A's frame).

    python examples/cross_run_pairs.py [--maps ../shared/maps] [--out docs/cross_run]
"""

import argparse
import os
from pathlib import Path

import taichi_match as tm
from taichi_match import io, plots
from taichi_match.merge import merge_maps

# (A, overrides, B, overrides): quirks from the maps' SOURCES.md
PAIRS = (
    ("gdc_3", {}, "gdc_3ne", {}),
    ("avz5floor_open", {}, "avz5floor_closed", {}),
    ("willow_full", {}, "willow_2010", {"occupied_thresh": 0.25}),        # anti-aliased grey walls
    ("intel_gondsm", {}, "intel_bwi", {"resolution": 0.05}),              # same pixel scale as gondsm
)


def load_path(folder, name):
    found = sorted((Path(folder) / name).glob("*.yaml"))
    if not found:
        raise SystemExit(f"no map {name!r} under {folder}: this example needs the project's shared robot maps "
                         f"(shared/maps beside the repository; their origin and licences in its SOURCES.md), "
                         f"or --maps FOLDER")
    return found[0]


def load(folder, name, overrides):
    return io.read_ros_map(load_path(folder, name), **overrides)


def main():
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--maps", default=str(Path(__file__).resolve().parents[2] / "shared" / "maps"))
    parser.add_argument("--out", default=str(Path(__file__).resolve().parents[1] / "docs" / "cross_run"))
    args = parser.parse_args()
    for name_a, _, name_b, _ in PAIRS:                 # every map there before any work
        for name in (name_a, name_b):
            load_path(args.maps, name)
    os.makedirs(args.out, exist_ok=True)
    print("| pair | searched (x, y, theta) | matched pose | accepted | runner-up / best | seconds |")
    print("|---|---|---|---|---|---|")
    for name_a, over_a, name_b, over_b in PAIRS:
        a, b = load(args.maps, name_a, over_a), load(args.maps, name_b, over_b)
        res = tm.match(a, b)
        name = f"{name_a}__{name_b}"
        plots.save_overlay(os.path.join(args.out, name + ".png"), a, b, res.initial_pose, res,
                           title=f"A = {name_a}, B = {name_b}")
        if res.accepted:
            plots.save_merge(os.path.join(args.out, name + "_merged.png"), a, b, merge_maps(a, b, res.pose),
                             title=f"{name_b} merged into {name_a}")
        g = ", ".join(f"{v:.2f}" for v in res.initial_pose)
        p = ", ".join(f"{v:.3f}" for v in res.pose)
        ratio = f"{res.hypotheses[1].score / res.hypotheses[0].score:.2f}" if len(res.hypotheses) > 1 else "-"
        print(f"| {name_a} / {name_b} | {g} | {p} | {res.accepted} | {ratio} | {res.seconds:.1f} |", flush=True)


if __name__ == "__main__":
    main()
