"""Recipes: named TOML files that set the configuration of every stage.

A recipe has one table per stage (``[filter]``, ``[ncc]``, ``[lsm]``, ``[rectify]``,
``[tracks]``, ``[pipeline]``, ``[mapping]``, ``[match_check]``) whose keys are fields of the
stage's dataclass; a missing table or key means the dataclass default, which is the default
recipe's. Unknown tables or keys are errors, never silently ignored; a key of an older release
is refused with a line naming what replaced it. ``--set table.key=value`` overrides are parsed
with the field's type.
"""

from __future__ import annotations

import dataclasses
import os
import sys
import types
import typing
from dataclasses import dataclass, field
from enum import Enum
from importlib import resources
from pathlib import Path

from .errors import InvalidInput
from .filtering.config import FilterConfig
from .pipeline_config import PipelineConfig
from .refinement.config import LSMConfig, NCCConfig, RectifyConfig, TrackConfig
from .sfm import MappingConfig
from .verification.config import MatchCheckConfig

if sys.version_info >= (3, 11):
    import tomllib
else:  # pragma: no cover
    import tomli as tomllib

# the recipe of every command and API call that is not given one: track-consistent NCC, then
# least-squares matching from each NCC peak (``mop_miho_ncc`` is the faster NCC-only recipe)
DEFAULT_RECIPE = "mop_miho_lsm"


@dataclass(frozen=True, kw_only=True)
class Recipe:
    """The configuration of every stage. ``Recipe()`` is the default recipe
    (:data:`DEFAULT_RECIPE`); each recipe file states only how it differs from it. The
    ``[lsm]`` and ``[rectify]`` tables are ``ncc.lsm`` and ``ncc.rectify`` here."""

    name: str = "custom"
    description: str = ""
    filter: FilterConfig = field(default_factory=FilterConfig)
    ncc: NCCConfig = field(default_factory=NCCConfig)
    tracks: TrackConfig = field(default_factory=TrackConfig)
    pipeline: PipelineConfig = field(default_factory=PipelineConfig)
    mapping: MappingConfig = field(default_factory=MappingConfig)
    match_check: MatchCheckConfig = field(default_factory=MatchCheckConfig)

    @property
    def lsm(self) -> LSMConfig:
        """The ``[lsm]`` table."""
        return self.ncc.lsm

    @property
    def rectify(self) -> RectifyConfig:
        """The ``[rectify]`` table."""
        return self.ncc.rectify


#: the recipe's tables and their dataclasses (``lsm`` and ``rectify`` nest in ``ncc``)
SECTIONS: dict[str, type] = {
    "filter": FilterConfig,
    "ncc": NCCConfig,
    "lsm": LSMConfig,
    "rectify": RectifyConfig,
    "tracks": TrackConfig,
    "pipeline": PipelineConfig,
    "mapping": MappingConfig,
    "match_check": MatchCheckConfig,
}
#: tables that are fields of another table's dataclass, not keys of it
NESTED = {"ncc": ("lsm", "rectify")}

_SEED = "--seed (seed= in Python): the run's root seed, every stage's derives from it"
#: keys of earlier releases -> what replaced them (the decisions: docs/results.md, "Recipe keys:
#: what a user sets")
RENAMED = {
    "match_check.rounds": "match_check.max_rounds",
    "ncc.lsm": "lsm.enabled", "ncc.lsm_radius": "lsm.radius", "ncc.lsm_antialias": "lsm.antialias",
    "ncc.lsm_max_shift_px": "lsm.max_shift_px", "ncc.lsm_tol_px": "lsm.tol_px",
    "ncc.rectification": "rectify.mode", "ncc.local_affine_neighbours": "rectify.neighbours",
    "ncc.local_affine_max_residual_px": "rectify.max_residual_px",
    "tracks.far_move_px": "rectify.max_residual_px (the far-move bound)",
    "mapping.seed": _SEED, "match_check.seed": _SEED, "pipeline.refine": "pipeline.refine_keypoints",
}
REMOVED = {
    "pair_check": "the pair check was removed (no recipe used it)",
    "ncc.match_blur": "blur matching was removed (it lost accuracy in the walk)",
    "ncc.lsm_only": "removed: a move LSM does not accept keeps the NCC peak's position",
    "ncc.lsm_affine": "now the constant LSMConfig.affine",
    "ncc.lsm_max_iterations": "now the constant LSMConfig.max_iterations",
    "ncc.lsm_max_sigma_px": "now the constant LSMConfig.max_sigma_px",
    "tracks.multiphoto_star_first": "removed: the joint pass starts from the walk's positions",
    "tracks.far_move_ratio": "removed: the far-move check has no peak-ratio test",
}


def _refuse_old(section: str, key: str | None = None) -> None:
    """Raise the line that names what replaced ``section.key`` (or the table), if it is old."""
    name = section if key is None else f"{section}.{key}"
    where = 'see docs/results.md, "Recipe keys: what a user sets"'
    if name in RENAMED:
        raise InvalidInput(f"{name} is now {RENAMED[name]}")
    if name in REMOVED or section in REMOVED:
        raise InvalidInput(f"{name} is no longer a recipe key: {REMOVED.get(name) or REMOVED[section]}; {where}")
    cls = SECTIONS.get(section)
    if key is not None and cls is not None and hasattr(cls, key) and not key.startswith("_") \
            and key not in _keys(section):
        raise InvalidInput(f"{name} is no longer a recipe key: a fixed constant ({cls.__name__}.{key}); {where}")


def _keys(section: str) -> list[str]:
    """The keys of the table ``section`` (the nested tables aside)."""
    return [f.name for f in dataclasses.fields(SECTIONS[section]) if f.name not in NESTED.get(section, ())]


def recipe_keys() -> list[str]:
    """Every key a recipe sets, ``table.key``."""
    return [f"{s}.{k}" for s in SECTIONS for k in _keys(s)]


def available_recipes() -> list[str]:
    """Names of the recipes shipped with the package."""
    root = resources.files("colmap_miho.recipes")
    return sorted(p.name[:-5] for p in root.iterdir() if p.name.endswith(".toml"))


#: A recipe is a few kB of TOML; a larger file is not one (``/dev/zero`` never ends).
MAX_RECIPE_BYTES = 1 << 20


def _read_recipe_text(name_or_path: str) -> tuple[str, str]:
    path = Path(name_or_path)
    if path.suffix == ".toml" or path.exists():
        return path.stem, _read_recipe_file(path)
    root = resources.files("colmap_miho.recipes")
    candidate = root / f"{name_or_path}.toml"
    if not candidate.is_file():
        raise InvalidInput(
            f"unknown recipe {name_or_path!r}; shipped recipes: {', '.join(available_recipes())}"
            " (or give a path to a .toml file)"
        )
    return name_or_path, candidate.read_text(encoding="utf-8")


def _read_recipe_file(path: Path) -> str:
    """The text of the recipe file ``path``: a regular file of UTF-8 text (a byte-order mark,
    as Windows editors write, is dropped), at most :data:`MAX_RECIPE_BYTES`.

    Raises:
        InvalidInput: missing, not a regular file (says what it is), unreadable, too large or
            not UTF-8 text; the message names the file.
    """
    from .adapters.staged_write import output_kind

    if not path.exists():
        raise InvalidInput(f"recipe file not found: {path}")
    if not path.is_file():
        raise InvalidInput(f"recipe {path} is a {output_kind(path) or 'special file'}, not a regular file; "
                           "give a .toml file")
    try:
        with open(path, "rb") as fh:
            data = fh.read(MAX_RECIPE_BYTES + 1)
    except OSError as exc:
        raise InvalidInput(f"cannot read recipe {path}: {exc.strerror or exc}") from None
    if len(data) > MAX_RECIPE_BYTES:
        raise InvalidInput(f"recipe {path} is larger than {MAX_RECIPE_BYTES >> 20} MB: not a recipe")
    try:
        return data.decode("utf-8-sig")
    except UnicodeDecodeError as exc:
        raise InvalidInput(f"recipe {path} is not UTF-8 text (byte {exc.start}): not a TOML recipe") from None


def _coerce(value, annotation, where: str):
    """Convert a TOML or command-line value to the annotated field type."""
    origin = typing.get_origin(annotation)
    if origin in (typing.Union, types.UnionType):
        args = [a for a in typing.get_args(annotation) if a is not type(None)]
        if isinstance(value, str) and value.lower() in ("none", "null", ""):
            return None
        if value is None:
            return None
        last_error: Exception | None = None
        for arg in args:
            try:
                return _coerce(value, arg, where)
            except ValueError as exc:
                last_error = exc
        raise last_error or ValueError(f"{where}: cannot parse {value!r}")
    if annotation is bool:
        if isinstance(value, bool):
            return value
        text = str(value).strip().lower()
        if text in ("1", "true", "yes", "on"):
            return True
        if text in ("0", "false", "no", "off"):
            return False
        raise InvalidInput(f"{where}: expected true or false, got {_shown(value)}")
    if annotation is int:
        # an integer literal only ("1e3" is a float, as 2.5 is), parsed exactly (no trip through float)
        if isinstance(value, int) and not isinstance(value, bool):
            return value
        try:
            return int(str(value).strip()) if isinstance(value, str) else _not_an_integer(value, where)
        except ValueError:
            raise InvalidInput(f"{where}: expected an integer, got {_shown(value)}") from None
    if annotation is float:
        if isinstance(value, bool):
            raise InvalidInput(f"{where}: expected a number, got {_shown(value)}")
        try:
            return float(value)
        except (TypeError, ValueError):
            raise InvalidInput(f"{where}: expected a number, got {_shown(value)}") from None
    if isinstance(annotation, type) and issubclass(annotation, Enum):
        return annotation.parse(value, where)  # type: ignore[attr-defined]
    if annotation is str:
        return str(value)
    if origin in (tuple, list):
        items = value if isinstance(value, (list, tuple)) else str(value).split(",")
        (inner, *_rest) = typing.get_args(annotation) or (str,)
        return tuple(_coerce(v, inner, where) for v in items)
    return value


def _shown(value, most: int = 60) -> str:
    """``repr(value)`` for a message, at most about ``most`` characters (a 5,000-digit value
    filled the terminal)."""
    text = repr(value)
    return text if len(text) <= most else f"{text[:most]}... ({len(text)} characters)"


def _not_an_integer(value, where: str):
    raise InvalidInput(f"{where}: expected an integer, got {_shown(value)}")


def _build_section(section: str, values: dict, base=None):
    cls = SECTIONS[section]
    types_ = typing.get_type_hints(cls)
    names = _keys(section)
    kwargs = {}
    for key, value in values.items():
        if key not in names:
            _refuse_old(section, key)
            raise InvalidInput(
                f"unknown key {section}.{key}; valid keys: "
                + ", ".join(f"{section}.{n}" for n in names)
            )
        kwargs[key] = _coerce(value, types_[key], f"{section}.{key}")
    try:
        if base is None:
            return cls(**kwargs)
        return dataclasses.replace(base, **kwargs)
    except ValueError as exc:
        raise InvalidInput(f"[{section}] {exc}") from None


def parse_overrides(overrides: list[str] | None) -> dict[str, dict[str, str]]:
    """Parse ``section.key=value`` strings into ``{section: {key: value}}``."""
    parsed: dict[str, dict[str, str]] = {}
    for item in overrides or []:
        if "=" not in item:
            raise InvalidInput(f"--set expects section.key=value, got {item!r}")
        key, value = item.split("=", 1)
        if "." not in key:
            raise InvalidInput(
                f"--set key {key!r} needs a section: one of {', '.join(SECTIONS)} "
                "(for example filter.t_l=12)"
            )
        section, name = key.strip().split(".", 1)
        if section not in SECTIONS:
            _refuse_old(section, name.strip())
            raise InvalidInput(f"--set {key!r}: unknown section {section!r}; one of {', '.join(SECTIONS)}")
        parsed.setdefault(section, {})[name.strip()] = value.strip()
    return parsed


def load_recipe(name_or_path: str | None = None, overrides: list[str] | None = None) -> Recipe:
    """Load a shipped recipe by name (or a TOML file by path) and apply ``--set`` overrides.

    Raises:
        ValueError: unknown recipe, table or key, or a value of the wrong type or range;
            the message names the offending key.
    """
    if name_or_path is not None and not isinstance(name_or_path, (str, os.PathLike)):
        raise InvalidInput(f"recipe must be a recipe name or a .toml path, got {type(name_or_path).__name__}")
    if overrides is not None and (isinstance(overrides, str) or not isinstance(overrides, (list, tuple))
                                  or not all(isinstance(o, str) for o in overrides)):
        raise InvalidInput(f"overrides must be a list of 'section.key=value' strings, got {overrides!r}")
    name, text = _read_recipe_text(os.fspath(name_or_path or DEFAULT_RECIPE))
    try:
        data = tomllib.loads(text.removeprefix("\ufeff"))
    except tomllib.TOMLDecodeError as exc:
        raise InvalidInput(f"recipe {name!r} is not valid TOML: {exc}") from None
    except RecursionError:  # arrays or tables nested thousands deep
        raise InvalidInput(f"recipe {name!r} is nested too deeply: not a recipe") from None
    description = str(data.pop("description", ""))
    data.pop("name", None)
    for section in data:
        if section not in SECTIONS:
            _refuse_old(section)
            raise InvalidInput(
                f"recipe {name!r}: unknown table [{section}]; valid tables: {', '.join(SECTIONS)}"
            )
        if not isinstance(data[section], dict):
            raise InvalidInput(f"recipe {name!r}: {section} must be a table")
    configs = {s: _build_section(s, data.get(s, {})) for s in SECTIONS}
    for section, values in parse_overrides(overrides).items():
        configs[section] = _build_section(section, values, base=configs[section])
    try:
        configs["ncc"] = dataclasses.replace(configs["ncc"], lsm=configs.pop("lsm"), rectify=configs.pop("rectify"))
    except ValueError as exc:
        raise InvalidInput(f"[ncc] {exc}") from None
    return Recipe(name=name, description=description, **configs)
