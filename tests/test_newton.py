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
    assert res.launches < 20


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
