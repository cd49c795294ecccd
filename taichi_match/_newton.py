"""A trust-region Newton driver on the stencil's own curvature (an alternative to BFGS).

Each iteration costs one kernel launch: the 25 poses of the Hessian stencil (eq. 10-12) give the
value, the gradient and the Hessian at once, so the model needs no history and the last launch
is also the covariance's (eq. 11). In scaled coordinates z (every component in metres), with
f, g, B at the centre, the step p minimises the model ``g.p + p.B.p / 2`` within ``|p| <= radius``
(Levenberg-Marquardt: ``(B + mu I) p = -g``, mu >= 0 the smallest that keeps p in the region),
where B is the stencil's Hessian with its eigenvalues replaced by their absolute values (floored):
far from the answer, or at a kink, the stencil Hessian of this piecewise-smooth cost is often
indefinite. The trial point's launch is the next iteration's: an accepted step moves the centre,
a rejected one shrinks the region. With ``gradient_fallback`` (the coarsest level), a rejected
step is followed by one along -g as long as the region: the stencil gradient is smoothed over
+-2 steps, and along it a long step often descends where the model's shorter one met a bump of
the noisy small-scale surface (measured: noisy-corridor failures 3 / 500 -> 0 / 500).

Stops, with the statuses of ``_status``:

- ``GRADIENT``: the gradient norm is at most ``gtol``;
- ``STEP``: the model's step is shorter than ``xtol`` (nothing left to gain at this resolution);
- ``NO_DESCENT``: the region shrank below ``xtol`` without a decrease;
- ``MAX_ITERATIONS``: the launch budget ran out (not converged).
"""

import math
from dataclasses import dataclass

import numpy as np

from ._status import Status

__all__ = ["NewtonResult", "minimize_newton", "trust_region_step"]


@dataclass
class NewtonResult:
    z: np.ndarray
    fun: float
    grad: np.ndarray
    hessian: np.ndarray
    extra: object            # whatever the callback returned with the accepted centre
    status: Status
    nit: int                 # accepted steps
    launches: int


def _norm(v):
    """``np.linalg.norm`` of a vector (the same sqrt of the same dot product), without its
    overhead, which is a tenth of an iteration's Python here."""
    return math.sqrt(float(v.dot(v)))


def trust_region_step(g, hessian, radius, floor_rtol=1e-6):
    """The step p minimising g.p + p.B.p/2 with |p| <= radius, B = |hessian| (see module doc);
    g and hessian of 3 components (x, y, theta).

    Returns (p, predicted decrease >= 0). After one eigendecomposition the work is on three
    floats in plain Python, written out per component: faster than NumPy, or than loops over
    lists, at this size (this runs once a launch).
    """
    evals, evecs = np.linalg.eigh(0.5 * (hessian + hessian.T))
    l0, l1, l2 = abs(float(evals[0])), abs(float(evals[1])), abs(float(evals[2]))
    floor = max(floor_rtol * max(l0, l1, l2), 1e-12)
    l0, l1, l2 = max(l0, floor), max(l1, floor), max(l2, floor)
    g0, g1, g2 = (float(v) for v in evecs.T @ g)
    mu = 0.0
    p_norm = math.sqrt(0 + (g0 / l0) ** 2 + (g1 / l1) ** 2 + (g2 / l2) ** 2)
    if p_norm > radius:
        # the secular equation 1/|p(mu)| = 1/radius by Newton's method (More & Sorensen), which
        # converges monotonically from mu = 0 for this convex model
        for _ in range(30):
            d0, d1, d2 = l0 + mu, l1 + mu, l2 + mu
            p_norm = math.sqrt(0 + (g0 / d0) ** 2 + (g1 / d1) ** 2 + (g2 / d2) ** 2)
            dnorm = -(0 + g0 * g0 / d0**3 + g1 * g1 / d1**3 + g2 * g2 / d2**3) / p_norm      # d|p|/d mu
            mu = max(mu - (1.0 / radius - 1.0 / p_norm) / (dnorm / p_norm**2), 0.0)
            if abs(p_norm - radius) <= 1e-3 * radius:
                break
    p0, p1, p2 = -g0 / (l0 + mu), -g1 / (l1 + mu), -g2 / (l2 + mu)
    predicted = -(0 + (g0 * p0 + 0.5 * l0 * p0 * p0) + (g1 * p1 + 0.5 * l1 * p1 * p1)
                  + (g2 * p2 + 0.5 * l2 * p2 * p2))
    return evecs @ np.array([p0, p1, p2]), max(predicted, 0.0)


def minimize_newton(evaluate, z0, *, radius, max_radius, xtol, gtol, max_launches, first=None,
                    gradient_fallback=False):
    """Minimise from z0 with ``evaluate(z) -> (f, g, B, extra)`` (one launch each).

    ``radius`` is the initial trust region, ``max_radius`` its cap, both in metres (scaled units);
    ``max_launches`` bounds the evaluations after the one at z0, which ``first`` may hold when the
    caller has it. ``launches`` in the result counts the evaluations made here.
    """
    z = np.asarray(z0, dtype=np.float64).copy()
    f, g, hess, extra = first if first is not None else evaluate(z)
    launches = 0 if first is not None else 1
    trials = 0
    nit = 0
    status = Status.MAX_ITERATIONS
    while True:
        if _norm(g) <= gtol:
            status = Status.GRADIENT
            break
        p, predicted = trust_region_step(g, hess, radius)
        step = _norm(p)
        if step < xtol:
            status = Status.STEP if radius >= xtol else Status.NO_DESCENT
            break
        if trials >= max_launches:
            break
        trial = evaluate(z + p)
        launches += 1
        trials += 1
        actual = f - trial[0]
        ratio = actual / predicted if predicted > 0.0 else (1.0 if actual > 0.0 else -1.0)
        if actual > 0.0:
            z, (f, g, hess, extra) = z + p, trial
            nit += 1
            if ratio > 0.75 and step > 0.9 * radius:       # the model holds: trust it further
                radius = min(4.0 * radius, max_radius)
            elif ratio < 0.25:
                radius = 0.5 * step
        else:
            if gradient_fallback and trials < max_launches:
                # the stencil's gradient is smoothed over +-2 steps: along it, a step as long as
                # the region often descends where the model's shorter step met a bump
                q = -g * (radius / _norm(g))
                trial = evaluate(z + q)
                launches += 1
                trials += 1
                if trial[0] < f:
                    z, (f, g, hess, extra) = z + q, trial
                    nit += 1
                    continue
            radius = 0.25 * step
    return NewtonResult(z=z, fun=f, grad=g, hessian=hess, extra=extra, status=status, nit=nit,
                        launches=launches)
