"""One error hierarchy for the whole engine.

Every public entry point checks its inputs and raises one of these (never ``assert``), so callers
(the CLI, the server) can map them to a clear message or an HTTP status in one place.
"""

from __future__ import annotations

from pathlib import Path

__all__ = [
    "VoxFusionError",
    "CaptureError",
    "CaptureFormatError",
    "ConfigError",
    "ShapeError",
    "ValidationError",
    "MapNotReadyError",
    "EngineFailedError",
]


def _rebuild_error(cls: type[VoxFusionError], args: tuple, state: dict) -> VoxFusionError:
    error = cls.__new__(cls)
    error.args = args
    error.__dict__.update(state)
    return error


class VoxFusionError(Exception):
    """Base class of every error voxfusion raises on purpose.

    Errors pickle with their attributes (``field``, ``path``, ...), whatever their constructor takes, so a
    session worker process can raise them in the API process.
    """

    def __reduce__(self) -> tuple:
        return _rebuild_error, (type(self), self.args, dict(self.__dict__))


class ValidationError(VoxFusionError, ValueError):
    """An input value is out of range or inconsistent; ``field`` names it."""

    def __init__(self, field: str, problem: str) -> None:
        self.field = field
        self.problem = problem
        super().__init__(f"{field}: {problem}")


class ShapeError(ValidationError):
    """A tensor or array has the wrong shape."""

    def __init__(self, field: str, actual: tuple[int, ...], expected: str) -> None:
        self.actual = tuple(actual)
        self.expected = expected
        super().__init__(field, f"expected shape {expected}, got {self.actual}")


class ConfigError(ValidationError):
    """A configuration key is unknown or its value is invalid."""


class CaptureError(VoxFusionError):
    """A capture on disk cannot be read; names the file and the problem."""

    def __init__(self, path: str | Path, problem: str) -> None:
        self.path = Path(path)
        self.problem = problem
        super().__init__(f"{self.path}: {problem}")


class CaptureFormatError(CaptureError):
    """A capture folder or file does not have the layout its reader expects."""


class MapNotReadyError(VoxFusionError):
    """The map is empty (no frame has been mapped yet): nothing to render, mesh or export."""


class EngineFailedError(VoxFusionError):
    """The engine (a tracking or mapping worker) failed; the message carries the original error, and
    ``record`` the recording position of the frame it was working on, when known."""

    def __init__(self, message: str, record: int | None = None) -> None:
        self.record = record
        super().__init__(message)
