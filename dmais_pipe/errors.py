"""Errors raised for bad user input; the CLI prints them on one line and exits with status 2."""

from __future__ import annotations

from pathlib import Path


class DmaisError(Exception):
    """Base class of every error caused by the user's input rather than by a bug."""


class DatasetError(DmaisError):
    """Malformed dataset input, naming the file and, where known, the line at fault.

    `line` is the 1-based line of the file as a text editor shows it (the CSV header is line 1).
    """

    def __init__(self, path: str | Path, message: str, line: int | None = None):
        self.path = str(path)
        self.line = line
        self.message = message
        where = self.path if line is None else f"{self.path}, line {line}"
        super().__init__(f"{where}: {message}")


class ConfigError(DmaisError):
    """Malformed configuration file or value."""


class GeometryError(DmaisError):
    """Input whose geometry cannot be handled (e.g. a rotation Cayley cannot express)."""


class PoseError(DmaisError):
    """Input the generalized pose solver cannot handle (too few, collinear or invalid data)."""


class FileAccessError(DmaisError):
    """A file or folder could not be read or written (permission, not a directory, disk full, gone)."""

    def __init__(self, path: str | Path, reason: str):
        self.path = str(path)
        self.reason = reason
        super().__init__(f"{self.path}: {reason}")

    @classmethod
    def of(cls, error: OSError, path: str | Path | None = None) -> FileAccessError:
        """From an OSError, naming `path` (else the error's own file name) and the system's reason."""
        where = path if path is not None else (error.filename if error.filename is not None else "(unknown file)")
        return cls(where, error.strerror or str(error))


def yaml_problem(error) -> tuple[str, int | None]:
    """One line describing a yaml.YAMLError and the 1-based line it points at (None if unknown)."""
    mark = getattr(error, "problem_mark", None)
    problem = getattr(error, "problem", None) or str(error).splitlines()[0]
    return problem, None if mark is None else mark.line + 1
