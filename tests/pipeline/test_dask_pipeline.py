"""``refine --dask``: a local Dask cluster of 2 workers writes the same database as the
process pool and as one process (only the client writes SQLite)."""

from __future__ import annotations

import pytest
from helpers.db_contents import assert_same_database
from helpers.small_budget import two_images

from colmap_miho.pipeline import filter as filter_stage
from colmap_miho.pipeline import track_groups
from colmap_miho.pipeline.executor import LOCAL
from colmap_miho.pipeline.refine_job import refine_database
from colmap_miho.pipeline_config import PipelineConfig
from miho_bench.synthetic import make_synthetic_scene


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    return make_synthetic_scene(tmp_path_factory.mktemp("dask"), num_images=4, num_points=80,
                                outlier_ratio=0.15, noise_px=1.0, seed=9)


def test_local_cluster_equals_process_pool_and_one_process(scene, tmp_path, monkeypatch):
    # small scene: let the process pool take it too (it keeps small jobs in this process)
    monkeypatch.setattr(filter_stage, "MIN_PAIRS_PER_WORKER", 1)
    monkeypatch.setattr(filter_stage, "MIN_MATCHES_PER_FILTER_WORKER", 0)
    monkeypatch.setattr(track_groups, "MIN_MATCHES_PER_REFINE_WORKER", 10)
    monkeypatch.setattr(track_groups, "MIN_MATCHES_TO_START_WORKERS", 0)
    monkeypatch.setattr(PipelineConfig, "image_budget_bytes", two_images)  # several track groups
    one = refine_database(scene.database, scene.image_dir, tmp_path / "one.db", workers=1, device="cpu")
    pool = refine_database(scene.database, scene.image_dir, tmp_path / "pool.db", workers=2, device="cpu")
    dask = refine_database(scene.database, scene.image_dir, tmp_path / "dask.db", workers=2, device="cpu",
                           dask=LOCAL)
    assert (one.runner, pool.runner, dask.runner) == ("inline", "processes", "dask")
    assert pool.workers == dask.workers == 2
    assert dask.filter_chunks >= 2  # the pairs were spread over the cluster in chunks
    assert dask.refine_groups >= 2 and dask.refine_stats["workers"] == 2  # and the track groups
    assert dask.keypoints_moved > 0 and dask.matches_removed > 0
    assert_same_database(one.output, pool.output)
    assert_same_database(pool.output, dask.output)


def test_dask_option_without_value_is_a_local_cluster():
    from colmap_miho.cli import build_parser

    base = ["refine", "--database", "d.db", "--images", "imgs"]
    parse = build_parser().parse_args
    assert parse(base).dask is None
    assert parse([*base, "--dask"]).dask == LOCAL
    assert parse([*base, "--dask", "--workers", "3"]).dask == LOCAL
    assert parse([*base, "--dask", "tcp://head:8786"]).dask == "tcp://head:8786"


def test_unreachable_scheduler_is_one_line_and_leaves_no_store(scene, tmp_path, monkeypatch, capsys):
    from colmap_miho.cli import main
    from colmap_miho.pipeline.store import store_folder

    monkeypatch.setattr("colmap_miho.pipeline.executor.CONNECT_TIMEOUT_S", 2)
    out = tmp_path / "o.db"
    assert main(["refine", "--database", str(scene.database), "--images", str(scene.image_dir),
                 "--output", str(out), "--dask", "tcp://127.0.0.1:1", "-q"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "cannot reach the Dask scheduler" in err[0]
    assert not out.exists() and not store_folder(out).exists()
