"""A small BFGS driver for the piecewise-smooth matching cost (sec. 4 of the paper).

It minimises ``f(z)`` given a callback returning the value and gradient at z (one kernel launch
for the centre and the stencil), in scaled coordinates where every component is in metres
(theta multiplied by a length: the matcher uses B's rms radius). Steps are capped at
``max_step``; a backtracking Armijo line search evaluates value and gradient together, so an
accepted trial point already carries the gradient of the next iteration.

The cost is piecewise smooth: with nearest-cell lookup it is a fine staircase, and at an exact
alignment it has a kink. Stopping rules therefore do not wait for a zero gradient alone:

- ``GRADIENT``: the gradient norm is at most ``gtol``;
- ``STEP``: an accepted step is shorter than ``xtol``;
- ``NO_DESCENT``: neither the quasi-Newton nor the steepest-descent direction decreases the cost by
  a step longer than ``xtol``: a minimum at the resolution of the cost (a kink or a floor step);
- ``MAX_ITERATIONS``: the iteration budget ran out (not converged).

Gradient methods zig-zag along a kinked valley: in a corridor the prior pulls along the valley
floor while the stencil gradient is dominated by the kink across it, and BFGS then crawls.
``polish`` finishes with a compass search (Kolda, Lewis & Torczon 2003) that needs no gradient:
each launch tries the six axis directions at three step lengths at once.
"""

from dataclasses import dataclass

import numpy as np

from ._status import Status

__all__ = ["BfgsResult", "minimize_bfgs", "polish"]


@dataclass
class BfgsResult:
    z: np.ndarray
    fun: float
    grad: np.ndarray
    status: Status
    nit: int
    nfev: int


def minimize_bfgs(fun_grad, z0, *, max_step, xtol, gtol, max_iterations, c1=1e-4, first=None):
    """Minimise ``fun_grad(z) -> (f, g)`` from z0; see the module docstring.

    ``first`` may hold ``fun_grad(z0)`` when the caller has already evaluated it.
    """
    z = np.asarray(z0, dtype=np.float64).copy()
    f, g = first if first is not None else fun_grad(z)
    nfev = 1
    hinv = None                                    # None: steepest descent with a capped step
    sd_length = max_step                           # steepest-descent step: last accepted length
    status = Status.MAX_ITERATIONS
    nit = 0
    while nit < max_iterations:
        if np.linalg.norm(g) <= gtol:
            status = Status.GRADIENT
            break
        accepted = None
        for quasi_newton in ((True, False) if hinv is not None else (False,)):
            p = -hinv @ g if quasi_newton else -g
            if quasi_newton and p @ g >= 0.0:
                continue
            norm_p = np.linalg.norm(p)
            limit = max_step if quasi_newton else sd_length
            if norm_p > limit or not quasi_newton:
                p = p * (limit / norm_p)
                norm_p = limit
            accepted, n = _line_search(fun_grad, z, f, g, p, norm_p, xtol, c1)
            nfev += n
            if accepted is not None:
                break
            hinv = None                            # the quasi-Newton model failed: restart it
        nit += 1
        if accepted is None:
            status = Status.NO_DESCENT
            break
        s, z_new, f_new, g_new = accepted
        y = g_new - g
        sy = s @ y
        if sy > 1e-12 * np.linalg.norm(s) * np.linalg.norm(y):
            if hinv is None:
                hinv = np.eye(len(z)) * (sy / (y @ y))
            rho = 1.0 / sy
            v = np.eye(len(z)) - rho * np.outer(s, y)
            hinv = v @ hinv @ v.T + rho * np.outer(s, s)
        z, f, g = z_new, f_new, g_new
        step = np.linalg.norm(s)
        sd_length = min(max_step, max(2.0 * step, 10.0 * xtol))
        if step < xtol:
            status = Status.STEP
            break
    return BfgsResult(z=z, fun=f, grad=g, status=status, nit=nit, nfev=nfev)


def _line_search(fun_grad, z, f, g, p, norm_p, xtol, c1):
    """Backtracking Armijo search along p with safeguarded quadratic interpolation.

    Returns ((step, z_new, f_new, g_new), evaluations), or (None, evaluations) when no
    step longer than ``xtol`` decreases f enough.
    """
    slope = p @ g
    alpha = 1.0
    n = 0
    while alpha * norm_p >= xtol:
        z_new = z + alpha * p
        f_new, g_new = fun_grad(z_new)
        n += 1
        if f_new <= f + c1 * alpha * slope:
            return (alpha * p, z_new, f_new, g_new), n
        # minimum of the quadratic through f(0), f'(0) and f(alpha), kept in [0.1, 0.5] * alpha
        curvature = f_new - f - slope * alpha
        trial = -slope * alpha * alpha / (2.0 * curvature) if curvature > 0.0 else 0.5 * alpha
        alpha = min(max(trial, 0.1 * alpha), 0.5 * alpha)
    return None, n


def polish(values, z, f, *, step, xtol, max_step, max_launches=20):
    """Compass search from z: move to the best of +-step along each axis while that lowers f.

    ``values(Z) -> f`` evaluates a batch of points in one launch. Each launch tries the six axis
    directions at lengths step * 4**-k, k = 0..2 (those >= xtol); on success the step doubles
    from the length that won, otherwise it goes on below the shortest length tried, until the
    step is shorter than xtol. Returns (z, f, launches).
    """
    z = np.asarray(z, dtype=np.float64)
    directions = np.vstack([np.eye(len(z)), -np.eye(len(z))])
    launches = 0
    while step >= xtol and launches < max_launches:
        lengths = step * 0.25 ** np.arange(3)
        lengths = lengths[lengths >= xtol]
        trials = (z + lengths[:, None, None] * directions[None, :, :]).reshape(-1, len(z))
        f_trials = values(trials)
        launches += 1
        best = int(np.argmin(f_trials))
        if f_trials[best] < f:
            z, f = trials[best], float(f_trials[best])
            step = min(2.0 * lengths[best // len(directions)], max_step)
        else:
            step = 0.25 * lengths[-1]
    return z, f, launches
