"""The ``taichi-match`` command line. Parses, calls the library, prints; heavy imports are lazy."""

import argparse
import sys

__all__ = ["main"]


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
    return 0 if res.converged else 1


def main(argv=None):
    parser = argparse.ArgumentParser(
        prog="taichi-match", description="Relative pose between overlapping occupancy grid maps.")
    sub = parser.add_subparsers(dest="command", required=True)
    demo = sub.add_parser("demo", help="match the paper's corridor against a copy of itself")
    demo.add_argument("--initial", nargs=3, type=float, metavar=("X", "Y", "THETA"), default=(0.8, -1.1, 0.3),
                      help="initial guess of B's pose in A (metres, metres, radians)")
    demo.set_defaults(func=_demo)
    args = parser.parse_args(argv)
    return args.func(args)


if __name__ == "__main__":
    sys.exit(main())
