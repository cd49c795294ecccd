"""Synthetic maps made by the tests, with their ground truth."""

import numpy as np
import pytest

from taichi_match import GridMap


def random_map(rng, shape, resolution, origin, unknown=0.2):
    """Random probabilities with a fraction of unknown cells."""
    prob = rng.random(shape)
    prob[rng.random(shape) < unknown] = np.nan
    return GridMap(prob, resolution, origin)


def room_scene(x, y):
    """An asymmetric walled room in world coordinates: occupancy 1 on walls and boxes, 0 free,
    NaN outside. x, y are arrays (metres)."""
    inside = (x > -4.0) & (x < 4.0) & (y > -3.0) & (y < 3.0)
    near_outer = inside & ((x < -3.8) | (x > 3.8) | (y < -2.8) | (y > 2.8))
    box1 = (x > -2.0) & (x < -1.2) & (y > 0.5) & (y < 1.5)
    box2 = (x > 1.0) & (x < 1.4) & (y > -2.0) & (y < 0.2)
    pillar = (x - 2.5) ** 2 + (y - 1.6) ** 2 < 0.3 ** 2
    inner_wall = (x > -3.8) & (x < -0.5) & (np.abs(y + 1.2) < 0.1)
    prob = np.where(inside, 0.0, np.nan)
    occupied = near_outer | (inside & (box1 | box2 | pillar | inner_wall))
    return np.where(occupied, 1.0, prob)


def rasterize(scene, shape, resolution, origin, pose_a2b=(0.0, 0.0, 0.0)):
    """Sample ``scene`` (defined in frame A) at the cell centres of a grid in frame B, where
    r_A2B = ``pose_a2b``; the truth of a later match is then exactly ``pose_a2b``."""
    rows, cols = np.indices(shape)
    xb = origin[0] + (cols + 0.5) * resolution
    yb = origin[1] + (rows + 0.5) * resolution
    x, y, t = pose_a2b
    xa = np.cos(t) * xb - np.sin(t) * yb + x
    ya = np.sin(t) * xb + np.cos(t) * yb + y
    return GridMap(scene(xa, ya), resolution, origin)


@pytest.fixture
def rng():
    return np.random.default_rng(12345)
