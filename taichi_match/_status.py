"""How a match ended: the optimisers' stopping rules and the outcomes only a whole match sees.

The first four are the optimisers' (``_bfgs``, ``_newton``); the last three are set by the matcher
when there was nothing to match. ``Status.converged`` says only that the optimiser stopped at a
minimum; whether the pose can be trusted is ``MatchResult.accepted``.
"""

import enum

__all__ = ["Status", "MESSAGES"]


class Status(enum.IntEnum):
    """Why a match stopped.

    Examples
    --------
    >>> from taichi_match import Status
    >>> Status.STEP.converged, Status.MAX_ITERATIONS.converged, Status.NO_OVERLAP.converged
    (True, False, False)
    """

    GRADIENT = 0          #: the gradient norm fell below ``gtol``
    STEP = 1              #: a step (BFGS: taken; Newton: proposed) fell below ``xtol``
    NO_DESCENT = 2        #: no step longer than ``xtol`` decreases the cost (a kink, a cell boundary)
    MAX_ITERATIONS = 3    #: the budget ran out
    NO_OVERLAP = 4        #: no known cell of B falls on a known cell of A at the initial pose
    SEPARATED = 5         #: the minimum found has no overlap: B was pushed off A
    NO_INFORMATION = 6    #: the discrepancy is flat in every direction at the pose

    @property
    def converged(self) -> bool:
        """True for the optimisers' three ways of stopping at a minimum."""
        return self in (Status.GRADIENT, Status.STEP, Status.NO_DESCENT)


MESSAGES = {
    Status.GRADIENT: "converged: gradient below tolerance",
    Status.STEP: "converged: step below tolerance",
    Status.NO_DESCENT: "converged: no descent at the resolution of the cost (a kink or a cell boundary)",
    Status.MAX_ITERATIONS: "not converged: maximum number of iterations reached",
    Status.NO_OVERLAP: "not matched: the maps do not overlap at the initial pose (no known cell of B "
                       "falls on a known cell of A)",
    Status.SEPARATED: "not matched: the minimum found has no overlap; B was pushed off A, so near the "
                      "initial pose no overlapping placement is free of conflicts (check the maps and r0)",
    Status.NO_INFORMATION: "not matched: the discrepancy is flat in every direction here (no structure "
                           "in the overlap), so the maps say nothing about the pose",
}
