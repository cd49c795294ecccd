"""The cost as the optimiser sees it: eq. (5) as an affine index map, eq. (7)-(8), the
finite-difference stencils of eq. (10)-(12), and h on one pyramid level (``LevelCost``).

Pose components are ordered (x, y, theta); ``steps = (eps_x, eps_y, eps_theta)`` in metres and
radians. All stencil poses a step needs are returned as one (N, 3) batch so that one kernel launch
evaluates them.
"""

import functools

import numpy as np

from ._covariance import centroid_metric
from ._grid import GridMap

__all__ = [
    "AffineMap", "prior", "prior_terms", "prior_values", "prior_hessian", "gradient_stencil", "gradient_from_stencil",
    "hessian_stencil", "hessian_from_stencil", "Counter", "LevelCost",
]

# ---------------------------------------------------------------------------------------------
# Eq. (5): f(c_B) = lambda_A^-1(T(r_AB) lambda_B(c_B)), as affine coefficients per pose.


class AffineMap:
    """Eq. (5) for one pair of maps: per pose, the (N, 6) coefficients mapping B's cell (i, j) to
    A's (padded) cell coordinates.

    ``u = c0*j + c1*i + c2`` is A's column and ``v = c3*j + c4*i + c5`` A's row, both offset by
    ``pad`` for A's ring of unknown cells; the cell is (floor(v), floor(u)). B's cells are taken
    at their centres (eq. 2), placed in B's frame by B's corner pose, moved into A's frame by the
    pose (eq. 4), and into A's grid by the inverse of A's corner pose and resolution (eq. 3).
    The coefficients are linear in (cos theta, sin theta, x, y, 1), so a batch is one product with
    the 5 x 6 ``matrix`` made once per pair (a few NumPy calls instead of thirty: this runs before
    every launch; the envelope kernel takes the matrix and does the product per pose itself).
    """

    def __init__(self, a: GridMap, b: GridMap, pad: int, b_pad: int = 0):
        """``pad``: the ring around A's grid (``_kernels.PAD``); ``b_pad``: around B's, whose cell (i, j) is then B's
        cell (i - b_pad, j - b_pad)."""
        # plain floats (the same IEEE arithmetic as NumPy's scalars, a tenth of the time)
        bx, by, b_yaw = (float(v) for v in b.corner_pose)
        ax, ay, a_yaw = (float(v) for v in a.corner_pose)
        ratio = float(b.resolution) / float(a.resolution)
        cd, sd = float(np.cos(b_yaw - a_yaw)), float(np.sin(b_yaw - a_yaw))
        ca, sa = float(np.cos(a_yaw)) / a.resolution, float(np.sin(a_yaw)) / a.resolution

        def coefficients(c, s, x, y, one):
            m00 = (c * cd - s * sd) * ratio       # B's grid axes in A's grid: theta + yaw_B - yaw_A
            m10 = (s * cd + c * sd) * ratio
            cx = c * bx - s * by + x - ax * one   # B's corner in A's frame, in A's grid
            cy = s * bx + c * by + y - ay * one
            u0 = ca * cx + sa * cy + pad * one
            v0 = ca * cy - sa * cx + pad * one
            # cell centres: + 1/2 cell along both of B's axes (less B's ring)
            centre = 0.5 - b_pad
            return [m00, -m10, u0 + centre * (m00 - m10), m10, m00, v0 + centre * (m10 + m00)]

        #: (5, 6): the coefficients of a pose r are (cos theta, sin theta, x, y, 1) @ matrix
        self.matrix = np.array([coefficients(*row) for row in ((1.0, 0.0, 0.0, 0.0, 0.0), (0.0, 1.0, 0.0, 0.0, 0.0),
                                (0.0, 0.0, 1.0, 0.0, 0.0), (0.0, 0.0, 0.0, 1.0, 0.0), (0.0, 0.0, 0.0, 0.0, 1.0))])

    def __call__(self, poses):
        poses = np.asarray(poses, dtype=np.float64).reshape(-1, 3)
        features = np.empty((len(poses), 5))
        np.cos(poses[:, 2], out=features[:, 0])
        np.sin(poses[:, 2], out=features[:, 1])
        features[:, 2], features[:, 3] = poses[:, 0], poses[:, 1]
        features[:, 4] = 1.0
        return features @ self.matrix


# ---------------------------------------------------------------------------------------------
# Eq. (7)-(8): h = e + K * ||r - r0||,  ||r|| = sqrt(x^2 + y^2 + L^2 theta^2).


def prior_terms(pose, initial_pose, weight, rotation_scale, min_norm):
    """K * ||r - r0|| (eq. 7-8) at r: (value, gradient, curvature for a Newton model).

    The gradient at r = r0 is taken as 0. The curvature is ``K W / ||r - r0||``, the Hessian of
    the quadratic that touches the cone at r from above (as in iteratively reweighted least
    squares). The cone itself is flat along r - r0, and a model with that zero curvature would
    step past r0 to the edge of its trust region. The norm is taken as at least ``min_norm`` there.
    """
    d = np.asarray(pose, dtype=np.float64) - initial_pose
    w, diagonal = _prior_metric(rotation_scale)
    norm = float(np.sqrt(np.dot(w * d, d)))
    curvature = weight * diagonal / max(norm, min_norm)
    if norm == 0.0:
        return 0.0, np.zeros(3), curvature
    return weight * norm, weight * w * d / norm, curvature


@functools.lru_cache(maxsize=16)
def _prior_metric(rotation_scale):
    """(W's diagonal (1, 1, L^2), W) of the norm, read-only: made once per rotation scale (this
    runs at every launch)."""
    w = np.array([1.0, 1.0, rotation_scale**2])
    diagonal = np.diag(w)
    w.setflags(write=False)
    diagonal.setflags(write=False)
    return w, diagonal


def prior(pose, initial_pose, weight, rotation_scale):
    """Value and gradient of K * ||r - r0|| (``prior_terms``)."""
    return prior_terms(pose, initial_pose, weight, rotation_scale, 1.0)[:2]


def prior_hessian(pose, initial_pose, weight, rotation_scale, min_norm):
    """The curvature of K * ||r - r0|| for a Newton model (``prior_terms``)."""
    return prior_terms(pose, initial_pose, weight, rotation_scale, min_norm)[2]


def prior_values(poses, initial_pose, weight, rotation_scale):
    """K * ||r - r0|| (eq. 7-8) for an (N, 3) batch of poses."""
    d = np.asarray(poses, dtype=np.float64) - initial_pose
    return weight * np.sqrt(d[:, 0] ** 2 + d[:, 1] ** 2 + (rotation_scale * d[:, 2]) ** 2)


# ---------------------------------------------------------------------------------------------
# Eq. (10): four-point central differences for the gradient.

_GRAD_OFFSETS = (-2.0, -1.0, 1.0, 2.0)
_GRAD_WEIGHTS = np.array([1.0, -8.0, 8.0, -1.0]) / 12.0
# (13, 3) offsets in units of the steps: the centre, then -2, -1, +1, +2 along x, y, theta
_GRAD_STENCIL = np.vstack([np.zeros(3)] + [np.outer(_GRAD_OFFSETS, np.eye(3)[d]) for d in range(3)])


def _offsets(stencil, steps, basis):
    """Stencil offsets (in steps) as pose offsets: along the columns of ``basis`` (3 x 3, None:
    the axes x, y, theta), the derivatives from it then being along those directions."""
    offsets = stencil * np.asarray(steps, dtype=np.float64)
    return offsets if basis is None else offsets @ np.asarray(basis, dtype=np.float64).T


def gradient_stencil(pose, steps, basis=None):
    """(13, 3) poses: the centre, then for x, y, theta (or the columns of ``basis``) the offsets
    -2, -1, +1, +2 steps."""
    return np.asarray(pose, dtype=np.float64) + _offsets(_GRAD_STENCIL, steps, basis)


def gradient_from_stencil(values, steps):
    """Eq. (10) from the 13 values of ``gradient_stencil`` (or the first 13 of a longer batch)."""
    values = np.asarray(values, dtype=np.float64)
    return values[1:13].reshape(3, 4) @ _GRAD_WEIGHTS / steps


# ---------------------------------------------------------------------------------------------
# Eq. (11)-(12): the numeric Hessian (5-point diagonal, 4-point mixed terms).

_PAIRS = ((0, 1), (0, 2), (1, 2))
_CROSS_SIGNS = ((-1, -1), (-1, 1), (1, -1), (1, 1))
_CROSS_WEIGHTS = np.array([1.0, -1.0, -1.0, 1.0]) / 4.0
_DIAG_WEIGHTS = np.array([-1.0, 16.0, 16.0, -1.0]) / 12.0     # at -2, -1, +1, +2 steps; centre -30/12
# (25, 3) offsets: the 13 of the gradient stencil, then 4 corners for each pair (x,y), (x,t), (y,t)
_HESS_STENCIL = np.vstack([_GRAD_STENCIL] + [
    np.array([s1 * np.eye(3)[d1] + s2 * np.eye(3)[d2] for s1, s2 in _CROSS_SIGNS]) for d1, d2 in _PAIRS])


def hessian_stencil(pose, steps, basis=None):
    """(25, 3) poses: the 13 of ``gradient_stencil``, then 4 corners for each pair (x,y), (x,t), (y,t)."""
    return np.asarray(pose, dtype=np.float64) + _offsets(_HESS_STENCIL, steps, basis)


def _hessian_weights():
    """(9, 25): the row-major 3x3 Hessian (times steps_i * steps_j) as weights of the 25 values."""
    w = np.zeros((3, 3, 25))
    for d in range(3):
        w[d, d, 1 + 4 * d: 5 + 4 * d] = _DIAG_WEIGHTS
        w[d, d, 0] = -30.0 / 12.0
    for p, (d1, d2) in enumerate(_PAIRS):
        w[d1, d2, 13 + 4 * p: 17 + 4 * p] = w[d2, d1, 13 + 4 * p: 17 + 4 * p] = _CROSS_WEIGHTS
    return w.reshape(9, 25)


_HESS_WEIGHTS = _hessian_weights()


def hessian_from_stencil(values, steps):
    """Eq. (12) from the 25 values of ``hessian_stencil``; returns the symmetric 3x3 Hessian."""
    return _hessian(np.asarray(values, dtype=np.float64), np.outer(steps, steps))


def _hessian(values, step_products):
    """Eq. (12) from the 25 stencil values and the steps' products ``outer(steps, steps)``."""
    return (_HESS_WEIGHTS @ values).reshape(3, 3) / step_products


# ---------------------------------------------------------------------------------------------
# h (eq. 8) on one pyramid level, in the coordinates the optimisers work in.


class Counter:
    """Kernel launches and poses evaluated during one match."""

    def __init__(self):
        self.launches = 0
        self.poses = 0


class LevelCost:
    """h (eq. 8) on one level of the pyramid, as the optimisers see it.

    Poses r are (x, y, theta); the optimisers work in z = M r, all in metres (see ``__init__``),
    so that a unit step moves a typical cell of B by about a metre whichever way it goes. K follows
    the number of B's known cells at this level.
    With ``interpolation="nearest"`` (the paper's e) derivatives come from the stencils of
    eq. (10)-(12); with "bilinear" the gradient of the paper's e is analytic (one pose) and the
    Hessian is the central difference of gradients at +-1 step on each axis (7 poses); the envelope
    discrepancy, bilinear or not, takes the stencils.
    """

    def __init__(self, engine, pa, pb, prep_b, opts, r0, full_weight, counter):
        """``engine`` evaluates e between the level's maps ``pa`` and ``pb`` (``make_engine``);
        ``prep_b`` is B as given, ``full_weight`` the K of eq. (8) there, ``counter`` a ``Counter``."""
        self._engine = engine
        self._bilinear = opts.analytic_gradient
        self._counter = counter
        self._r0 = r0
        self._rotation_scale = opts.rotation_scale
        self.steps = opts.steps(pa.resolution, prep_b.radius)
        self.weight = full_weight * pb.n_known / max(prep_b.n_known, 1)
        # z = M r: B's centroid's position in A and theta times B's rms radius about its centroid,
        # linearised at r0's theta. A unit step in z then moves a typical cell of B by about a
        # metre whichever way, also when B's frame origin lies far from its cells (ROS maps put it
        # at a corner, tens of metres away): there a rotation about the origin is mostly a
        # translation, and a trust region in (x, y, theta * radius) crawled along the valley of
        # rotations about the map's own centre (a self-match from 0.02 rad stopped 0.4 deg off).
        self._to_z = centroid_metric(prep_b.centroid, prep_b.spread, r0[2])
        self._from_z = np.linalg.inv(self._to_z)
        # the stencils' steps in z: one cell of A along x and y, and a rotation about B's centroid
        # that moves a typical cell of B by one cell (the derivatives of e then come in z directly;
        # taken about B's frame origin they hid the rotation about B's centre in the rounding of
        # far larger terms)
        self.z_steps = np.array([self.steps[0], self.steps[1],
                                 self.steps[0] if opts.rotation_step is None else opts.rotation_step * prep_b.spread])
        self.max_step = opts.max_step if opts.max_step is not None else max(opts.blur / 2.0, 4.0 * self.steps[0])
        # the Hessian stencil's offsets in r and its steps' products, the same at every launch
        self._hessian_offsets = _offsets(_HESS_STENCIL, self.z_steps, self._from_z)
        self._step_products = np.outer(self.z_steps, self.z_steps)

    @property
    def counts_free(self):
        """Whether the engine counts the overlap in the same launch as e."""
        return self._engine.counts_free

    def to_z(self, r):
        """The optimiser's coordinates z = M r of a pose r."""
        return self._to_z @ np.asarray(r, dtype=np.float64)

    def to_r(self, z):
        """The pose r of the optimiser's coordinates z."""
        return self._from_z @ np.asarray(z, dtype=np.float64)

    def grad_z(self, grad_r):
        """A gradient in r as a gradient in z."""
        return self._from_z.T @ grad_r

    def _count(self, poses, count="none"):
        self._counter.launches += 1 if count in ("none", "any") or self.counts_free else 2
        self._counter.poses += poses

    def overlap(self, r):
        """The overlap at r (one launch)."""
        self._count(1)
        return int(self._engine.overlap(np.asarray(r, dtype=np.float64)[None, :])[0])

    def evaluate(self, poses, count="first"):
        """e and the overlap (see ``make_engine`` for ``count``) for a batch of poses: one launch."""
        self._count(len(poses), count)
        if self._bilinear:
            return self._engine.bilinear(poses)[:2]
        return self._engine(poses, count)

    def value_and_gradient(self, r, count="none"):
        """h and its gradient in r at r: the 13-pose stencil (eq. 10) in z, or one pose (bilinear)."""
        if self._bilinear:
            self._count(1)
            values, counts, grads = self._engine.bilinear(r[None, :])
            grad = grads[0]
        else:
            values, counts = self.evaluate(gradient_stencil(r, self.z_steps, self._from_z), count)
            grad = self._to_z.T @ gradient_from_stencil(values, self.z_steps)
        p_val, p_grad = prior(r, self._r0, self.weight, self._rotation_scale)
        return values[0] + p_val, grad + p_grad, counts

    def value_gradient_hessian(self, z, count="none"):
        """h, its gradient and Hessian in z (the prior's included), from one launch; extra:
        (e, overlap or None, Hessian of e in r) at z."""
        r = self.to_r(z)
        if self._bilinear:
            self._count(7)
            poses = r + np.vstack([np.zeros(3), np.diag(self.steps), -np.diag(self.steps)])
            values, counts, grads = self._engine.bilinear(poses)
            hess = (grads[1:4] - grads[4:7]).T / (2.0 * self.steps)      # column q: d grad / d r_q
            hess = 0.5 * (hess + hess.T)
            grad_z, hess_z = self.grad_z(grads[0]), self._from_z.T @ hess @ self._from_z
        else:
            self._count(25, count)
            spared = getattr(self._engine, "dense_launches", 0)        # count="any": a launch only if needed
            values, counts = self._engine(r + self._hessian_offsets, count)       # ``hessian_stencil``
            self._counter.launches += getattr(self._engine, "dense_launches", 0) - spared
            grad_z = gradient_from_stencil(values, self.z_steps)
            hess_z = _hessian(values, self._step_products)
            hess = self._to_z.T @ hess_z @ self._to_z                      # eq. (12) in r
        p_val, p_grad, h_prior = prior_terms(r, self._r0, self.weight, self._rotation_scale, self.steps[0])
        extra = (values[0], None if counts is None else counts[0], hess)
        return (values[0] + p_val, grad_z + self.grad_z(p_grad),
                hess_z + self._from_z.T @ h_prior @ self._from_z, extra)

    def fun_grad(self, z):
        """h and its gradient in z (for BFGS)."""
        h, grad, _ = self.value_and_gradient(self.to_r(z))
        return h, self.grad_z(grad)

    def batch(self, zs):
        """h at a batch of points z, one launch (for the compass search)."""
        rs = zs @ self._from_z.T
        e_values, _ = self.evaluate(rs, count="none")
        return e_values + prior_values(rs, self._r0, self.weight, self._rotation_scale)
