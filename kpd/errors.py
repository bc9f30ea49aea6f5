"""Exception types raised by kpd.

Every error a user can cause is a :class:`KpdError`. The command line catches it, prints its message on one line and
exits with status 2, so messages must name the problem, the expected value and the actual one.
"""

from __future__ import annotations

__all__ = ["KpdError", "InputError", "BundleError", "DataError", "NotFittedError", "WriteError", "TrainingError"]


class KpdError(Exception):
    """Base class of every error kpd raises on purpose."""


class InputError(KpdError, ValueError):
    """A file, array or argument given by the user is missing, unreadable or malformed."""


class BundleError(KpdError):
    """A model bundle is missing, tampered with, of another format version, or inconsistent."""


class DataError(KpdError):
    """A dataset cannot be used: unknown layout, missing split, too few readable shapes."""


class NotFittedError(KpdError, AttributeError):
    """A fitted attribute of an estimator was used before ``fit``."""


class WriteError(KpdError):
    """An output cannot be written or placed: a full disk, a read-only or forbidden folder, a file that another
    process created at the output path meanwhile, or a writer that wrote less than it was given. Nothing is left
    behind when it is raised (no partial output, no temporary file) and no existing file was changed."""


class TrainingError(KpdError):
    """Training cannot go on (the loss diverged); the run folder keeps its last good checkpoint."""
