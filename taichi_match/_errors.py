"""The library's own exceptions: one root, subclasses of the built-ins where natural."""

__all__ = ["shown", "TaichiMatchError", "InvalidMapError", "InvalidPoseError", "InvalidOptionError", "EngineError",
           "MapFileError", "MapFormatError", "LogFileError", "LogFormatError"]


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
    as plain numbers (NumPy 2's repr would print ``np.float64(nan)``).

    >>> import numpy as np
    >>> shown((np.float64(0.5), np.int64(3))), shown(np.float32(2.0)), shown("a")
    ('(0.5, 3)', '2.0', "'a'")
    """
    def plain(v):
        if hasattr(v, "item") and type(v).__module__ == "numpy" and getattr(v, "ndim", None) == 0:
            return v.item()
        if isinstance(v, (tuple, list)):
            return type(v)(plain(x) for x in v)
        return v

    return repr(plain(value))
