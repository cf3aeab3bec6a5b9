"""Exceptions meant for users: the CLI prints their message on one line and exits."""

from __future__ import annotations


class UserError(Exception):
    """A problem with the user's input (file, option, database) that stops the run."""

    exit_code = 2


class InvalidInput(UserError, ValueError):
    """A bad value from the user; a ValueError too, so API callers catch it. The CLI exits 2
    for it and 1 for any other ValueError (an internal error)."""


class DatabaseError(UserError):
    """The database is missing, not a COLMAP database, locked, or inconsistent."""


class RunFailed(UserError):
    """The run itself failed (for example mapping registered no image)."""

    exit_code = 1


class Terminated(KeyboardInterrupt):
    """SIGTERM (or SIGHUP) raised by the CLI's handler so a run cleans up like Ctrl-C."""

    signum: int | None = None
