"""Shared part of the ``*_at_write.py`` runners: run ``colmap-miho`` with the write stage's
per-pair call wrapped so that ``action()`` runs once, when the second pair is about to be
written (the first one is then in the open transaction)."""

import sys
from collections.abc import Callable
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))  # this checkout's colmap_miho

import colmap_miho.pipeline.write as write_stage  # noqa: E402
from colmap_miho.cli import main  # noqa: E402


def run_with_write_hook(action: Callable[[], None], cli_args: list[str]) -> int:
    """``colmap-miho cli_args`` with ``action`` run inside the write stage; the exit code."""
    write_pair = write_stage.write_pair
    calls = 0

    def wrapped(*args, **kwargs):
        nonlocal calls
        calls += 1
        if calls == 2:
            action()
        return write_pair(*args, **kwargs)

    write_stage.write_pair = wrapped
    return main(cli_args)
