"""A worker for the process-pool test: importable by name in a spawned child."""

import numpy as np


def match_pose(r0):
    import taichi_match as tm
    from taichi_match.scenes import corridor

    grid = corridor(size=6.0, resolution=0.05, width=3.0)
    return np.asarray(tm.match(grid, grid, r0).pose).tobytes()
