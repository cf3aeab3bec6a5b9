"""Every numeric recipe key carries its range beside it (``colmap_miho.validation.within`` in the
field's metadata), checked before any work, with a message naming the key and the range."""

from __future__ import annotations

import dataclasses
import math
import time
import typing

import pytest
import torch

from colmap_miho.cli import main
from colmap_miho.errors import InvalidInput
from colmap_miho.recipe import SECTIONS, load_recipe
from colmap_miho.validation import MAX_BLUR_PX, OPTION_BOUNDS, bounds_of


def _outside(bound, side: str, is_int: bool):
    if side == "low":
        value = bound.lo if bound.lo_open else bound.lo - (1 if is_int else max(1e-6, abs(bound.lo) * 1e-3))
    else:
        value = bound.hi if bound.hi_open else bound.hi + (1 if is_int else max(1e-6, abs(bound.hi) * 1e-3))
    return int(value) if is_int else value


def _is_int(section: str, key: str) -> bool:
    hint = typing.get_type_hints(SECTIONS[section])[key]
    return hint is int or int in typing.get_args(hint)


CASES = [(section, key, side) for section, cls in SECTIONS.items() for key in bounds_of(cls)
         for side in ("low", "high")]


@pytest.mark.parametrize(("section", "key", "side"), CASES, ids=[f"{s}.{k}-{e}" for s, k, e in CASES])
def test_every_bounded_key_refuses_a_value_past_each_end(section, key, side):
    bound = bounds_of(SECTIONS[section])[key]
    value = _outside(bound, side, _is_int(section, key))
    with pytest.raises(InvalidInput, match=rf"\[{section}\] {key} must be in [\[(]"):
        load_recipe(None, [f"{section}.{key}={value}"])


def test_every_numeric_key_is_bounded():
    """The audit: no int or float field of a recipe section is left without a range."""
    missing = []
    for section, cls in SECTIONS.items():
        hints = typing.get_type_hints(cls)
        for f in dataclasses.fields(cls):
            kinds = {hints[f.name], *typing.get_args(hints[f.name])}
            if (int in kinds or float in kinds) and f.name not in bounds_of(cls):
                missing.append(f"{section}.{f.name}")
    assert not missing


def test_cases_cover_every_bounded_key():
    assert len(CASES) == 2 * sum(len(bounds_of(cls)) for cls in SECTIONS.values()) >= 54


def test_bounds_hold_the_defaults_and_every_shipped_recipe():
    from colmap_miho.recipe import available_recipes

    for name in available_recipes():
        load_recipe(name)


@pytest.mark.parametrize("override", ["lsm.antialias=1e20", "lsm.antialias=1e3",
                                      "match_check.max_rounds=1000000000", "filter.max_iters=-1",
                                      "mapping.num_threads=-5", "lsm.radius=1e300"])
def test_the_attack_values_are_refused_fast_naming_the_key(override, tmp_path, capfd):
    key = override.split("=")[0].split(".")[1]
    start = time.perf_counter()
    rc = main(["refine", "--database", str(tmp_path / "missing.db"), "--images", str(tmp_path), "--set", override,
               "-q"])
    assert time.perf_counter() - start < 10
    lines = [line for line in capfd.readouterr().err.splitlines() if line.strip()]
    assert rc == 2 and len(lines) == 1 and key in lines[0], lines


def test_lsm_antialias_is_at_most_the_lsm_window():
    # the LSM window is lsm.radius, or ncc.template_radius when lsm.radius is 0
    load_recipe("mop_miho_ncc", ["lsm.antialias=6", "ncc.template_radius=6", "lsm.radius=0"])
    with pytest.raises(InvalidInput, match="lsm.antialias must be <= 6"):
        load_recipe("mop_miho_ncc", ["lsm.antialias=6.5", "ncc.template_radius=6", "lsm.radius=0"])
    load_recipe("mop_miho_lsm", ["lsm.antialias=8", "lsm.radius=8"])
    with pytest.raises(InvalidInput, match="lsm.antialias must be <= 8"):
        load_recipe("mop_miho_lsm", ["lsm.antialias=8.5", "lsm.radius=8"])


@pytest.mark.parametrize(("option", "value"), [("--seed", "-5"), ("--workers", "0"), ("--workers", "100000"),
                                                ("--seed", str(2**40))])
def test_numeric_options_are_checked_before_any_work(option, value, tmp_path, capfd):
    assert main(["refine", "--database", str(tmp_path / "missing.db"), "--images", str(tmp_path), option, value,
                 "-q"]) == 2
    lines = [line for line in capfd.readouterr().err.splitlines() if line.strip()]
    assert len(lines) == 1 and lines[0].startswith(f"ERROR: {option} must be in"), lines
    assert set(OPTION_BOUNDS) >= {"seed", "workers"}


def test_the_lsm_blur_is_capped_for_the_kernel():
    from colmap_miho.refinement.lsm.step import blur_sigma

    s = blur_sigma(torch.tensor([1e9, 2.0, 1.0], dtype=torch.float64), torch.ones(3, dtype=torch.float64), 0.5)
    assert float(s.max()) == MAX_BLUR_PX and math.isclose(float(s[1]), 0.5 * math.sqrt(3))


def test_the_lsm_kernel_refuses_sizes_its_buffers_were_not_made_for():
    from colmap_miho.refinement.lsm import kernel as lsm_kernel

    img = torch.zeros((32, 32))
    eye = torch.eye(3, dtype=torch.float64)[None]
    z = torch.zeros((1, 2), dtype=torch.float64)
    blur = (torch.ones(1, dtype=torch.bool), torch.tensor([1e20], dtype=torch.float64))
    with pytest.raises(ValueError, match="LSM blur must be finite"):
        lsm_kernel.lsm_frames(img, img, eye, z, eye, z, z, 4, blur_f=blur)
    with pytest.raises(ValueError, match="LSM radius"):
        lsm_kernel.lsm_frames(img, img, eye, z, eye, z, z, 10_000)
