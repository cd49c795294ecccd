"""The trust-region Newton driver: its step against SciPy, and minimisation of known functions."""

import numpy as np
import pytest
from scipy import differentiate, optimize

from taichi_match import Status
from taichi_match._cost import prior, prior_hessian
from taichi_match._newton import minimize_newton, trust_region_step


def random_symmetric(rng, definite):
    q, _ = np.linalg.qr(rng.standard_normal((3, 3)))
    evals = rng.uniform(0.1, 10.0, 3) * (1.0 if definite else rng.choice([-1.0, 1.0], 3))
    return (q * evals) @ q.T


@pytest.mark.parametrize("definite", [True, False])
def test_the_step_minimises_the_model_within_the_region(rng, definite):
    for _ in range(30):
        hess = random_symmetric(rng, definite)
        g = rng.standard_normal(3) * rng.uniform(0.1, 10.0)
        radius = rng.uniform(0.01, 2.0)
        p, predicted = trust_region_step(g, hess, radius)
        evals, evecs = np.linalg.eigh(hess)
        b = (evecs * np.abs(evals)) @ evecs.T                   # the model's curvature: |eigenvalues|

        def model(q):
            return g @ q + 0.5 * q @ b @ q

        ref = optimize.minimize(model, np.zeros(3), jac=lambda q: g + b @ q, method="SLSQP",
                                constraints=[{"type": "ineq", "fun": lambda q: radius**2 - q @ q}],
                                options={"ftol": 1e-12, "maxiter": 500})
        assert ref.x @ ref.x <= radius**2 * (1 + 1e-6)
        assert np.linalg.norm(p) <= radius * (1 + 2e-3)
        assert model(p) <= ref.fun + 1e-3 * abs(ref.fun)
        assert np.isclose(predicted, -model(p), rtol=1e-9, atol=1e-12)


def test_the_gradient_fallback_steps_out_of_a_small_dip():
    target, z0 = np.array([1.0, 0.0, 0.0]), np.zeros(3)

    def evaluate(z):        # a bowl around target, with a narrow dip at z0; the "stencil" gradient
        f = float((z - target) @ (z - target)) - 0.5 * np.exp(-((z - z0) @ (z - z0)) / (2 * 0.01**2))
        return f, 2.0 * (z - target), 100.0 * np.eye(3), None       # sees the bowl, its curvature is off

    kwargs = dict(radius=0.5, max_radius=0.5, xtol=1e-3, gtol=1e-9, max_launches=50)
    stuck = minimize_newton(evaluate, z0, **kwargs)
    assert stuck.status == Status.NO_DESCENT and np.array_equal(stuck.z, z0)
    res = minimize_newton(evaluate, z0, gradient_fallback=True, **kwargs)
    assert res.fun < 0.1 < evaluate(z0)[0] and np.linalg.norm(res.z - target) < 0.5


def test_minimises_a_smooth_function_to_scipys_answer():
    shift = np.array([0.3, -0.2, 0.1])

    def f(z):
        d = z - shift
        return float(d @ np.diag([4.0, 1.0, 9.0]) @ d + 0.5 * d[0] ** 4 + np.cos(d[1]) - 1.0 + 0.3 * d[0] * d[2])

    def evaluate(z):
        g = optimize.approx_fprime(z, f, 1e-7)
        h = differentiate.hessian(f_vec, z).ddf
        return f(z), g, h, None

    def f_vec(z):
        return np.apply_along_axis(f, 0, z)

    res = minimize_newton(evaluate, np.array([2.0, 1.5, -1.0]), radius=0.5, max_radius=1.0, xtol=1e-6,
                          gtol=1e-6, max_launches=50)
    ref = optimize.minimize(f, np.array([2.0, 1.5, -1.0]), method="BFGS", options={"gtol": 1e-10})
    assert res.status in (Status.GRADIENT, Status.STEP)
    assert np.allclose(res.z, ref.x, atol=1e-5)
    # measured (deterministic): 6 accepted steps, no rejection; launches = the start + 6 trials
    assert (res.nit, res.launches) == (6, 1 + 6), (res.nit, res.launches)


def test_reports_the_budget_and_a_stuck_start():
    calls = []

    def evaluate(z):
        calls.append(z)
        return float(z @ z), 2.0 * z, 2.0 * np.eye(3), None

    res = minimize_newton(evaluate, np.full(3, 10.0), radius=0.1, max_radius=0.1, xtol=1e-9, gtol=1e-9,
                          max_launches=3)
    assert res.status == Status.MAX_ITERATIONS and res.launches == 4 and len(calls) == 4

    def rising(z):                                   # the model promises descent, the function rises
        return float(-np.sum(z)) + 100.0 * float(z @ z > 0), -np.ones(3), np.eye(3), None

    res = minimize_newton(rising, np.zeros(3), radius=1.0, max_radius=1.0, xtol=1e-3, gtol=1e-9,
                          max_launches=100)
    assert res.status == Status.NO_DESCENT and np.array_equal(res.z, np.zeros(3))


def test_the_prior_curvature_is_that_of_its_touching_quadratic(rng):
    r0 = np.array([0.2, -0.1, 0.05])
    for _ in range(5):
        r = r0 + rng.uniform(-1, 1, 3)
        k, length = 7.0, 2.0
        n_c = prior(r, r0, 1.0, length)[0]

        def touching(q):            # K (|q - r0|^2 / (2 n_c) + n_c / 2): equals the cone at r, above it elsewhere
            d = np.moveaxis(q, 0, -1) - r0
            return k * (np.sum(d**2 * [1.0, 1.0, length**2], axis=-1) / (2 * n_c) + n_c / 2)

        assert np.isclose(touching(r), prior(r, r0, k, length)[0])
        ref = differentiate.hessian(touching, r).ddf
        assert np.allclose(prior_hessian(r, r0, k, length, min_norm=1e-3), ref, rtol=1e-6, atol=1e-6)


MINIMUM = np.array([0.7, -1.3, 0.4])
_BASIS, _ = np.linalg.qr(np.array([[1.0, 2.0, 0.5], [-1.0, 0.3, 2.0], [0.4, -1.0, 1.0]]))
Q = (_BASIS * [1.0, 4.0, 9.0]) @ _BASIS.T            # (z - m)^T Q (z - m): eigenvalues 1, 4, 9


class Quadratic:
    """The convex quadratic with its exact derivatives; remembers the points evaluated."""

    def __init__(self):
        self.points = []

    def __call__(self, z):
        self.points.append(np.array(z, dtype=np.float64))
        d = z - MINIMUM
        return float(d @ Q @ d), 2.0 * Q @ d, 2.0 * Q, None


def test_one_newton_step_solves_a_quadratic_inside_the_region():
    """Newton's step on a quadratic with its exact Hessian lands on the minimum; the gradient there
    is zero: 1 accepted step, the start and 1 trial launched."""
    evaluate = Quadratic()
    res = minimize_newton(evaluate, MINIMUM + [0.1, -0.05, 0.02], radius=1.0, max_radius=1.0, xtol=1e-9,
                          gtol=1e-9, max_launches=50)
    assert res.status == Status.GRADIENT and res.nit == 1 and res.launches == 2 and len(evaluate.points) == 2
    assert np.allclose(res.z, MINIMUM, rtol=0, atol=1e-12)
    assert np.allclose(res.hessian, 2.0 * Q) and res.fun == pytest.approx(0.0, abs=1e-24)


def test_a_zero_gradient_at_the_start_stops_at_once():
    evaluate = Quadratic()
    res = minimize_newton(evaluate, MINIMUM, radius=1.0, max_radius=1.0, xtol=1e-9, gtol=1e-9, max_launches=50)
    assert res.status == Status.GRADIENT and res.nit == 0 and res.launches == 1
    assert np.array_equal(res.z, MINIMUM)
    first = evaluate(MINIMUM)
    res = minimize_newton(evaluate, MINIMUM, radius=1.0, max_radius=1.0, xtol=1e-9, gtol=1e-9, max_launches=50,
                          first=first)
    assert res.status == Status.GRADIENT and res.launches == 0 and len(evaluate.points) == 2


def test_every_trial_lies_within_the_largest_trust_region():
    """From 11.5 units away with max_radius 0.5: every point evaluated lies within max_radius (plus the
    secular equation's 1e-3 tolerance) of the centre it was tried from, the best point so far (the
    driver moves only on a decrease); the cap is reached (else this proves nothing); the minimum
    is found."""
    evaluate = Quadratic()
    max_radius = 0.5
    res = minimize_newton(evaluate, np.array([10.0, -7.0, 4.0]), radius=0.1, max_radius=max_radius, xtol=1e-9,
                          gtol=1e-9, max_launches=200)
    assert res.status in (Status.GRADIENT, Status.STEP) and np.allclose(res.z, MINIMUM, atol=1e-9)
    values = [float((p - MINIMUM) @ Q @ (p - MINIMUM)) for p in evaluate.points]
    distances = []
    for k in range(1, len(evaluate.points)):
        centre = evaluate.points[int(np.argmin(values[:k]))]
        distances.append(np.linalg.norm(evaluate.points[k] - centre))
    assert max(distances) <= max_radius * (1 + 2e-3)
    assert sum(d >= max_radius * (1 - 2e-3) for d in distances) >= 20, distances
    assert len(evaluate.points) == res.launches
