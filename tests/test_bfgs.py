"""The BFGS driver and the compass polish (``_bfgs``) on analytic functions whose minima are known."""

import numpy as np
import pytest

from taichi_match import Status
from taichi_match._bfgs import minimize_bfgs, polish

MINIMUM = np.array([0.7, -1.3, 0.4])
# a convex quadratic (z - m)^T Q (z - m) with eigenvalues 1, 4, 9 along a rotated basis
_BASIS, _ = np.linalg.qr(np.array([[1.0, 2.0, 0.5], [-1.0, 0.3, 2.0], [0.4, -1.0, 1.0]]))
Q = (_BASIS * [1.0, 4.0, 9.0]) @ _BASIS.T


def quadratic(z):
    d = np.asarray(z, dtype=np.float64) - MINIMUM
    return float(d @ Q @ d), 2.0 * Q @ d


class Recorded:
    """``fun_grad`` that remembers every point it was asked for."""

    def __init__(self, fun_grad):
        self.fun_grad, self.points = fun_grad, []

    def __call__(self, z):
        self.points.append(np.array(z, dtype=np.float64))
        return self.fun_grad(z)


KINK = np.array([0.0, 1.0, -0.5])


def kinked(z):
    """|x| + 2 |y - 1| + (t + 0.5)^2: minimum 0 at KINK, on the kink of the first two terms."""
    x, y, t = z
    return float(abs(x) + 2.0 * abs(y - 1.0) + (t + 0.5) ** 2), np.array([np.sign(x), 2.0 * np.sign(y - 1.0),
                                                                          2.0 * (t + 0.5)])


def kinked_batch(zs):
    zs = np.atleast_2d(zs)
    return np.abs(zs[:, 0]) + 2.0 * np.abs(zs[:, 1] - 1.0) + (zs[:, 2] + 0.5) ** 2


@pytest.mark.parametrize("z0", [(10.0, -7.0, 4.0), (0.0, 0.0, 0.0), (0.71, -1.29, 0.41)])
def test_a_convex_quadratic_reaches_its_known_minimum(z0):
    res = minimize_bfgs(quadratic, z0, max_step=1.0, xtol=1e-12, gtol=1e-9, max_iterations=200)
    assert res.status == Status.GRADIENT, res
    # |grad| = |2 Q d| <= 1e-9 and the smallest eigenvalue of 2Q is 2: |d| <= 5e-10
    assert np.linalg.norm(res.z - MINIMUM) <= 5e-10 * (1 + 1e-6)
    assert res.fun == pytest.approx(0.0, abs=1e-18)
    assert np.allclose(res.grad, quadratic(res.z)[1], rtol=0, atol=0)


def test_a_zero_gradient_at_the_start_stops_at_once():
    # a saddle with zero gradient at the origin: the gradient rule stops before any step
    saddle = Recorded(lambda z: (float(z[0] ** 2 - z[1] ** 2 + z[2] ** 2), np.array([2 * z[0], -2 * z[1], 2 * z[2]])))
    res = minimize_bfgs(saddle, np.zeros(3), max_step=1.0, xtol=1e-6, gtol=1e-9, max_iterations=50)
    assert res.status == Status.GRADIENT and res.nit == 0 and res.nfev == 1 and len(saddle.points) == 1
    assert np.array_equal(res.z, np.zeros(3))
    # with the caller's evaluation of the start, none at all
    res = minimize_bfgs(saddle, np.zeros(3), max_step=1.0, xtol=1e-6, gtol=1e-9, max_iterations=50,
                        first=(0.0, np.zeros(3)))
    assert res.status == Status.GRADIENT and res.nit == 0 and len(saddle.points) == 1


def test_the_iteration_budget():
    z0 = np.array([10.0, -7.0, 4.0])
    calls = Recorded(quadratic)
    res = minimize_bfgs(calls, z0, max_step=1.0, xtol=1e-9, gtol=1e-9, max_iterations=0)
    assert res.status == Status.MAX_ITERATIONS and res.nit == 0 and len(calls.points) == 1
    assert np.array_equal(res.z, z0) and res.fun == quadratic(z0)[0]
    res = minimize_bfgs(quadratic, z0, max_step=1.0, xtol=1e-9, gtol=1e-9, max_iterations=1)
    # one steepest-descent step of at most max_step from 11.5 units away: not converged, but lower
    assert res.status == Status.MAX_ITERATIONS and res.nit == 1
    assert res.fun < quadratic(z0)[0] and 0.0 < np.linalg.norm(res.z - z0) <= 1.0 + 1e-12


def test_every_step_and_every_trial_stays_within_max_step():
    """The iterate after k iterations (a run with max_iterations=k) moves at most max_step from the
    one after k - 1, and every point evaluated during iteration k lies within max_step of the
    iterate it started from."""
    z0, max_step = np.array([10.0, -7.0, 4.0]), 0.5
    kwargs = dict(max_step=max_step, xtol=1e-9, gtol=1e-9)
    previous, previous_points, steps = None, [], []
    for k in range(40):
        calls = Recorded(quadratic)
        res = minimize_bfgs(calls, z0, max_iterations=k, **kwargs)
        if previous is not None:
            start = previous.z
            steps.append(np.linalg.norm(res.z - start))
            # the runs are deterministic: run k repeats run k-1's evaluations, then iteration k's
            assert all(np.array_equal(p, q) for p, q in zip(calls.points, previous_points))
            for point in calls.points[len(previous_points):]:
                assert np.linalg.norm(point - start) <= max_step * (1 + 1e-12)
        previous, previous_points = res, calls.points
        if res.status != Status.MAX_ITERATIONS:
            break
    assert res.status in (Status.GRADIENT, Status.STEP) and np.allclose(res.z, MINIMUM, atol=1e-6)
    assert max(steps) <= max_step * (1 + 1e-12)
    # 11.5 units from the minimum: the cap is what limited the first steps (else this proves nothing)
    assert sum(np.isclose(s, max_step, rtol=1e-9) for s in steps) >= 10, steps


@pytest.mark.parametrize("z0", [(0.37, 0.2, 0.8), (-1.3, 2.2, -0.1), (0.9, 0.95, -0.5)])
def test_bfgs_stalls_at_a_kink_and_polish_reaches_it_within_the_tolerance(z0):
    xtol = 1e-4
    res = minimize_bfgs(kinked, z0, max_step=0.5, xtol=xtol, gtol=1e-6, max_iterations=100)
    # |df/dx| = 1 wherever x != 0: the gradient never vanishes near the kink, so only the step
    # rules can stop BFGS, and (a zig-zag across the kink) not at it
    assert res.status in (Status.STEP, Status.NO_DESCENT), res
    z, f, launches = polish(kinked_batch, res.z, res.fun, step=4 * xtol, xtol=xtol, max_step=0.5)
    assert launches < 20                                        # stopped by its step, not its budget
    assert f == pytest.approx(kinked(z)[0], abs=1e-15) and f <= res.fun
    # the compass search stops after a launch in which no axis move of length l (its shortest
    # l < 4 xtol) lowered f; for each of these separable terms no such move lowers f iff the
    # coordinate is within l / 2 of its minimum: each coordinate is within 2 xtol of the kink
    assert np.all(np.abs(z - KINK) < 2 * xtol), (z - KINK, res.z - KINK)


def test_polish_tries_the_documented_pattern():
    """First launch: the six axis directions at step * 4**-k, k = 0, 1, 2."""
    seen = []

    def values(zs):
        seen.append(np.array(zs))
        return kinked_batch(zs)

    z0 = np.array([0.3, 0.4, 0.1])
    polish(values, z0, kinked(z0)[0], step=0.5, xtol=1e-3, max_step=1.0, max_launches=1)
    expected = {tuple(np.round(z0 + s * length * e, 12)) for length in (0.5, 0.125, 0.03125)
                for e in np.eye(3) for s in (1.0, -1.0)}
    assert len(seen) == 1 and {tuple(np.round(z, 12)) for z in seen[0]} == expected


def test_polish_doubles_its_step_up_to_max_step_and_keeps_its_budget():
    # f falls linearly along +x: every launch moves by its longest trial, which then doubles,
    # capped at max_step: 0.1 + 0.2 + 0.4 + 0.8 + 1.0 after 5 launches
    def falling(zs):
        return -np.atleast_2d(zs)[:, 0]

    z, f, launches = polish(falling, np.zeros(3), 0.0, step=0.1, xtol=1e-3, max_step=1.0, max_launches=5)
    assert launches == 5
    assert np.allclose(z, [2.5, 0.0, 0.0], atol=1e-12) and f == pytest.approx(-2.5)


def test_polish_at_the_minimum_stays_and_stops_on_its_step():
    # nothing improves (xtol = 1e-4): launch 1 tries 1, 1/4, 1/16 and goes on a quarter below the
    # shortest, at 4**-3; launch 2 tries 4**-3, 4**-4, 4**-5 (all >= xtol), then 4**-6 = 2.4e-4;
    # launch 3 tries 4**-6 alone (4**-7 = 6.1e-5 < xtol), then goes on at 4**-7 < xtol: done after 3
    z, f, launches = polish(kinked_batch, KINK, 0.0, step=1.0, xtol=1e-4, max_step=1.0)
    assert np.array_equal(z, KINK) and f == 0.0 and launches == 3
