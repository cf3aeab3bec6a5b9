"""Argument helpers shared by the commands (private: the CLI skips ``_`` modules)."""

from __future__ import annotations

import argparse

from ..enums import Device, Mapper


def list_items(values) -> list[str]:
    """Items of a list option given as ``a,b,c``, ``a b c`` or mixed; empty pieces dropped."""
    return [item for value in ([values] if isinstance(values, str) else values)
            for item in value.split(",") if item.strip()]


class ListAction(argparse.Action):
    """A list option taking ``a,b,c`` as well as ``a b c``; ``item_type`` converts each item,
    ``join`` keeps COLMAP's comma-separated text."""

    def __init__(self, option_strings, dest, *, item_type=str, join: bool = False, **kwargs):
        kwargs.setdefault("nargs", "+")
        super().__init__(option_strings, dest, **kwargs)
        self.item_type, self.join = item_type, join

    def __call__(self, parser, namespace, values, option_string=None):
        items = list_items(values)
        if not items:
            raise argparse.ArgumentError(self, "expected at least one value")
        if self.join:
            setattr(namespace, self.dest, ",".join(item.strip() for item in items))
            return
        converted = []
        for item in items:
            try:
                converted.append(self.item_type(item))
            except ValueError:
                raise argparse.ArgumentError(self, f"invalid {self.item_type.__name__} value: {item!r}") from None
        setattr(namespace, self.dest, converted)


def add_recipe_arguments(parser) -> None:
    """The recipe and run options shared with run and demo (read with :func:`load_run_recipe`)."""
    parser.add_argument("--recipe", default=None, help="recipe name or .toml path (default mop_miho_lsm)")
    parser.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE",
                        help="override a recipe value, e.g. --set filter.t_l=12 (repeatable)")
    parser.add_argument("--mapper", default=None, choices=Mapper.values(),
                        help="pycolmap mapper (default: the recipe's mapping.mapper, incremental)")
    parser.add_argument("--workers", type=int, default=None, help="processes filtering pairs (default: all cores)")
    parser.add_argument("--device", choices=Device.values(), default=Device.AUTO.value, help="torch device")
    parser.add_argument("--seed", type=int, default=0,
                        help="the run's root seed: every stage's seed derives from it (default 0)")
    add_refine_intrinsics_argument(parser)


def add_refine_intrinsics_argument(parser) -> None:
    """``--refine-intrinsics {all,default,none}`` (-> ``mapping.refine_intrinsics``)."""
    from ..sfm import RefineIntrinsics

    parser.add_argument("--refine-intrinsics", default=None, choices=RefineIntrinsics.values(),
                        help="what bundle adjustment may change in the cameras: all (focal, principal point, "
                             "distortion), default (COLMAP's: focal and distortion), none (keep the given "
                             "intrinsics); default: the recipe's mapping.refine_intrinsics (default)")


def add_camera_arguments(parser) -> None:
    """``--camera-model`` / ``--camera-params`` (-> ``mapping.camera_model`` / ``camera_params``)."""
    parser.add_argument("--camera-model", default=None,
                        help="COLMAP camera model written into every camera of the mapped copy (e.g. PINHOLE); "
                             "the input database is never changed")
    parser.add_argument("--camera-params", default=None, action=ListAction, join=True, metavar="P",
                        help="known intrinsics for --camera-model, COLMAP's list with commas or spaces (e.g. PINHOLE "
                             "'fx,fy,cx,cy' or fx fy cx cy, COLMAP pixel convention); with --refine-intrinsics none "
                             "they are kept")


def add_auc_arguments(parser) -> None:
    """``--auc-thresholds`` (degrees), read with :func:`auc_thresholds`."""
    parser.add_argument("--auc-thresholds", action=ListAction, item_type=float, default=None, metavar="DEG",
                        help="pose-AUC thresholds in degrees, with commas or spaces (default 0.5,1,2,5,10,20; 5, 10 "
                             "and 20 are always reported)")


def auc_thresholds(args) -> tuple[float, ...]:
    """The validated ``--auc-thresholds`` (ValueError for a non-positive one)."""
    from ..reporting.report import auc_thresholds as with_defaults

    return with_defaults(getattr(args, "auc_thresholds", None))


def mapping_overrides(args) -> list[str]:
    """``--set`` strings for the mapping flags the command has and the user gave."""
    out = []
    for flag, key in (("mapper", "mapper"), ("threads", "num_threads"),
                      ("min_num_matches", "min_num_matches"), ("camera_model", "camera_model"),
                      ("camera_params", "camera_params"), ("refine_intrinsics", "refine_intrinsics")):
        value = getattr(args, flag, None)
        if value is not None:
            out.append(f"mapping.{key}={value}")
    return out


def load_run_recipe(args):
    """The recipe of compare / run / demo: ``--recipe`` and ``--set``, then the flags, which
    override it (``--mapper`` -> ``mapping.mapper``,
    ``--refine-intrinsics``, ``--camera-model``, ``--camera-params`` -> ``mapping.*``).

    Raises:
        ValueError: a bad recipe or value (e.g. camera parameters that do not fit the model).
    """
    from ..recipe import load_recipe

    return load_recipe(args.recipe, [*args.overrides, *mapping_overrides(args)])

def add_repeat_arguments(parser) -> None:
    """``--repeats`` and ``--camera-from-gt`` (compare and run)."""
    parser.add_argument("--repeats", type=int, default=1,
                        help="map each side N times (seeds SEED, SEED+1, ...) and report median and range of "
                             "every mapping figure, with the per-run rows in the JSON (default 1)")
    parser.add_argument("--camera-from-gt", action="store_true",
                        help="write the GT model's intrinsics into the mapped copies (needs --gt; add "
                             "--refine-intrinsics none to keep them)")


def check_repeat_arguments(args) -> None:
    """One-line errors for ``--repeats`` < 1 and ``--camera-from-gt`` without ``--gt``."""
    from ..errors import UserError

    if args.repeats < 1:
        raise UserError(f"--repeats must be >= 1, got {args.repeats}")
    if args.camera_from_gt and args.gt is None:
        raise UserError("--camera-from-gt needs --gt")


def quiet_colmap(verbose: bool) -> None:
    """Keep COLMAP's INFO lines off the terminal outside the mapper (which logs to a file)."""
    if not verbose:
        import pycolmap

        pycolmap.logging.minloglevel = 1

