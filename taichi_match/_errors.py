"""The library's own exceptions: one root, subclasses of the built-ins where natural."""

import reprlib

__all__ = ["shown", "TaichiMatchError", "InvalidMapError", "InvalidPoseError", "InvalidOptionError", "EngineError",
           "MapFileError", "MapFormatError", "LogFileError", "LogFormatError", "SlamRunError"]


class TaichiMatchError(Exception):
    """Root of every exception raised by taichi_match itself."""


class InvalidMapError(TaichiMatchError, ValueError):
    """A map's probabilities, resolution or origin are not usable."""


class InvalidPoseError(TaichiMatchError, ValueError):
    """A pose or a batch of poses is malformed or not finite."""


class InvalidOptionError(TaichiMatchError, ValueError, TypeError):
    """An option is unknown, of the wrong type or out of range."""


class EngineError(TaichiMatchError, RuntimeError):
    """The evaluation engine cannot run here (for instance Taichi in a forked child)."""


class MapFileError(TaichiMatchError, OSError):
    """A map file (YAML, image, .npz) cannot be read or written."""


class MapFormatError(TaichiMatchError, ValueError):
    """A map file is readable but malformed (a YAML field missing or of the wrong type, a
    truncated or unsupported image)."""


class LogFileError(TaichiMatchError, OSError):
    """A laser log or trajectory file cannot be read."""


class LogFormatError(TaichiMatchError, ValueError):
    """A laser log or trajectory file is readable but malformed."""


def shown(value) -> str:
    """``repr(value)`` as an error message shows it: NumPy scalars, also inside tuples and lists,
    as plain numbers (NumPy 2's repr would print ``np.float64(nan)``), and at most a few items and
    levels of what a hostile file holds (a YAML of nested aliases expands to billions).

    >>> import numpy as np
    >>> shown((np.float64(0.5), np.int64(3))), shown(np.float32(2.0)), shown("a")
    ('(0.5, 3)', '2.0', "'a'")
    >>> shown([[1] * 100] * 3)
    '[[1, 1, 1, 1, 1, 1, ...], [1, 1, 1, 1, 1, 1, ...], [1, 1, 1, 1, 1, 1, ...]]'
    """
    def plain(v, depth):
        if hasattr(v, "item") and type(v).__module__ == "numpy" and getattr(v, "ndim", None) == 0:
            return v.item()
        if isinstance(v, (tuple, list)) and depth < _SHOWN.maxlevel:
            return type(v)(plain(x, depth + 1) for x in v[:_SHOWN.maxlist + 1])
        return v

    return _SHOWN.repr(plain(value, 0))


_SHOWN = reprlib.Repr()
_SHOWN.maxlevel, _SHOWN.maxlist, _SHOWN.maxtuple, _SHOWN.maxdict = 2, 6, 6, 6
_SHOWN.maxstring, _SHOWN.maxother, _SHOWN.maxlong = 120, 120, 60


class SlamRunError(TaichiMatchError, RuntimeError):
    """A run of the mapping loop (``slam.Slam.add``) cannot go on: an error broke it part-way, or
    another run is under way on the same mapper."""
