"""Regenerate every table and figure of the paper, and the covariance check, into a folder.

``reproduce(out_dir)`` writes ``report.md``, ``results.json``, ``config.json`` and ``figures/*.png``.
The command line's ``taichi-match reproduce --out DIR`` calls it with a progress bar.
"""

import dataclasses
import datetime
import json
import os
import platform
import subprocess
import time

import numpy as np

from . import plots
from ._matcher import Matcher
from ._options import MatchOptions
from ._prepared import PreparedMap
from .experiments import TABLES, covariance_check, run_row, surface
from .scenes import corridor

__all__ = ["reproduce", "git_revision", "COVARIANCE_NOISE"]

COVARIANCE_NOISE = ({"flip": 0.002, "drop": 0.1}, {"flip": 0.0, "drop": 0.0})


def git_revision():
    """The short git revision of the source tree, ``-dirty`` if the package has uncommitted changes."""
    here = os.path.dirname(os.path.abspath(__file__))
    try:
        rev = subprocess.run(["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True, cwd=here,
                             timeout=10).stdout.strip()
        dirty = subprocess.run(["git", "status", "--porcelain", "--untracked-files=no", "--", "."],
                               capture_output=True, text=True, cwd=here, timeout=10).stdout.strip()
    except (OSError, subprocess.SubprocessError):
        return "unknown"
    return (rev + ("-dirty" if dirty else "")) if rev else "unknown"


def _progress(callback, total):
    done = [0]

    def step(n=1):
        done[0] += n
        if callback is not None:
            callback(done[0], total)
    return step


def reproduce(out_dir, *, trials=100, covariance_trials=300, seed=0, surface_step=0.2, progress=None,
              options=None):
    """Run Tables 1-2, Figs. 2-9 and the covariance check; write them under ``out_dir``.

    ``progress(done, total)`` is called after each match. Returns the results as a dict. The
    options default to the paper's (``MatchOptions.paper()``): this reproduces the paper's method.
    """
    start = time.perf_counter()
    figures = os.path.join(out_dir, "figures")
    os.makedirs(figures, exist_ok=True)
    matcher = Matcher(options if options is not None else MatchOptions.paper())
    opts = matcher.options
    grid = corridor()
    total = trials * len(TABLES) + covariance_trials * len(COVARIANCE_NOISE)
    step = _progress(progress, total)

    rows = [run_row(matcher, grid, row, trials=trials, seed=seed + k, progress=step) for k, row in enumerate(TABLES)]
    checks = [covariance_check(matcher, grid, trials=covariance_trials, seed=seed + 10 + k, progress=step, **noise)
              for k, noise in enumerate(COVARIANCE_NOISE)]

    # Figs. 2-5: surfaces over x, y in (-12, 12) at theta = 0, one launch per row of poses
    raw = PreparedMap(grid, 0.0)
    blurred = matcher.prepare(grid)
    xs = np.arange(-12.0, 12.0 + 1e-9, surface_step)
    weight = opts.weight(blurred.n_known)
    surfaces = {
        "fig2_discrepancy_raw": (surface(raw, raw, xs, xs), "e on the raw maps (Fig. 2)", "e"),
        "fig4_discrepancy_blurred": (surface(blurred, blurred, xs, xs, unknown_cost=opts.unknown_cost),
                                     "e on the blurred maps (Fig. 4)", "e"),
        "fig5_cost": (surface(blurred, blurred, xs, xs, unknown_cost=opts.unknown_cost,
                              prior=(np.zeros(3), weight, opts.rotation_scale)),
                      f"h = e + K ||r - r0||, r0 = 0, K = {weight:.0f} (Fig. 5)", "h"),
    }
    for name, (z, title, zlabel) in surfaces.items():
        plots.save_surface(os.path.join(figures, name + ".png"), xs, xs, z, title=title, zlabel=zlabel)
    plots.save_maps(os.path.join(figures, "fig3_maps.png"), grid, blurred.blurred,
                    title=f"the corridor, raw and blurred ({opts.blur_kind}, {opts.blur:g} m) (Fig. 3)")

    # Figs. 6-9: a matching case, a poorer but feasible one, and two parallel-corridor cases
    t1, t2 = rows[1], rows[2]
    worst_t1 = int(np.argmax(np.abs(t1.final[:, 1]) / 0.025 + np.abs(t1.final[:, 2]) / 0.045))
    t2_err = np.abs(t2.final[:, 1] - t2.row.target_y) / 0.025 + np.abs(t2.final[:, 2]) / 0.045
    t2_good = int(np.argmin(t2_err))
    overlap = np.array([r.overlap for r in t2.results])
    feasible = np.flatnonzero(overlap > 0)
    t2_poor = int(feasible[np.argsort(t2_err[feasible])[len(feasible) * 9 // 10]]) if len(feasible) else t2_good
    cases = {
        "fig6_matching": (t1, 0, "matching case (Fig. 6)"),
        "fig7_poorer_feasible": (t1, worst_t1, "the least accurate trial of Table 1, second row (Fig. 7)"),
        "fig8_parallel": (t2, t2_good, "parallel corridors (Fig. 8)"),
        "fig9_parallel_poorer": (t2, t2_poor, "parallel corridors, poorer alignment: 90th percentile (Fig. 9)"),
    }
    for name, (row, k, title) in cases.items():
        plots.save_overlay(os.path.join(figures, name + ".png"), grid, grid, row.initial[k], row.results[k],
                           title=title)

    config = {"options": dataclasses.asdict(opts), "trials": trials, "covariance_trials": covariance_trials,
              "seed": seed, "surface_step": surface_step, "scene": "corridor() defaults: 12 m, 0.025 m, 6 m wide",
              "prior_weight": weight, "revision": git_revision(),
              "date": datetime.datetime.now().isoformat(timespec="seconds"),
              "machine": f"{platform.machine()}, {os.cpu_count()} cores, Python {platform.python_version()}"}
    results = {
        "tables": [{"table": r.row.table, "noise": r.row.label, "bands": r.row.bands, "ours": r.rates,
                    "paper": r.row.paper, "mean_iterations": r.mean_iterations, "mean_seconds": r.mean_seconds,
                    "median_seconds": r.median_seconds, "paper_iterations": r.row.paper_iterations,
                    "paper_seconds": r.row.paper_seconds} for r in rows],
        "covariance_checks": [{"noise": c.noise, "trials": c.trials, "scale": c.scale, "nees_mean": c.nees_mean,
                               "nees_band": c.nees_band, "consistent": c.consistent, "mean_error": c.mean_error,
                               "scatter": c.scatter, "predicted": c.predicted} for c in checks],
        "figures": sorted(f for f in os.listdir(figures) if f.endswith(".png")),
        "seconds": time.perf_counter() - start,
    }
    with open(os.path.join(out_dir, "config.json"), "w") as f:
        json.dump(config, f, indent=2, default=_jsonable)
    with open(os.path.join(out_dir, "results.json"), "w") as f:
        json.dump(results, f, indent=2, default=_jsonable)
    with open(os.path.join(out_dir, "report.md"), "w") as f:
        f.write(_report(rows, checks, config, results))
    return {"rows": rows, "checks": checks, "config": config, "results": results}


def _jsonable(value):
    if isinstance(value, np.ndarray):
        return value.tolist()
    if isinstance(value, (np.floating, np.integer, np.bool_)):
        return value.item()
    raise TypeError(f"not JSON serialisable: {type(value).__name__}")


def _report(rows, checks, config, results):
    o = config["options"]
    lines = [
        "# The paper, reproduced",
        "",
        f"Generated by `taichi-match reproduce` at revision {config['revision']} on {config['date']} "
        f"({config['machine']}), {config['trials']} trials per row, seed {config['seed']}, in "
        f"{results['seconds']:.0f} s. Settings: blur {o['blur_kind']} {o['blur']:g} m, "
        f"K = {config['prior_weight']:.0f}, L = {o['rotation_scale']:g} m/rad (all in `config.json`).",
        "",
        "## Tables 1 and 2",
        "",
        "Success: the percentage of trials whose final |y - target| and |theta| fall within a band. As in the",
        "paper, Table 1's second band counts only the trials outside the first; Table 2's bands are cumulative.",
        "Table 2's target is y = 6.05 m: B's lower wall on A's upper wall (a 6 m corridor, 5 cm walls).",
        "",
        "| table | initial-pose noise (m, rad) | bands (abs y - target, abs theta) | ours % | paper % "
        "| iterations ours / paper | time per match ours / paper |",
        "|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        bands = ", ".join(f"< {by:g}, < {bt:g}" for by, bt in r.row.bands)
        lines.append(f"| {r.row.table} | {r.row.label} | {bands} | {' / '.join(f'{v:.0f}' for v in r.rates)} "
                     f"| {' / '.join(str(v) for v in r.row.paper)} | {r.mean_iterations:.1f} "
                     f"/ {r.row.paper_iterations} | {1e3 * r.mean_seconds:.1f} ms / {r.row.paper_seconds:g} s |")
    lines += ["", "## Figures", ""]
    captions = {
        "fig2_discrepancy_raw.png": "Fig. 2: e on the raw maps over x, y in (-12, 12), theta = 0: the flat valley at "
                                    "y = 0 and two prisms with sharp edges.",
        "fig3_maps.png": "Fig. 3: the map and its blurred version.",
        "fig4_discrepancy_blurred.png": "Fig. 4: e on the blurred maps: the same shape, smoothed.",
        "fig5_cost.png": "Fig. 5: the cost h with the prior around r0 = 0: a bowl.",
        "fig6_matching.png": "Fig. 6: a matching case; the 95 % covariance ellipse (cyan) is long along the corridor.",
        "fig7_poorer_feasible.png": "Fig. 7: the least accurate trial of Table 1: feasible, poorer alignment.",
        "fig8_parallel.png": "Fig. 8: parallel corridors: B pushed out of A's free space to share a wall.",
        "fig9_parallel_poorer.png": "Fig. 9: parallel corridors with a poorer (90th percentile) alignment.",
    }
    for name in results["figures"]:
        lines += [f"![{name}](figures/{name})", "", captions.get(name, name), ""]
    lines += ["## Covariance check (beyond the paper)", "",
              "B is a noisy copy of A (a fraction of its known cells flipped p -> 1 - p, another fraction turned",
              "unknown), matched from initial poses in +-0.5 (m, rad). On the informative axes (y, theta) the",
              "first half of the trials calibrates the scale s of cov = s H(e)^-1 (mean NEES = 2), the second",
              "half tests it against the chi-square 95 % band of the mean NEES (the library's calibrated",
              "covariance for its default options is fitted on real data: bench/calibrate_covariance.py).", "",
              "| flip | drop | trials | scale s | mean NEES (test half) | 95 % band | consistent | scatter sd y, theta "
              "| predicted sd y, theta | mean error y, theta |",
              "|---|---|---|---|---|---|---|---|---|---|"]
    for c in checks:
        sd = np.sqrt(np.diag(c.scatter))
        pd = np.sqrt(np.diag(c.predicted))
        lines.append(f"| {c.noise['flip']:.1%} | {c.noise['drop']:.0%} | {c.trials} | {c.scale:.3g} | "
                     f"{c.nees_mean:.2f} | {c.nees_band[0]:.2f} - {c.nees_band[1]:.2f} | "
                     f"{'yes' if c.consistent else 'no'} | {sd[0]:.4f} m, {sd[1]:.5f} rad | "
                     f"{pd[0]:.4f} m, {pd[1]:.5f} rad | {c.mean_error[0]:+.4f} m, {c.mean_error[1]:+.5f} rad |")
    lines.append("")
    return "\n".join(lines)
