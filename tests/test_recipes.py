import pytest

from colmap_miho.enums import FilterMethod, MatchSource
from colmap_miho.recipe import available_recipes, load_recipe


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
    assert recipe.filter.method is FilterMethod.MOP_MIHO
    assert recipe.pipeline.refine is True
    assert recipe.filter.inlier_count == 8 and recipe.filter.strict_threshold == 7.5


def test_overrides_are_typed():
    recipe = load_recipe("mop", ["filter.t_l=12", "pipeline.source=raw", "pipeline.refine=yes", "filter.t_h=none"])
    assert recipe.filter.t_l == 12.0 and recipe.filter.t_h is None
    assert recipe.pipeline.source is MatchSource.RAW and recipe.pipeline.refine is True


@pytest.mark.parametrize(
    "override, message",
    [
        ("filter.t_lx=3", "unknown key filter.t_lx"),
        ("t_l=3", "needs a section"),
        ("nope.t_l=3", "unknown section"),
        ("filter.t_l=abc", "filter.t_l: expected a number"),
        ("filter.t_l=-1", "t_l must be > 0"),
        ("filter.method=ransac", "method='ransac' is not one of"),
        ("filter.max_iters=2.5", "expected an integer"),
        ("filter.rotation_fix=maybe", "expected true or false"),
        ("noequals", "section.key=value"),
        ("filter.device=cpu", "unknown key filter.device"),  # the filter always runs in numpy
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
