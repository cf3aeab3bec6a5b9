"""Recipes (:mod:`colmap_miho.recipe`): every shipped recipe loads, the default recipe, typed
`--set` overrides, errors that name the key."""

from __future__ import annotations

import dataclasses

import pytest

from colmap_miho.enums import FilterMethod, Mapper, MatchSource
from colmap_miho.recipe import DEFAULT_RECIPE, available_recipes, load_recipe


def test_every_shipped_recipe_loads():
    names = available_recipes()
    assert "mop_miho_ncc" in names and len(names) >= 5
    methods = set()
    for name in names:
        recipe = load_recipe(name)
        assert recipe.name == name
        assert recipe.description
        methods.add(recipe.filter.method)
    assert methods == set(FilterMethod)


def test_default_recipe_is_mop_miho_with_refinement():
    recipe = load_recipe()
    assert recipe.name == DEFAULT_RECIPE == "mop_miho_lsm"
    assert recipe.filter.method is FilterMethod.MOP_MIHO
    assert recipe.pipeline.refine_keypoints is True
    # least-squares matching from each NCC peak; mop_miho_ncc is the same recipe without it
    assert recipe.lsm.enabled is True and recipe.tracks.multiphoto_lsm is False
    ncc = load_recipe("mop_miho_ncc")
    assert ncc.lsm.enabled is False
    assert dataclasses.replace(recipe.ncc, lsm=ncc.lsm) == ncc.ncc
    assert (recipe.filter, recipe.tracks, recipe.pipeline) == (ncc.filter, ncc.tracks, ncc.pipeline)
    assert recipe.filter.inlier_count == 8 and recipe.filter.strict_threshold == 7.5


def test_mapping_table_defaults_and_overrides():
    assert load_recipe().mapping.mapper is Mapper.INCREMENTAL  # shipped recipes omit [mapping]
    recipe = load_recipe(None, ["mapping.mapper=global", "mapping.min_num_matches=30"])
    assert recipe.mapping.mapper is Mapper.GLOBAL
    assert recipe.mapping.min_num_matches == 30 and recipe.mapping.num_threads == -1


def test_run_commands_apply_mapper_and_seed_flags_over_the_recipe():
    from colmap_miho.cli import build_parser
    from colmap_miho.commands._options import load_run_recipe

    base = ["compare", "--database", "d.db", "--images", "i", "--output", "o"]
    args = build_parser().parse_args([*base, "--set", "mapping.mapper=global", "--seed", "5"])
    recipe = load_run_recipe(args)
    assert recipe.mapping.mapper is Mapper.GLOBAL and args.seed == 5  # the root seed, not a recipe key
    args = build_parser().parse_args([*base, "--set", "mapping.mapper=global", "--mapper", "incremental"])
    assert load_run_recipe(args).mapping.mapper is Mapper.INCREMENTAL
    # compare / run / demo now pass the whole mapping table (threads, min matches, cameras) on
    args = build_parser().parse_args([*base, "--set", "mapping.num_threads=1", "--set", "mapping.min_num_matches=30",
                                      "--refine-intrinsics", "none", "--camera-model", "pinhole"])
    m = load_run_recipe(args).mapping
    assert (m.num_threads, m.min_num_matches, m.refine_intrinsics, m.camera_model) == (1, 30, "none", "pinhole")


def test_overrides_are_typed():
    recipe = load_recipe("mop", ["filter.t_l=12", "pipeline.source=raw", "pipeline.refine_keypoints=yes",
                                 "filter.t_h=none"])
    assert recipe.filter.t_l == 12.0 and recipe.filter.t_h is None
    assert recipe.pipeline.source is MatchSource.RAW and recipe.pipeline.refine_keypoints is True


@pytest.mark.parametrize(
    "override, message",
    [
        ("filter.t_lx=3", "unknown key filter.t_lx"),
        ("t_l=3", "needs a section"),
        ("nope.t_l=3", "unknown section"),
        ("filter.t_l=abc", "filter.t_l: expected a number"),
        ("filter.t_l=-1", "t_l must be in \\[0.001, 100000\\]"),
        ("filter.method=ransac", "method='ransac' is not one of"),
        ("filter.max_iters=2.5", "expected an integer"),
        ("filter.coherence=maybe", "expected true or false"),
        ("noequals", "section.key=value"),
        ("filter.device=cpu", "unknown key filter.device"),  # the filter always runs in numpy
        ("ncc.cornerness_gate=true", "unknown key ncc.cornerness_gate"),  # removed switches
        ("tracks.align_to_anchor=true", "unknown key tracks.align_to_anchor"),
        # keys of the earlier layout name what replaced them
        ("ncc.lsm_radius=4", "ncc.lsm_radius is now lsm.radius"),
        ("ncc.lsm=false", "ncc.lsm is now lsm.enabled"),
        ("ncc.rectification=local", "ncc.rectification is now rectify.mode"),
        ("mapping.seed=3", "mapping.seed is now --seed"),
        ("match_check.seed=3", "match_check.seed is now --seed"),
        ("match_check.rounds=3", "match_check.rounds is now match_check.max_rounds"),
        ("pipeline.refine=false", "pipeline.refine is now pipeline.refine_keypoints"),
        ("pair_check.enabled=true", "pair check was removed"),
        ("ncc.match_blur=true", "ncc.match_blur is no longer a recipe key"),
        ("filter.sampling=uniform", "a fixed constant .FilterConfig.sampling"),
        ("ncc.perturbations=paper", "a fixed constant .NCCConfig.perturbations"),
        ("lsm.nope=1", "unknown key lsm.nope"),
    ],
)
def test_bad_overrides_name_the_key(override, message):
    with pytest.raises(ValueError, match=message.replace("(", r"\(")):
        load_recipe(None, [override])


def test_recipe_file_with_unknown_table(tmp_path):
    path = tmp_path / "mine.toml"
    path.write_text('[filtre]\nmethod = "mop"\n')
    with pytest.raises(ValueError, match=r"unknown table \[filtre\]"):
        load_recipe(str(path))
    with pytest.raises(ValueError, match="unknown recipe"):
        load_recipe("does_not_exist")


def test_the_dataclass_defaults_are_the_default_recipe():
    from colmap_miho.recipe import Recipe

    assert dataclasses.replace(load_recipe(), name="custom", description="") == Recipe()


def test_each_recipe_file_states_only_how_it_differs_from_the_defaults():
    import sys
    from importlib import resources

    from colmap_miho.recipe import SECTIONS

    tomllib = pytest.importorskip("tomllib" if sys.version_info >= (3, 11) else "tomli")
    for name in available_recipes():
        data = tomllib.loads((resources.files("colmap_miho.recipes") / f"{name}.toml").read_text("utf-8"))
        recipe = load_recipe(name)
        for section in set(data) & set(SECTIONS):
            default = SECTIONS[section]()
            same = [k for k in data[section] if getattr(getattr(recipe, section), k) == getattr(default, k)]
            assert not same, f"{name}: [{section}] restates the defaults of {same}"


def test_the_pairwise_preset_is_the_papers_ncc():
    from colmap_miho.refinement.config import PAIRWISE, NCCConfig

    cfg = NCCConfig.pairwise(move="2")
    assert (cfg.template_radius, cfg.search_radius, cfg.inner_radius, cfg.lsm.enabled) == (10, 10, 0, False)
    assert cfg.move == "2" and all(getattr(cfg, k) == v for k, v in PAIRWISE.items())
    assert NCCConfig().template_radius == 6 and NCCConfig().lsm.enabled
    assert NCCConfig.pairwise(lsm={"enabled": True}).lsm.tol_px == PAIRWISE["lsm"].tol_px


@pytest.mark.parametrize(("override", "message"), [
    ("filter.max_iters=1e3", "expected an integer, got '1e3'"),  # a float literal, as 2.5 is
    ("filter.max_iters=2.5", "expected an integer, got '2.5'"),
    ("filter.max_iters=10000000000000000000000001", "got 10000000000000000000000001"),  # exact, not through float
    ("match_check.max_threshold_px=1e-320", "subnormal"),
])
def test_integers_are_integer_literals_and_numbers_keep_their_digits(override, message):
    with pytest.raises(ValueError, match=message):
        load_recipe(None, [override])
    assert load_recipe(None, ["filter.max_iters= 1000 "]).filter.max_iters == 1000


@pytest.mark.parametrize(("key", "value"), [("filter.max_iters", "9" * 5000), ("filter.max_iters", "1." + "5" * 5000),
                                          ("filter.t_l", "x" * 5000), ("filter.coherence", "y" * 5000)],
                         ids=["huge integer", "long float", "long text", "long bool"])
def test_a_very_long_value_is_shown_cut_short(key, value):
    """(the whole 5,000-character value was echoed in the error line)"""
    with pytest.raises(ValueError) as err:
        load_recipe(None, [f"{key}={value}"])
    assert len(str(err.value)) < 300 and "characters)" in str(err.value), str(err.value)[:300]



def test_a_recipe_has_few_keys_and_every_table_mirrors_a_stage():
    from colmap_miho.recipe import SECTIONS, recipe_keys

    keys = recipe_keys()
    assert len(keys) <= 45 and len(set(keys)) == len(keys)
    assert {"lsm.radius", "lsm.enabled", "rectify.mode", "ncc.template_radius"} <= set(keys)
    assert list(SECTIONS) == ["filter", "ncc", "lsm", "rectify", "tracks", "pipeline", "mapping", "match_check"]
    recipe = load_recipe(None, ["lsm.radius=4", "rectify.mode=local"])
    assert recipe.ncc.lsm.radius == 4 and recipe.rectify.mode == "local" and recipe.ncc.lsm_window == 4


def test_every_stage_seed_derives_from_the_root():
    from colmap_miho.seeds import mapping_seed, match_check_seed, pair_seed

    # the default root gives the seeds the stages had before they were derived from one
    assert (match_check_seed(0), mapping_seed(0), mapping_seed(0, 2)) == (0, 0, 2)
    assert pair_seed(0, 1, 2) == pair_seed(0, 1, 2) != pair_seed(1, 1, 2)
    assert (match_check_seed(7), mapping_seed(7, 1)) == (7, 8)


def test_a_resumed_run_names_a_changed_key_of_a_nested_table(tmp_path):
    from colmap_miho.pipeline.store import fingerprint_difference, run_fingerprint

    db = tmp_path / "d.db"
    db.write_bytes(b"not read as a database here")
    a = run_fingerprint(db, tmp_path, load_recipe(), 0, "cpu")
    b = run_fingerprint(db, tmp_path, load_recipe(None, ["lsm.radius=4"]), 0, "cpu")
    assert fingerprint_difference(a, b).startswith("recipe value lsm.radius (8 then, 4 now)")
    assert "lsm" not in a["recipe"]["ncc"] and fingerprint_difference(a, a) is None
