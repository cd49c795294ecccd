"""The README's usage example: a walled corridor matched against a copy of itself."""

import numpy as np

import taichi_match as tm

prob_a = np.full((400, 400), np.nan)          # NaN = unknown, else occupancy in [0, 1]
prob_a[100:300, 50:350] = 0.0                 # free space ...
prob_a[100:102, 50:350] = prob_a[298:300, 50:350] = 1.0   # ... between two walls
a = tm.GridMap(prob_a, resolution=0.05, origin=(-10.0, -10.0))
b = tm.GridMap(prob_a, resolution=0.05, origin=(-10.0, -10.0))

result = tm.match(a, b, initial_pose=(0.3, -0.4, 0.1))      # B's pose in A: x, y (m), theta (rad)
print(result.pose, result.converged, result.message)
print(result.covariance)                      # 3x3, (x, y, theta); huge variance along the corridor
print(result.degenerate)                      # [[1, 0, 0]]: no information along x
