"""The machine's speed as a benchmark run found it: the paper's corridor matched from Table 1-like
guesses, the median time. The machine is shared and its speed drifts by a quarter from hour to
hour; a benchmark's times are comparable with another run's only beside this figure of each
(2.5 ms on a quiet 2026-12-02, 3.2-3.8 ms on 2026-12-03). The match is the package's own at its
default options, so changes to the package move it too: from cf2baf2 (2026-12-06, the envelope
kernel making each pose's affine maps) it takes 0.93 of its former time on the same machine
(alternating in one process, bit-identical), and yardsticks of earlier files read 7 % high
against later ones."""

import time

import numpy as np

import taichi_match as tm
from taichi_match.scenes import corridor


def corridor_median_ms(trials: int = 50) -> float:
    """Median milliseconds of ``trials`` full matches of the corridor against itself (the kernels
    compiled first), from seeded guesses within 0.5 m and 0.1 rad."""
    grid = corridor()
    matcher = tm.Matcher()
    matcher.match(grid, grid, (0.1, 0.1, 0.01))
    rng = np.random.default_rng(0)
    times = []
    for _ in range(trials):
        guess = rng.uniform(-1, 1, 3) * (0.5, 0.5, 0.1)
        t0 = time.perf_counter()
        matcher.match(grid, grid, guess)
        times.append(time.perf_counter() - t0)
    return 1e3 * float(np.median(times))
