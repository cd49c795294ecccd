"""The library's own exceptions: one root, subclasses of the built-ins where natural."""

__all__ = ["TaichiMatchError", "InvalidMapError", "InvalidPoseError", "EngineError"]


class TaichiMatchError(Exception):
    """Root of every exception raised by taichi_match itself."""


class InvalidMapError(TaichiMatchError, ValueError):
    """A map's probabilities, resolution or origin are not usable."""


class InvalidPoseError(TaichiMatchError, ValueError):
    """A pose or a batch of poses is malformed or not finite."""


class EngineError(TaichiMatchError, RuntimeError):
    """The evaluation engine cannot run here (for instance Taichi in a forked child)."""
