"""``MatchResult.information`` (the numeric Hessian of e at the pose found, eq. 12) against SciPy.

The oracle is independent of the package: the maps are blurred by SciPy's ``gaussian_filter``
(the normalised convolution over known cells that ``_blur`` documents for the paper's options),
e (eq. 6, or its bilinear form) is summed in plain NumPy, and ``scipy.differentiate.hessian``
differentiates it with its own stencil and steps. tests/test_stencils.py checks the kernel's
25-pose stencil against SciPy at given steps in r; this checks the whole path behind
``information``: the pose the matcher reports, its steps (one cell of A in x and y, a rotation
about B's centroid moving a typical cell by one cell), the change of coordinates from the
optimiser's z back to (x, y, theta), and the bilinear Hessian from analytic gradients.

e on a grid is piecewise constant (nearest cell) or piecewise bilinear below the scale of a cell,
so SciPy's steps are 2 cells (in units where a rotation moves a typical cell of B by one cell),
with its 4th-order stencil and no extrapolation (``maxiter=1``: Richardson extrapolation assumes
smoothness that the staircase does not have).
"""

import numpy as np
import pytest
from scipy import differentiate, ndimage

from taichi_match import GridMap, Matcher, MatchOptions

RES = 0.05
TRUTH = np.array([0.12, -0.08, 0.04])
BLUR = 0.5                          # MatchOptions.paper()'s Gaussian, metres


def smooth_field(seed):
    """A smooth occupancy field in world coordinates: a logistic of six random plane waves."""
    rng = np.random.default_rng(seed)
    waves, phases, amplitudes = rng.normal(0.0, 1.2, (6, 2)), rng.uniform(0, 2 * np.pi, 6), rng.uniform(0.3, 1.0, 6)

    def field(x, y):
        v = sum(a * np.sin(k[0] * x + k[1] * y + p) for a, k, p in zip(amplitudes, waves, phases))
        return 1.0 / (1.0 + np.exp(-v))

    return field


def sampled(field, shape, pose=(0.0, 0.0, 0.0)):
    """``field`` at the cell centres of a grid centred on its frame's origin, that frame at
    r_A2B = ``pose`` in the field's frame."""
    origin = (-shape[1] * RES / 2, -shape[0] * RES / 2)
    rows, cols = np.indices(shape)
    xb, yb = origin[0] + (cols + 0.5) * RES, origin[1] + (rows + 0.5) * RES
    x, y, t = pose
    return field(np.cos(t) * xb - np.sin(t) * yb + x, np.sin(t) * xb + np.cos(t) * yb + y), origin


@pytest.fixture(scope="module", params=[11, 13])
def pair(request):
    """A smooth map A and a map B of the same place seen with less contrast and some noise
    (0.25 + 0.5 p + N(0, 0.02)), at r_A2B = TRUTH: the two never agree exactly, so |p_A - p_B|
    changes sign only along curves and e is smooth at the scale of a few cells (a map against
    itself would give e a cone at the truth, whose finite-difference Hessian grows as 1 / step)."""
    field = smooth_field(request.param)
    prob_a, origin_a = sampled(field, (240, 280))
    prob_b, origin_b = sampled(field, (180, 220), TRUTH)
    noise = np.random.default_rng(request.param + 1).standard_normal(prob_b.shape)
    prob_b = np.clip(0.25 + 0.5 * prob_b + 0.02 * noise, 0.0, 1.0)
    return GridMap(prob_a, RES, origin_a), GridMap(prob_b, RES, origin_b)


def gaussian_blur(grid):
    """The paper's blur with SciPy: normalised convolution (every cell is known here)."""
    sigma = BLUR / grid.resolution
    known = ~np.isnan(grid.prob)
    num = ndimage.gaussian_filter(np.where(known, grid.prob, 0.0), sigma, mode="constant", truncate=3.0)
    den = ndimage.gaussian_filter(known.astype(float), sigma, mode="constant", truncate=3.0)
    return num / den


def plain_discrepancy(a, b, interpolation):
    """e(r) on the blurred maps in plain NumPy, and B's known cells' centres (in B's frame)."""
    blurred_a, blurred_b = gaussian_blur(a), gaussian_blur(b)
    rows, cols = np.indices(b.shape).reshape(2, -1)
    centres = np.column_stack([b.origin[0] + (cols + 0.5) * RES, b.origin[1] + (rows + 0.5) * RES])
    values_b = blurred_b[rows, cols]

    def e(r):
        x, y, t = r
        u = (np.cos(t) * centres[:, 0] - np.sin(t) * centres[:, 1] + x - a.origin[0]) / RES
        v = (np.sin(t) * centres[:, 0] + np.cos(t) * centres[:, 1] + y - a.origin[1]) / RES
        if interpolation == "nearest":          # eq. (6): the cell of A under B's cell centre
            j, i = np.floor(u).astype(int), np.floor(v).astype(int)
            ok = (i >= 0) & (i < a.shape[0]) & (j >= 0) & (j < a.shape[1])
            return float(np.abs(blurred_a[i[ok], j[ok]] - values_b[ok]).sum())
        u, v = u - 0.5, v - 0.5                 # bilinear between A's cell centres, where all four exist
        j, i = np.floor(u).astype(int), np.floor(v).astype(int)
        ok = (i >= 0) & (i + 1 < a.shape[0]) & (j >= 0) & (j + 1 < a.shape[1])
        fu, fv, i, j = u[ok] - j[ok], v[ok] - i[ok], i[ok], j[ok]
        p_a = (blurred_a[i, j] * (1 - fu) * (1 - fv) + blurred_a[i, j + 1] * fu * (1 - fv)
               + blurred_a[i + 1, j] * (1 - fu) * fv + blurred_a[i + 1, j + 1] * fu * fv)
        return float(np.abs(p_a - values_b[ok]).sum())

    return e, centres


def relative_error(h, reference):
    """max |v.H.v / v.R.v - 1| over all directions v: the spectral norm of R^-1/2 H R^-1/2 - I,
    whatever the units of x, y and theta."""
    w, v = np.linalg.eigh(reference)
    assert w.min() > 0, w
    root = (v / np.sqrt(w)) @ v.T
    return float(np.abs(np.linalg.eigvalsh(root @ h @ root) - 1.0).max())


def scipy_hessian(e, pose, centres, step_cells=2.0):
    """SciPy's Hessian of e at ``pose`` in (x, y, theta), differentiated in cells: a unit moves B
    by one cell of A along x or y, or turns it about its frame's origin (its centroid here) so
    that a typical cell moves by one cell."""
    spread = np.sqrt(np.mean(np.sum((centres - centres.mean(axis=0)) ** 2, axis=1)))
    units = np.array([RES, RES, RES / spread])

    def e_cells(u):                      # SciPy passes u of shape (3, ...)
        u = np.asarray(u)
        flat = u.reshape(3, -1).T
        return np.array([e(pose + units * q) for q in flat]).reshape(u.shape[1:])

    res = differentiate.hessian(e_cells, np.zeros(3), initial_step=step_cells, order=4, maxiter=1)
    return res.ddf / np.outer(units, units)


def test_the_bilinear_information_is_scipys_hessian_of_e(pair):
    """Measured on seeds 11-15 (two run here): 1.2-3.5 % apart in the worst direction, x and y
    curvatures within 2 %, with SciPy's steps of 2 cells (of 3 cells: within 4 %); SciPy's
    2nd-order stencil at 2 cells is 4-9 % apart (its truncation error on the field's curvature).
    The 10 % tolerance covers that spread, which comes from the staircase of B's 40k cells
    crossing the bilinear patches' edges; a wrong unit or step for theta (a factor 2 on its
    step gives 190-320 % here) or a Hessian at the wrong pose would exceed it."""
    a, b = pair
    res = Matcher(MatchOptions.paper(interpolation="bilinear")).match(a, b, TRUTH + [0.1, -0.05, 0.03])
    assert res.converged, res
    e, centres = plain_discrepancy(a, b, "bilinear")
    # the oracle computes the matcher's e (float32 sums in the kernel)
    assert res.discrepancy == pytest.approx(e(res.pose), rel=1e-5)
    reference = scipy_hessian(e, res.pose, centres)
    assert relative_error(res.information, reference) <= 0.10, (res.information, reference)
    assert np.allclose(np.diag(res.information)[:2], np.diag(reference)[:2], rtol=0.05)


def test_the_nearest_cell_information_is_scipys_hessian_of_e_loosely(pair):
    """eq. (6) with nearest-cell lookup (the paper's options): e is a fine staircase, and the pose
    found is a minimum of that staircase, where a second difference is biased by the centre's
    own rounding. Measured on seeds 11-15 (two run here) against SciPy at 2 cells: the x and y
    curvatures agree within 1 %, theta's is 0.72-1.30 times SciPy's, the worst direction 2-30 %
    apart. So: 5 % along x and y, and a loose 50 % in any direction (a factor 2 on theta's step
    gives 190-420 % here)."""
    a, b = pair
    res = Matcher(MatchOptions.paper()).match(a, b, TRUTH + [0.1, -0.05, 0.03])
    assert res.converged, res
    e, centres = plain_discrepancy(a, b, "nearest")
    assert res.discrepancy == pytest.approx(e(res.pose), rel=1e-5)
    reference = scipy_hessian(e, res.pose, centres)
    assert np.allclose(np.diag(res.information)[:2], np.diag(reference)[:2], rtol=0.05)
    assert relative_error(res.information, reference) <= 0.5, (res.information, reference)
