"""Argument helpers shared by the commands (private: the CLI skips ``_`` modules)."""

from __future__ import annotations

from ..enums import Device, Mapper


def add_recipe_arguments(parser) -> None:
    """--recipe / --set / --workers / --device / --seed / --mapper, shared with run and demo
    (read them with :func:`load_run_recipe`)."""
    parser.add_argument("--recipe", default=None, help="recipe name or .toml path (default mop_miho_ncc)")
    parser.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE",
                        help="override a recipe value, e.g. --set filter.t_l=12 (repeatable)")
    parser.add_argument("--mapper", default=None, choices=Mapper.values(),
                        help="pycolmap mapper (default: the recipe's mapping.mapper, incremental)")
    parser.add_argument("--workers", type=int, default=None, help="processes filtering pairs (default: all cores)")
    parser.add_argument("--device", choices=Device.values(), default=Device.AUTO.value, help="torch device")
    parser.add_argument("--seed", type=int, default=0, help="seed of refinement, mapping and RANSAC")


def load_run_recipe(args):
    """The recipe of compare / run / demo: ``--recipe`` and ``--set``, then the flags, which
    override it (``--mapper`` -> ``mapping.mapper``, ``--seed`` -> ``mapping.seed``).

    Raises:
        ValueError: a bad recipe or value, or a ``mapping`` key that these commands do not
            apply yet (only ``map`` passes ``num_threads`` and ``min_num_matches``).
    """
    from ..recipe import load_recipe
    from ..sfm import MappingConfig

    overrides = [*args.overrides, f"mapping.seed={args.seed}"]
    if args.mapper:
        overrides.append(f"mapping.mapper={args.mapper}")
    recipe = load_recipe(args.recipe, overrides)
    for key in ("num_threads", "min_num_matches"):
        if getattr(recipe.mapping, key) != getattr(MappingConfig(), key):
            raise ValueError(f"mapping.{key} is applied by `colmap-miho map` only (compare, run "
                             "and demo map with the defaults)")
    return recipe


def quiet_colmap(verbose: bool) -> None:
    """Keep COLMAP's INFO lines off the terminal outside the mapper (which logs to a file)."""
    if not verbose:
        import pycolmap

        pycolmap.logging.minloglevel = 1
