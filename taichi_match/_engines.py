"""Who evaluates the discrepancy: the seam between the matcher and its backends.

An engine evaluates e for a batch of poses r_A2B (N, 3) of prepared map B in prepared map A, in
one launch, with the overlap (known cells of B on known cells of A) where asked. A backend
provides two evaluators, the protocols below; ``BACKENDS`` names them:

- "taichi": batched Taichi kernels over affine index arrays (``_kernels``, ``_envelope``);
- "numpy": the plain reference written from the paper on the maps themselves (``_reference``,
  ``_envelope.NumpyEnvelope``): the tests' oracle and the benchmarks' baseline.

Another backend (a Taichi fork, say) is one new module providing the two evaluators, and one
line in ``BACKENDS``. The NumPy reference takes poses, not the kernels' affine arrays, so that it
stays independent of eq. (5)'s affine form (``_cost.AffineMap``), which the tests check with it.
"""

from typing import Callable, NamedTuple, Optional, Protocol, Tuple

import numpy as np

from ._errors import InvalidOptionError
from ._prepared import PreparedMap

__all__ = ["ENGINES", "BACKENDS", "Backend", "DenseEvaluator", "EnvelopeEvaluator", "make_engine"]

# count="any": this many of B's walls landing on known cells of A stand for the overlap count
OVERLAP_PROOF_WALLS = 10


class DenseEvaluator(Protocol):
    """Eq. (6) (|p_A - p_B| over B's known cells) between two prepared maps' ``lower`` grids."""

    counts_free: bool      # whether counting the overlap comes with the same launch

    def __call__(self, poses: np.ndarray, count: str = "all") -> Tuple[np.ndarray, Optional[np.ndarray]]:
        """(e (N,), overlap (N,) int64 or None). ``count`` says whose overlap is needed: "all"
        poses, only the "first" (the others may be 0), "any" (a lower bound on the first's, > 0
        exactly when it is) or "none" (None may be returned)."""

    def bilinear(self, poses: np.ndarray) -> Tuple[np.ndarray, np.ndarray, np.ndarray]:
        """A interpolated bilinearly between its cell centres: (e (N,), overlap (N,), gradient of
        e in (x, y, theta) (N, 3))."""


class EnvelopeEvaluator(Protocol):
    """The envelope discrepancy (``_envelope``) between two maps prepared with the envelope blur."""

    def __call__(self, poses: np.ndarray, count: str = "all") -> Tuple[np.ndarray, Optional[np.ndarray]]:
        """(e (N,), walls landing on known cells of the other map (N,) int64, or None for
        ``count`` "none"); with "b_walls" B's walls alone."""


class Backend(NamedTuple):
    """A backend: how to make its two evaluators from prepared maps."""

    dense: Callable[[PreparedMap, PreparedMap, bool], DenseEvaluator]     # (a, b, count_only)
    # (a, b, unknown_cost, bilinear, edge_unknown)
    envelope: Callable[[PreparedMap, PreparedMap, float, bool, bool], EnvelopeEvaluator]


def _taichi() -> Backend:
    from ._envelope import EnvelopeEngine
    from ._kernels import TaichiDense

    return Backend(TaichiDense, EnvelopeEngine)


def _numpy() -> Backend:
    from ._envelope import NumpyEnvelope
    from ._reference import NumpyDense

    return Backend(lambda a, b, count_only: NumpyDense(a.lower, b.lower),
                   lambda a, b, unknown_cost, bilinear, edge: NumpyEnvelope(a.lower, b.lower, a.blur_width,
                                                                            b.blur_width, unknown_cost, bilinear, edge))


BACKENDS = {"taichi": _taichi, "numpy": _numpy}     # name -> the backend (its modules imported when first used)
ENGINES = tuple(BACKENDS)


def make_engine(name: str, a: PreparedMap, b: PreparedMap, unknown_cost: float = 0.0, interpolation: str = "nearest",
                grid_edge: str = "free"):
    """The engine of backend ``name`` for B in A: eq. (6) (a ``DenseEvaluator``, whose ``bilinear``
    evaluates the interpolated e), or for maps prepared with the "envelope" blur the envelope
    discrepancy (``EnvelopeDiscrepancy``), its walls' costs interpolated with ``interpolation``
    "bilinear", a wall off the other map's grid paying ``unknown_cost`` with ``grid_edge``
    "unknown" (``MatchOptions``)."""
    if name not in BACKENDS:
        raise InvalidOptionError(f"engine must be one of {ENGINES}; got {name!r}")
    if (a.blur_kind == "envelope") != (b.blur_kind == "envelope"):
        raise InvalidOptionError("both maps must be prepared with the same kind of blur")
    backend = BACKENDS[name]()
    if a.blur_kind == "envelope":
        return EnvelopeDiscrepancy(backend, a, b, unknown_cost, interpolation == "bilinear", grid_edge == "unknown")
    return backend.dense(a, b, False)


class EnvelopeDiscrepancy:
    """The envelope discrepancy with the dense evaluator's interface; ``bilinear``: its walls' costs
    interpolated between cell centres (``_envelope``), its derivatives still from the stencils.

    The overlap (known cells of B on known cells of A, as for eq. 6) takes a second launch of the
    dense evaluator on the maps themselves, for the poses ``count`` asks for; for "any", only
    when fewer than ``OVERLAP_PROOF_WALLS`` of B's walls landing on known cells of A (counted in
    the envelope's launch, free) do not already show it (``dense_launches`` counts those launches).
    """

    counts_free = False          # counting the overlap costs a launch of its own

    def __init__(self, backend: Backend, a: PreparedMap, b: PreparedMap, unknown_cost: float, bilinear: bool = False,
                 edge_unknown: bool = False):
        self._evaluate = backend.envelope(a, b, unknown_cost, bilinear, edge_unknown)
        self._make_dense = lambda: backend.dense(a, b, True)
        self._dense_evaluator = None
        self.dense_launches = 0          # overlap counts that count="any" could not spare

    @property
    def _dense(self):
        """The dense evaluator that counts the overlap, made when first needed (a middle pyramid
        level never counts)."""
        if self._dense_evaluator is None:
            self._dense_evaluator = self._make_dense()
        return self._dense_evaluator

    def __call__(self, poses, count="all"):
        poses = np.asarray(poses, dtype=np.float64).reshape(-1, 3)
        if count == "any":
            # whether the maps overlap at the first pose: B's walls landing on known cells of A
            # are known cells of B doing so; the dense launch only when fewer than
            # ``OVERLAP_PROOF_WALLS`` show it (the two evaluations round the lookup differently)
            values, walls = self._evaluate(poses, "b_walls")
            counts = np.zeros(len(poses), dtype=np.int64)
            if walls[0] >= OVERLAP_PROOF_WALLS:
                counts[0] = walls[0]
            else:
                self.dense_launches += 1
                counts[:1] = self._dense(poses[:1], "all")[1]
            return values, counts
        values = self._evaluate(poses, "none")[0]
        if count == "none":
            return values, None
        if count == "first":
            counts = np.zeros(len(poses), dtype=np.int64)
            counts[:1] = self._dense(poses[:1], "all")[1]
            return values, counts
        return values, self._dense(poses, "all")[1]

    def overlap(self, poses):
        """The overlap (N,) at each pose, one launch."""
        return self._dense(poses, "all")[1]

    def bilinear(self, poses):
        raise InvalidOptionError("the envelope discrepancy has no analytic gradient: with interpolation="
                                 "\"bilinear\" its walls' costs are interpolated and its derivatives come from the "
                                 "stencils (``LevelCost``)")
