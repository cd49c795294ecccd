"""Coarse to fine: the optimiser run on each pyramid level, from the coarsest to the given maps.

The coarsest level finds the basin from the initial guess with the full iteration budget; each
finer level refines within a small budget from where the coarser one stopped. Both drivers end on
the given maps with e, the overlap and the Hessian of e (eq. 12) at the pose, for the covariance.
"""

import functools
from dataclasses import dataclass
from typing import Optional

import numpy as np

from ._bfgs import minimize_bfgs, polish
from ._cost import Counter, LevelCost
from ._engines import make_engine
from ._newton import minimize_newton
from ._options import MatchOptions
from ._prepared import PreparedMap
from ._status import Status

__all__ = ["Descent", "descend"]

# Trust region of the Newton driver on entering a finer level, in that level's cells: the
# coarser level left the pose within a few of its own cells (measured in bench/TUNING.md).
ENTRY_RADIUS_CELLS = 4.0          # middle levels
ENTRY_RADIUS_CELLS_FINEST = 1.0   # the given maps


@dataclass(frozen=True)
class Descent:
    """Where the descent ended, on the given maps.

    ``status`` is the coarsest level's (the finer ones refine within a fixed budget);
    ``iterations`` sums the levels'; ``cost`` is h and ``discrepancy`` e at ``pose``;
    ``information`` the Hessian of e there (eq. 12), zero when nothing was matched; ``overlap``
    None where it was not counted (``MatchOptions.count_overlap``), ``overlapping`` whether the
    maps overlap at ``pose`` either way.
    """

    pose: np.ndarray
    status: Status
    iterations: int
    cost: float
    discrepancy: float
    overlap: Optional[int]
    information: np.ndarray
    overlapping: bool


def descend(prep_a: PreparedMap, prep_b: PreparedMap, opts: MatchOptions, r0: np.ndarray, weight: float,
            counter: Counter) -> Descent:
    """Minimise h (eq. 8) from ``r0`` with ``opts.method`` over ``opts.levels`` levels of the
    prepared maps; ``weight`` is K on the given maps, ``counter`` counts launches and poses."""
    levels = _bfgs_levels if opts.method == "bfgs" else _newton_levels
    return levels(prep_a, prep_b, opts, r0, weight, counter)


def _level_cost(prep_a, prep_b, level, opts, r0, weight, counter):
    pa, pb = prep_a.level(level), prep_b.level(level)
    engine = make_engine(opts.engine, pa, pb, opts.unknown_cost, opts.interpolation, opts.grid_edge)
    return LevelCost(engine, pa, pb, prep_b, opts, r0, weight, counter)


def _no_overlap(r0, cost_value):
    return Descent(r0, Status.NO_OVERLAP, 0, cost_value, 0.0, 0, np.zeros((3, 3)), False)


def _newton_levels(prep_a, prep_b, opts, r0, weight, counter):
    """Trust-region Newton on each level, coarse to fine; one 25-pose launch per iteration."""
    top = opts.levels - 1
    r, status, nit = r0, Status.MAX_ITERATIONS, 0
    for level in range(top, -1, -1):                  # coarse to fine; level 0: the given maps
        cost = _level_cost(prep_a, prep_b, level, opts, r0, weight, counter)
        eps = cost.steps[0]
        # the overlap is needed at the start (is there any?) and at the end: the result's, or
        # without ``count_overlap`` whether there is any, from the launches where that comes free
        count = "none"
        if level == 0 and cost.counts_free:
            count = "first"
        elif level == 0 and not opts.count_overlap:
            count = "any"
        evaluate = functools.partial(cost.value_gradient_hessian, count=count)
        # at the top: is there any overlap? (the exact count only when the top level is also the last)
        first_count = ("any" if top > 0 else "first") if level == top else count
        first = cost.value_gradient_hessian(cost.to_z(r), count=first_count)
        if level == top and first[3][1] == 0:
            return _no_overlap(r0, first[0])
        if level == top:
            radius, budget = cost.max_step, opts.max_iterations
        else:
            radius = (ENTRY_RADIUS_CELLS_FINEST if level == 0 else ENTRY_RADIUS_CELLS) * eps
            budget = min(opts.refine_iterations, opts.max_iterations)
        xtol = opts.step_tolerance if level == top else opts.refine_xtol
        res = minimize_newton(evaluate, cost.to_z(r), radius=radius, max_radius=cost.max_step, xtol=xtol * eps,
                              gtol=opts.gtol * cost.weight, max_launches=budget, first=first,
                              gradient_fallback=level == top)
        r, nit = cost.to_r(res.z), nit + res.nit
        if level == top:          # the finer levels refine within a fixed budget of launches
            status = res.status
    e, overlap, information = res.extra
    return _ended(cost, opts, r, status, nit, res.fun, e, overlap, information)


def _bfgs_levels(prep_a, prep_b, opts, r0, weight, counter):
    """The paper's BFGS (eq. 9) on each level, compass polish, then one 25-pose Hessian launch."""
    top = opts.levels - 1
    r, status, nit, cost_value = r0, Status.MAX_ITERATIONS, 0, 0.0
    for level in range(top, -1, -1):                  # coarse to fine; level 0: the given maps
        cost = _level_cost(prep_a, prep_b, level, opts, r0, weight, counter)
        eps = cost.steps[0]
        # the overlap is needed at the start (is there any?) and at the end (the result's)
        h_start, grad_start, counts = cost.value_and_gradient(
            r, count="first" if level == top or cost.counts_free else "none")
        z, step = cost.to_z(r), 4.0 * eps
        if level == top and counts[0] == 0:
            return _no_overlap(r0, h_start)
        if level == top:                               # BFGS from the initial guess
            res = minimize_bfgs(cost.fun_grad, z, max_step=cost.max_step, xtol=opts.step_tolerance * eps,
                                gtol=opts.gtol * cost.weight, max_iterations=opts.max_iterations,
                                first=(h_start, cost.grad_z(grad_start)))
            z, h_start, status, nit = res.z, res.fun, res.status, nit + res.nit
        elif level == 0:                               # a few BFGS steps of at most two cells
            res = minimize_bfgs(cost.fun_grad, z, max_step=2.0 * eps, xtol=opts.step_tolerance * eps,
                                gtol=opts.gtol * cost.weight,
                                max_iterations=min(opts.refine_iterations, opts.max_iterations),
                                first=(h_start, cost.grad_z(grad_start)))
            z, h_start, nit, step = res.z, res.fun, nit + res.nit, eps
        # then the compass search (alone on the levels in between)
        z, cost_value, _ = polish(cost.batch, z, h_start, step=step, xtol=opts.step_tolerance * eps,
                                  max_step=cost.max_step)
        r = cost.to_r(z)
    # eq. (11)-(12) on the given maps, one launch (two when counting the overlap takes its own)
    count = "first" if opts.count_overlap or cost.counts_free else "any"
    _, _, _, (e, overlap, information) = cost.value_gradient_hessian(cost.to_z(r), count=count)
    return _ended(cost, opts, r, status, nit, cost_value, e, overlap, information)


def _ended(cost, opts, r, status, nit, cost_value, e, overlap, information):
    """The Descent at ``r``. ``overlap``: what the last launch at ``r`` counted, or None. Without
    ``count_overlap``, where counting takes a launch of its own (the envelope discrepancy), that
    is only the proof that the maps overlap or not (count "any"), and no overlap is reported."""
    if overlap is None:
        overlap = cost.overlap(r)
    proof = not opts.count_overlap and not cost.counts_free
    return Descent(r, status, nit, cost_value, e, None if proof else overlap, information, overlap > 0)
