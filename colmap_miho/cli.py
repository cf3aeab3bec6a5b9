"""The ``colmap-miho`` command line: one console script with subcommands.

Each subcommand lives in ``colmap_miho/commands/<name>.py`` and defines ``HELP`` (one line),
``ORDER`` (position in ``--help``), ``add_arguments(parser)`` and ``run(args) -> int``.
Command modules import heavy libraries (torch, pycolmap) inside ``run`` only, so that
``colmap-miho --help`` stays fast.
"""

from __future__ import annotations

import argparse
import importlib
import logging
import pkgutil
import sys

from . import __version__
from .errors import UserError

log = logging.getLogger("colmap_miho")


def _command_modules() -> list:
    from . import commands

    mods = []
    for info in pkgutil.iter_modules(commands.__path__):
        if info.name.startswith("_"):
            continue
        mod = importlib.import_module(f"{commands.__name__}.{info.name}")
        if hasattr(mod, "run") and hasattr(mod, "add_arguments"):
            mods.append(mod)
    return sorted(mods, key=lambda m: (getattr(m, "ORDER", 100), m.__name__))


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="colmap-miho",
        description=(
            "Filter (MOP+MiHo) and refine (track-consistent NCC) the matches of a COLMAP "
            "database before Structure-from-Motion, then map and evaluate."
        ),
    )
    parser.add_argument("--version", action="version", version=f"colmap-miho {__version__}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    for mod in _command_modules():
        name = mod.__name__.rsplit(".", 1)[1].rstrip("_").replace("_", "-")
        name = getattr(mod, "NAME", name)
        p = sub.add_parser(name, help=mod.HELP, description=getattr(mod, "DESCRIPTION", mod.HELP))
        verbosity = p.add_mutually_exclusive_group()
        verbosity.add_argument("-v", "--verbose", action="store_true", help="more log output (and COLMAP's own log)")
        verbosity.add_argument("-q", "--quiet", action="store_true", help="only warnings and errors, no progress bars")
        mod.add_arguments(p)
        p.set_defaults(_run=mod.run)
    return parser


def configure_logging(verbose: bool = False, quiet: bool = False) -> None:
    level = logging.DEBUG if verbose else logging.WARNING if quiet else logging.INFO
    handler = logging.StreamHandler(sys.stderr)
    handler.setFormatter(logging.Formatter("%(asctime)s %(name)s %(levelname)s: %(message)s" if verbose
                                           else "%(levelname)s: %(message)s"))
    root = logging.getLogger("colmap_miho")
    root.handlers[:] = [handler]
    root.setLevel(level)
    root.propagate = False


def main(argv: list[str] | None = None) -> int:
    """Run the CLI; return the process exit code (0 ok, 1 failed run, 2 bad input, 130 Ctrl-C)."""
    parser = build_parser()
    args = parser.parse_args(argv)
    if not getattr(args, "command", None):
        parser.print_help()
        return 2
    configure_logging(getattr(args, "verbose", False), getattr(args, "quiet", False))
    try:
        return int(args._run(args) or 0)
    except UserError as exc:
        log.error("%s", exc)
        return exc.exit_code
    except (ValueError, FileNotFoundError, FileExistsError, NotADirectoryError, PermissionError) as exc:
        log.error("%s", exc)
        return 2
    except KeyboardInterrupt:
        log.error("interrupted; nothing was written to the input")
        return 130


def console_main() -> None:
    sys.exit(main())


if __name__ == "__main__":  # pragma: no cover
    console_main()
