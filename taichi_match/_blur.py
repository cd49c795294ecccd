"""Blurring a map once before matching (sec. 3.2 of the paper).

The paper applies "a standard blurring algorithm that introduces a gradient of grey from black
(occupied) to white (free) cells" and leaves the choice open. Two are offered:

``"gaussian"`` (the default): a Gaussian of standard deviation ``width`` metres, normalised over
the known cells (normalised convolution)::

    p'(c) = sum_k G(c - k) p(k) / sum_k G(c - k)      over known cells k, for known c,

unknown cells stay unknown and do not pull the grey level toward any value. It is linear, so a
stray occupied cell (a speckle, clutter that differs between two maps) adds only a faint smudge.

``"ramp"``: a linear ramp in the distance to the nearest occupied cell (p >= ``occupied``)::

    p'(c) = max(p(c), p(o) * max(0, 1 - d(c, o) / width))

It keeps walls at full strength and gives e a constant slope out to ``width``, but every stray
occupied cell becomes a full-height cone ``width`` wide, so on noisy maps the discrepancy floor
rises until moving the maps apart (zero overlap) is cheaper than aligning them.

``"envelope"``: the Gaussian envelope of the occupied cells (p >= ``occupied``)::

    hi(c) = max(p(c), max_o p(o) * exp(-d(c, o)^2 / (2 width^2)))

over the occupied cells o: 1 on a wall, falling smoothly to 0 within a few ``width``. When every
wall is 1 (trinary maps) the nearest wall gives the maximum, and one distance transform gives hi;
with grey walls (coarse pyramid levels) the transform of ``-2 width^2 ln p(o)`` does
(``_distance.squared_distance``: the lower envelope of the walls' parabolas, lifted by their
weight), where the nearest wall's own value once stood in for the maximum (a weak wall next to a
strong one hid it, and SciPy's feature transform, three times slower, had to find it).
A one-cell laser wall keeps full strength, where a normalised Gaussian dilutes it to
1 / (2.5 sigma) and leaves e lower away from the truth (measured on laser-built submaps in
bench/TUNING.md). It serves the envelope discrepancy (``_envelope``), not |p_A - p_B|.

The measurements behind the default are in ``bench/TUNING.md``.
"""

from typing import Literal

import numpy as np

from ._distance import squared_distance, wall_distance
from ._errors import InvalidOptionError
from ._grid import GridMap

__all__ = ["blur", "blur_everywhere", "wall_transform", "BLUR_KINDS"]

BLUR_KINDS = ("gaussian", "ramp", "envelope")


# Kernels at least this many taps wide are applied by FFT: the same sums (to rounding), in time
# independent of the width (measured on 480 x 480 cells, sigma = 20 cells: 15 ms direct, 6 ms FFT).
_FFT_MIN_TAPS = 25
_TRUNCATE = 3.0


def gaussian_filter(stack, sigma):
    """``scipy.ndimage.gaussian_filter(a, sigma, mode="constant", truncate=3)`` of each 2-D array
    of ``stack`` (shape (k, rows, cols)): the normalised, truncated Gaussian, zeros outside."""
    # beyond the map's own extent a wider kernel changes nothing (zeros outside): a blur of a
    # million cells costs no more than one as wide as the map
    radius = int(min(_TRUNCATE * sigma + 0.5, max(stack.shape[1:])))
    if 2 * radius + 1 < _FFT_MIN_TAPS:
        from scipy import ndimage  # SciPy is imported where used: `taichi-match --help` answers fast

        return np.stack([ndimage.gaussian_filter(a, sigma, mode="constant", truncate=_TRUNCATE) for a in stack])
    taps = np.exp(-0.5 * (np.arange(-radius, radius + 1) / sigma) ** 2)
    taps /= taps.sum()
    return _convolve_same(_convolve_same(stack, taps, axis=2), taps, axis=1)


def _convolve_same(x, taps, axis):
    """Linear convolution of ``x`` with the odd-length ``taps`` along ``axis`` by FFT, zeros
    outside, cropped to x's size (centred, as ``mode="same"``). scipy.fft, not scipy.signal, whose
    import alone takes about 0.4 s."""
    from scipy import fft

    size = x.shape[axis]
    n = fft.next_fast_len(size + len(taps) - 1, real=True)
    spectrum = fft.rfft(x, n, axis=axis) * np.expand_dims(fft.rfft(taps, n), tuple(range(1, x.ndim - axis)))
    full = fft.irfft(spectrum, n, axis=axis)
    start = (len(taps) - 1) // 2
    return np.take(full, np.arange(start, start + size), axis=axis)


def wall_transform(grid: GridMap, occupied: float = 0.5):
    """(distance, (rows, cols) or None): per cell the distance in cells to the nearest cell with
    p >= ``occupied`` ("wall") and that cell's index; None when the map has no wall. The "ramp"
    and "envelope" blurs and the verdict's wall distances use it.

    When every wall has p = 1 (trinary maps) the nearest wall's value is 1 wherever it is, so
    only the distances are computed, by ``_distance.wall_distance`` (the same numbers as SciPy's,
    3x faster here), and the indices are None; otherwise ``ndimage.distance_transform_edt``.
    """
    p = grid.prob
    occ = p >= occupied                          # False on unknown (NaN) cells
    if not occ.any():
        return None
    if p[occ].min() == 1.0:
        return wall_distance(occ), None
    from scipy import ndimage

    return ndimage.distance_transform_edt(~occ, return_indices=True)


def blur(grid: GridMap, width: float, *, kind: Literal["gaussian", "ramp", "envelope"] = "gaussian",
         occupied: float = 0.5, transform=None) -> GridMap:
    """Return ``grid`` blurred with ``width`` metres (see the module docstring); unknown stays NaN.
    ``transform``: ``wall_transform(grid, occupied)`` when the caller has it already."""
    out = blur_everywhere(grid, width, kind=kind, occupied=occupied, transform=transform)
    if out is grid.prob:
        return grid
    out[np.isnan(grid.prob)] = np.nan
    return grid._with_trusted(out)


def blur_everywhere(grid: GridMap, width: float, *, kind: Literal["gaussian", "ramp", "envelope"] = "gaussian",
                    occupied: float = 0.5, transform=None) -> np.ndarray:
    """``blur``'s values on unknown cells too (a new array; ``grid.prob`` itself when the blur
    changes nothing): the "ramp" and "envelope" blurs reach unknown cells from the walls (the
    envelope discrepancy charges a wall there by its distance from the other map's walls); the
    Gaussian's normalised convolution is 0 where no known cell is near."""
    width = float(width)
    if not np.isfinite(width) or width < 0.0:
        raise InvalidOptionError(f"blur width must be a finite number of metres >= 0; got {width}")
    if kind not in BLUR_KINDS:
        raise InvalidOptionError(f"blur kind must be one of {BLUR_KINDS}; got {kind!r}")
    if width == 0.0:
        return grid.prob
    prob = grid.prob
    unknown = np.isnan(prob)
    if kind == "gaussian":
        sigma = width / grid.resolution
        both = gaussian_filter(np.stack([np.where(unknown, 0.0, prob), (~unknown).astype(np.float64)]), sigma)
        out = np.clip(both[0] / np.maximum(both[1], 1e-300), 0.0, 1.0)
    else:
        if kind == "envelope" and transform is None:
            walls = prob >= occupied                 # False on unknown (NaN) cells
            if not walls.any():
                return prob
            if prob[walls].min() < 1.0:
                return _grey_envelope(prob, walls, width / grid.resolution)
        transform = transform if transform is not None else wall_transform(grid, occupied)
        if transform is None:
            return prob
        dist, nearest = transform
        d = dist * (grid.resolution / width)
        if kind == "ramp":
            profile = np.clip(1.0 - d, 0.0, None)
        else:                                    # exp(-0.5 * d * d), in place: fresh arrays cost page faults
            profile = d * -0.5
            profile *= d
            np.exp(profile, out=profile)
        if nearest is None:                      # every wall at 1 (trinary maps): 1 * profile is profile
            out = np.fmax(prob, profile, out=profile)
        else:
            out = np.fmax(prob, prob[nearest[0], nearest[1]] * profile, out=profile)
    return out


def _grey_envelope(prob, walls, width_cells):
    """``max(p, max_o p(o) exp(-d^2 / 2 w^2))`` over the walls o (w in cells): exp(-D / 2 w^2) with
    D the squared-distance transform of -2 w^2 ln p(o) on the walls (+inf elsewhere)."""
    s2 = 2.0 * width_cells * width_cells
    f = np.full(prob.shape, np.inf)
    f[walls] = -s2 * np.log(prob[walls])
    profile = squared_distance(f)
    profile /= -s2
    np.exp(profile, out=profile)
    return np.fmax(prob, profile, out=profile)
