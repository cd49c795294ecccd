"""The library's own exceptions: one root, subclasses of the built-ins where natural."""

__all__ = ["TaichiMatchError", "InvalidMapError", "InvalidPoseError", "InvalidOptionError", "EngineError",
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
