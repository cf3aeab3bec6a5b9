"""Argument helpers shared by the commands (private: the CLI skips ``_`` modules)."""

from __future__ import annotations


def add_recipe_arguments(parser) -> None:
    """--recipe / --set / --workers / --device / --seed / --mapper, shared with run and demo."""
    parser.add_argument("--recipe", default=None, help="recipe name or .toml path (default mop_miho_ncc)")
    parser.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE",
                        help="override a recipe value, e.g. --set filter.t_l=12 (repeatable)")
    parser.add_argument("--mapper", default="incremental", choices=["incremental", "global"], help="pycolmap mapper")
    parser.add_argument("--workers", type=int, default=None, help="processes filtering pairs (default: all cores)")
    parser.add_argument("--device", choices=["auto", "cpu", "cuda"], default="auto", help="torch device")
    parser.add_argument("--seed", type=int, default=0, help="seed of refinement, mapping and RANSAC")


def quiet_colmap(verbose: bool) -> None:
    """Keep COLMAP's INFO lines off the terminal outside the mapper (which logs to a file)."""
    if not verbose:
        import pycolmap

        pycolmap.logging.minloglevel = 1
