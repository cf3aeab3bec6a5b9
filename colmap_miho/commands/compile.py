"""``colmap-miho compile``: fill the compiled kernels' cache ahead of the first run."""

from __future__ import annotations

import argparse

from ..errors import RunFailed, UserError

HELP = "compile the kernels a recipe uses into the cache, ahead of the first run (a Docker build step)"
DESCRIPTION = (
    "Compile the numba kernels the recipe runs (default recipe mop_miho_lsm; --all: every "
    "kernel) into the kernel cache, so that no run pays their compilation (tens of seconds on "
    "a fresh installation). The cache folder is $COLMAP_MIHO_CACHE_DIR, else $NUMBA_CACHE_DIR, "
    "else colmap-miho/numba in the user's cache folder (~/.cache on Linux); runs must see the "
    "same folder. Kernels already in the cache are not compiled again. Prints the folder and "
    "what was compiled."
)
ORDER = 90


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--recipe", default=None, help="recipe name or .toml path (default mop_miho_lsm)")
    parser.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE",
                        help="override a recipe value, e.g. --set lsm.enabled=false (repeatable)")
    parser.add_argument("--all", action="store_true", help="every kernel, whatever the recipe")
    parser.add_argument("--processes", type=int, default=None,
                        help="kernel families compiled at once, each in a process (default: one per core)")


def run(args: argparse.Namespace) -> int:
    from ..compiled import CACHE_ENV
    from ..kernel_cache import FAMILIES, ensure_compiled, families_for
    from ..recipe import load_recipe

    families = tuple(FAMILIES) if args.all else families_for(load_recipe(args.recipe, list(args.overrides)))
    report = ensure_compiled(families, processes=args.processes)
    if not report.writable:
        raise UserError(f"cannot write the kernel cache in {report.folder}: set {CACHE_ENV} to a writable folder")
    if report.failed:
        failed = ", ".join(f"{family} kernels ({why})" for family, why in report.failed.items())
        raise RunFailed(f"could not compile the {failed}")
    if not args.quiet:
        print(f"kernel cache: {report.folder}")
        for family in families:
            if family in report.compiled:
                print(f"  {family:8s} compiled in {report.compiled[family]:.1f} s")
            else:
                print(f"  {family:8s} already in the cache")
    return 0
