"""The public Python API refuses, with one line naming the argument, what the CLI refuses:
``workers`` outside [1, 1024] or not an integer (``workers=10**6`` became the global mapper's
thread count), a seed that is not a 32-bit integer, and a path that is not a path. Every call
here fails before any work: no scene is needed."""

from __future__ import annotations

import numpy as np
import pytest

import colmap_miho as cm
from colmap_miho.errors import InvalidInput
from colmap_miho.pipeline.jobs import run_from_images

BAD_WORKERS = [(0, r"workers must be in \[1, 1024\] \(processes\), got 0"),
               (-1, r"workers must be in \[1, 1024\] \(processes\), got -1"),
               (10**6, r"workers must be in \[1, 1024\] \(processes\), got 1000000"),
               ("2", r"workers must be an integer, got '2'"),
               (2.5, r"workers must be an integer, got 2.5"),
               (True, r"workers must be an integer, got True")]
BAD_SEEDS = [(2**40, r"seed must be in \[0, 2147483647\] \(a 32-bit seed\), got 1099511627776"),
             (1.5, r"seed must be an integer, got 1.5"),
             (-1, r"seed must be in \[0, 2147483647\] \(a 32-bit seed\), got -1"),
             ("a", r"seed must be an integer, got 'a'")]


def _one_line(exc: pytest.ExceptionInfo) -> str:
    text = str(exc.value)
    assert "\n" not in text and isinstance(exc.value, ValueError)
    return text


@pytest.mark.parametrize(("workers", "message"), BAD_WORKERS)
def test_refine_database_bounds_workers(workers, message, tmp_path):
    with pytest.raises(InvalidInput, match=message) as exc:
        cm.refine_database(tmp_path / "missing.db", tmp_path, tmp_path / "o.db", workers=workers)
    _one_line(exc)


@pytest.mark.parametrize(("seed", "message"), BAD_SEEDS)
def test_refine_database_bounds_seed(seed, message, tmp_path):
    with pytest.raises(InvalidInput, match=message) as exc:
        cm.refine_database(tmp_path / "missing.db", tmp_path, tmp_path / "o.db", seed=seed)
    _one_line(exc)


@pytest.mark.parametrize("value", [None, 123, "", b"x.db"])
@pytest.mark.parametrize("argument", ["database", "image_dir", "output"])
def test_refine_database_names_a_bad_path(argument, value, tmp_path):
    if argument == "output" and value is None:
        return  # None: the default output beside the input
    args = {"database": tmp_path / "missing.db", "image_dir": tmp_path, "output": tmp_path / "o.db"}
    args[argument] = value
    with pytest.raises(InvalidInput, match=rf"^{argument} must be a path \(str or os.PathLike\), got "):
        cm.refine_database(args.pop("database"), args.pop("image_dir"), args.pop("output"))


@pytest.mark.parametrize(("workers", "message"), BAD_WORKERS)
def test_job_options_bound_workers(workers, message):
    with pytest.raises(InvalidInput, match=message):
        cm.JobOptions(workers=workers)


@pytest.mark.parametrize(("seed", "message"), BAD_SEEDS)
def test_job_options_bound_seed(seed, message):
    with pytest.raises(InvalidInput, match=message):
        cm.JobOptions(seed=seed)


@pytest.mark.parametrize("repeats", [0, 101, "2", 1.0])
def test_job_options_bound_repeats(repeats):
    with pytest.raises(InvalidInput, match="^repeats must be"):
        cm.JobOptions(repeats=repeats)


@pytest.mark.parametrize(("seed", "message"), BAD_SEEDS[1:])
def test_run_mapping_bounds_seed(seed, message, tmp_path):
    with pytest.raises(InvalidInput, match=message):
        cm.run_mapping(tmp_path / "missing.db", tmp_path, tmp_path / "m", seed=seed)


@pytest.mark.parametrize("call", ["run_mapping", "compare_databases", "run_from_images", "extract_and_match"])
def test_entry_points_name_a_none_path(call, tmp_path):
    calls = {"run_mapping": lambda: cm.run_mapping(None, tmp_path, tmp_path / "m"),
             "compare_databases": lambda: cm.compare_databases(tmp_path / "x.db", tmp_path, None),
             "run_from_images": lambda: run_from_images(123, tmp_path / "out"),
             "extract_and_match": lambda: cm.extract_and_match(tmp_path, None)}
    with pytest.raises(InvalidInput, match=r"^(database|output|image_dir) must be a path"):
        calls[call]()
    assert not (tmp_path / "m").exists() and not (tmp_path / "out").exists()


@pytest.mark.parametrize(("max_features", "message"), [(0, r"max_features must be in \[1, 1000000\]"),
                                                        (2.5, "max_features must be an integer")])
def test_extraction_bounds_max_features(max_features, message, tmp_path):
    with pytest.raises(InvalidInput, match=message):
        cm.extract_and_match(tmp_path, tmp_path / "new.db", max_features=max_features)
    with pytest.raises(InvalidInput, match=message):
        cm.ExtractionOptions(max_features=max_features)


def test_build_report_bounds_seed(tmp_path):
    with pytest.raises(InvalidInput, match=r"seed must be in \[0, 2147483647\]"):
        cm.build_report(tmp_path, seed=2**40)


@pytest.mark.parametrize(("seed", "message"), [(2**40, r"seed must be in \[0, 4294967295\]"),
                                                (-1, r"seed must be in \[0, 4294967295\]"),
                                                (1.5, "seed must be an integer"), ("a", "seed must be an integer")])
def test_filter_matches_bounds_seed(seed, message):
    pts = np.random.default_rng(0).uniform(0, 100, (20, 2))
    with pytest.raises(InvalidInput, match=message):
        cm.filter_matches(pts, pts + 1, seed=seed)


def test_filter_matches_takes_numpy_and_32_bit_seeds():
    """The pipeline gives each pair a ``SeedSequence`` state: any uint32, often a numpy integer."""
    pts = np.random.default_rng(0).uniform(0, 100, (20, 2))
    a = cm.filter_matches(pts, pts + 1, seed=np.uint32(2**32 - 1))
    b = cm.filter_matches(pts, pts + 1, seed=2**32 - 1)
    assert np.array_equal(a.inliers, b.inliers)


@pytest.mark.parametrize(("model", "params", "message"), [("BOGUS", "", "unknown camera model 'BOGUS'"),
                                                          ("PINHOLE", "1,2", "PINHOLE takes 4 parameters, got 2"),
                                                          ("PINHOLE", "a,b,c,d", "'a' is not a number")])
def test_extraction_camera_is_checked_before_colmap(model, params, message, tmp_path, capfd):
    """COLMAP's own check says only ``Check failed: ExistsCameraModelWithName(...)`` (an
    "unexpected" error after ``run`` made its output folder)."""
    from colmap_miho.cli import main

    with pytest.raises(InvalidInput, match=message):
        cm.extract_and_match(tmp_path, tmp_path / "new.db", camera_model=model, camera_params=params)
    with pytest.raises(InvalidInput, match=message):
        cm.ExtractionOptions(camera_model=model, camera_params=params)
    capfd.readouterr()
    (tmp_path / "images").mkdir()
    argv = ["run", "--images", str(tmp_path / "images"), "--output", str(tmp_path / "out"), "--camera-model", model,
            "-q"]
    assert main([*argv, "--camera-params", params] if params else argv) == 2
    lines = [ln for ln in capfd.readouterr().err.splitlines() if ln.startswith("ERROR")]
    assert len(lines) == 1 and message in lines[0] and "unexpected" not in lines[0], lines
    assert not (tmp_path / "out").exists() and not (tmp_path / "new.db").exists()


def test_wrong_types_for_the_whole_jobs_are_named(tmp_path):
    from colmap_miho.sfm import MappingConfig

    with pytest.raises(InvalidInput, match="^config must be of type MappingConfig, got str$"):
        cm.run_mapping(tmp_path / "x.db", tmp_path, tmp_path / "m", config="x")
    with pytest.raises(InvalidInput, match=r"^pairs must be a pairs file or a list of \(name1, name2\), got int$"):
        cm.compare_databases(tmp_path / "x.db", tmp_path, tmp_path / "c", pairs=123)
    with pytest.raises(InvalidInput, match="^options must be of type JobOptions, got dict$"):
        cm.compare_databases(tmp_path / "x.db", tmp_path, tmp_path / "c", options={"workers": 2})
    with pytest.raises(InvalidInput, match="^extraction must be of type ExtractionOptions, got dict$"):
        run_from_images(tmp_path, tmp_path / "out", extraction={})
    assert not (tmp_path / "m").exists() and not (tmp_path / "c").exists() and not (tmp_path / "out").exists()
    with pytest.raises(InvalidInput, match="^num_threads must be a number, got '4'$"):
        MappingConfig(num_threads="4")
    with pytest.raises(InvalidInput, match="^t_l must be a number, got '3'$"):
        cm.FilterConfig(t_l="3")


IMG = np.zeros((40, 40), np.uint8)
ONE = np.tile(np.eye(3), (1, 2, 1, 1))


@pytest.mark.parametrize(("args", "message"), [
    (("x.png", IMG, [[5.0, 5.0]], [[5.0, 5.0]]), "got str .read a file first"),
    ((None, IMG, [[5.0, 5.0]], [[5.0, 5.0]]), "got NoneType"),
    ((np.zeros((0, 0), np.uint8), IMG, [[5.0, 5.0]], [[5.0, 5.0]]), "must hold pixels"),
    ((IMG, IMG, [[np.nan, 5.0]], [[5.0, 5.0]]), "pts1 holds NaN or inf"),
    ((IMG, IMG, [[5.0, 5.0]], [[5.0, np.inf]]), "pts2 holds NaN or inf"),
    ((IMG, IMG, [["a", 5.0]], [[5.0, 5.0]]), "pts1 must be a numeric array"),
])
def test_refine_pair_names_a_bad_input(args, message):
    with pytest.raises(InvalidInput, match=message):
        cm.refine_pair(*args, ONE)


@pytest.mark.parametrize("config", ["ncc", {"move": "1"}, cm.FilterConfig()])
def test_refine_pair_names_a_config_of_another_type(config):
    """(an AttributeError on ``config.move``)"""
    with pytest.raises(InvalidInput, match="config must be an NCCConfig, got "):
        cm.refine_pair(IMG, IMG, [[5.0, 5.0]], [[5.0, 5.0]], ONE, config=config)


@pytest.mark.parametrize(("kwargs", "message"), [
    ({"config": "x"}, "config must be a Recipe, an NCCConfig, a TrackConfig or a tuple .* got str"),
    ({"config": (1, 2)}, "the NCC config must be an NCCConfig, got int"),
    ({"config": (cm.NCCConfig(),)}, "got 1 items"),
    ({"ncc_config": cm.FilterConfig()}, "the NCC config must be an NCCConfig, got FilterConfig"),
    ({"track_config": cm.NCCConfig()}, "the track config must be a TrackConfig, got NCCConfig"),
])
def test_refine_tracks_names_a_config_of_another_type(kwargs, message):
    """(a config of another type was silently replaced by the defaults, or an AttributeError)"""
    with pytest.raises(InvalidInput, match=message):
        cm.refine_tracks({1: IMG}, {1: np.zeros((1, 2))}, {}, {}, **kwargs)


@pytest.mark.parametrize(("args", "message"), [((None, 5), "overrides must be a list"),
                                               ((5,), "recipe must be a recipe name"),
                                               ((None, "filter.t_l=3"), "overrides must be a list")])
def test_load_recipe_names_a_wrong_type(args, message):
    with pytest.raises(InvalidInput, match=message):
        cm.load_recipe(*args)


def test_an_existing_output_tells_python_callers_what_to_pass(tmp_path):
    from colmap_miho.adapters.working_copy import WorkingCopy

    db = tmp_path / "in.db"
    db.write_bytes(b"x")
    (tmp_path / "out.db").write_bytes(b"y")
    from colmap_miho.errors import UserError

    with pytest.raises(UserError, match="overwrite=True in Python"):
        with WorkingCopy(db, tmp_path / "out.db"):
            pass
