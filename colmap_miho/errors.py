"""Exceptions meant for users: the CLI prints their message on one line and exits."""

from __future__ import annotations


class UserError(Exception):
    """A problem with the user's input (file, option, database) that stops the run."""

    exit_code = 2


class InvalidInput(UserError, ValueError):
    """A bad value from the user: an option, a recipe value, or the contents of an input file.

    A ``ValueError`` too, so that callers of the Python API catch it as one; the CLI reports it
    on one line with exit code 2, while any other ``ValueError`` is an internal error (exit 1)."""


class DatabaseError(UserError):
    """The database is missing, not a COLMAP database, locked, or inconsistent."""


class RunFailed(UserError):
    """The run itself failed (for example mapping registered no image)."""

    exit_code = 1


class Terminated(KeyboardInterrupt):
    """SIGTERM (or SIGHUP), raised by the CLI's handler so that a terminated run cleans up like
    Ctrl-C; ``signum`` is the signal's number (None when raised otherwise)."""

    signum: int | None = None
