"""The ``taichi-match`` command line: parses, calls the library, prints. Heavy imports are lazy."""

import argparse
import os
import sys
import time

__all__ = ["main"]


class _ProgressBar:
    """A one-line progress bar on stderr (only when stderr is a terminal, or forced)."""

    def __init__(self, label, enabled):
        self.label = label
        self.enabled = enabled
        self.start = time.perf_counter()
        self.last = 0.0

    def __call__(self, done, total):
        now = time.perf_counter()
        if not self.enabled or (now - self.last < 0.2 and done < total):
            return
        self.last = now
        width = 30
        filled = int(width * done / max(total, 1))
        sys.stderr.write(f"\r{self.label} [{'#' * filled}{'.' * (width - filled)}] {done}/{total} "
                         f"{now - self.start:5.0f} s")
        if done >= total:
            sys.stderr.write("\n")
        sys.stderr.flush()


def _demo(args):
    import numpy as np

    import taichi_match as tm
    from taichi_match.scenes import corridor

    grid = corridor()
    r0 = np.array(args.initial, dtype=float)
    matcher = tm.Matcher()
    matcher.match(grid, grid, r0)                        # first call compiles the kernel
    res = matcher.match(grid, grid, r0)
    np.set_printoptions(precision=6, suppress=False)
    print("The paper's corridor: 12 m square map at 0.025 m (480 x 480 cells), 6 m corridor along x;")
    print("B is a copy of A, so the true y and theta are 0 and x is free along the corridor.")
    print(f"initial pose  x={r0[0]:+.4f} m  y={r0[1]:+.4f} m  theta={r0[2]:+.5f} rad")
    x, y, t = res.pose
    print(f"matched pose  x={x:+.4f} m  y={y:+.4f} m  theta={t:+.5f} rad")
    print(f"status        {res.status.name}: {res.message}")
    print(f"iterations    {res.iterations} ({res.launches} kernel launches, {res.evaluations} poses evaluated)")
    print(f"overlap       {res.overlap} cells compared, discrepancy {res.discrepancy:.2f}")
    print("covariance (x, y, theta):")
    print(res.covariance)
    for d in res.degenerate:
        dx, dy, dt = np.round(d, 4) + 0.0
        print(f"degenerate direction (no information): ({dx:+.4f}, {dy:+.4f}, {dt:+.4f}) in (x, y, theta)")
    print(f"time          {1e3 * res.seconds:.1f} ms (the paper: about 6 s)")
    if args.plot:
        try:
            from taichi_match import plots
            plots.save_overlay(args.plot, grid, grid, r0, res, title="taichi-match demo: the paper's corridor")
            print(f"picture       {args.plot}")
        except ImportError as exc:
            print(f"picture       not written: {exc}")
    return 0 if res.converged else 1


def _reproduce(args):
    from taichi_match.reproduce import reproduce

    bar = _ProgressBar("matching", args.progress or sys.stderr.isatty())
    out = reproduce(args.out, trials=args.trials, covariance_trials=args.covariance_trials, seed=args.seed,
                    progress=bar)
    print(open(os.path.join(args.out, "report.md")).read().split("## Figures")[0].rstrip())
    print(f"\nwrote {os.path.join(args.out, 'report.md')}, results.json, config.json and "
          f"{len(out['results']['figures'])} figures in {out['results']['seconds']:.0f} s")
    return 0


def main(argv=None):
    parser = argparse.ArgumentParser(
        prog="taichi-match", description="Relative pose between overlapping occupancy grid maps.")
    sub = parser.add_subparsers(dest="command", required=True)
    demo = sub.add_parser("demo", help="match the paper's corridor against a copy of itself")
    demo.add_argument("--initial", nargs=3, type=float, metavar=("X", "Y", "THETA"), default=(0.8, -1.1, 0.3),
                      help="initial guess of B's pose in A (metres, metres, radians)")
    demo.add_argument("--plot", default="taichi_match_demo.png", metavar="PNG",
                      help="where to write the overlay picture (default: %(default)s; '' for none)")
    demo.set_defaults(func=_demo)
    rep = sub.add_parser("reproduce", help="regenerate the paper's tables and figures and the covariance check")
    rep.add_argument("--out", required=True, metavar="DIR", help="output folder")
    rep.add_argument("--trials", type=int, default=100, help="trials per table row (default: %(default)s)")
    rep.add_argument("--covariance-trials", type=int, default=200,
                     help="matches per noise level of the covariance check (default: %(default)s)")
    rep.add_argument("--seed", type=int, default=0, help="seed of the initial poses and noise (default: %(default)s)")
    rep.add_argument("--progress", action="store_true", help="show the progress bar even when not on a terminal")
    rep.set_defaults(func=_reproduce)
    args = parser.parse_args(argv)
    if getattr(args, "trials", 1) < 1 or getattr(args, "covariance_trials", 2) < 2:
        parser.error("--trials must be >= 1 and --covariance-trials >= 2")
    return args.func(args)


if __name__ == "__main__":
    sys.exit(main())
