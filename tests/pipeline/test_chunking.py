"""The filter stage's chunks: sized by the memory budget, and the output does not depend on
them (bit-identical databases with one pair per chunk and with the default chunks) nor on
which process filtered them."""

from __future__ import annotations

from concurrent.futures import Future

import pytest
from helpers.db_contents import assert_same_database, database_rows

from colmap_miho.adapters.database import PairRecord
from colmap_miho.pipeline import filter as filter_stage
from colmap_miho.pipeline.executor import Runner
from colmap_miho.pipeline.filter import chunk_matches, plan_chunks
from colmap_miho.pipeline.refine_job import refine_database
from colmap_miho.pipeline_config import PipelineConfig
from colmap_miho.recipe import load_recipe
from miho_bench.synthetic import make_synthetic_scene


def _pairs(*counts):
    return [PairRecord(1, k + 2, n) for k, n in enumerate(counts)]


def test_plan_chunks_cuts_by_match_count_in_order():
    chunks = plan_chunks(_pairs(5, 5, 5, 20, 3, 3), 10)
    assert [[p.num_matches for p in c] for c in chunks] == [[5, 5], [5], [20], [3, 3]]
    assert [p for c in chunks for p in c] == _pairs(5, 5, 5, 20, 3, 3)  # every pair once, in order
    assert plan_chunks([], 10) == []


def test_chunk_size_follows_the_budget_and_the_slots(monkeypatch):
    mib = 2**20
    assert chunk_matches(2048 * mib, 1, 10**9) == filter_stage.MAX_CHUNK_MATCHES  # the resume cap
    monkeypatch.setattr(filter_stage, "MAX_CHUNK_MATCHES", 10**9)
    one = chunk_matches(256 * mib, 1, 10**9)
    # 256 MiB x 1/4 over 2 chunks in flight x 160 bytes per match
    assert one == int(256 * mib * filter_stage.FILTER_BUDGET_SHARE
                      / (filter_stage.IN_FLIGHT_PER_SLOT * filter_stage.BYTES_PER_MATCH_IN_FLIGHT))
    assert chunk_matches(128 * mib, 1, 10**9) == one // 2  # half the budget, half the chunk
    # parallel: at least CHUNKS_PER_SLOT chunks per slot
    assert chunk_matches(2048 * mib, 2, 80_000) == 10_000
    assert chunk_matches(2048 * mib, 2, 3) == 1


def test_memory_budget_is_validated():
    assert PipelineConfig().memory_budget_mb == 2048
    with pytest.raises(ValueError, match=r"memory_budget_mb must be in \[256, "):
        PipelineConfig(memory_budget_mb=100)
    with pytest.raises(ValueError, match="memory_budget_mb"):
        load_recipe(None, ["pipeline.memory_budget_mb=12"])


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    return make_synthetic_scene(tmp_path_factory.mktemp("chunks"), num_images=5, num_points=80,
                                outlier_ratio=0.15, noise_px=1.0, seed=7)


def test_tiny_and_default_chunks_write_identical_databases(scene, tmp_path, monkeypatch):
    ref = refine_database(scene.database, scene.image_dir, tmp_path / "default.db", workers=1, device="cpu")
    monkeypatch.setattr(filter_stage, "MAX_CHUNK_MATCHES", 1)  # one pair per chunk
    tiny = refine_database(scene.database, scene.image_dir, tmp_path / "tiny.db", workers=1, device="cpu")
    assert ref.filter_chunks == 1 and tiny.filter_chunks == tiny.pairs_filtered == 10
    assert ref.keypoints_moved > 0 and ref.matches_removed > 0  # both stages changed something
    assert (tiny.matches_in, tiny.matches_kept, tiny.keypoints_moved) == \
        (ref.matches_in, ref.matches_kept, ref.keypoints_moved)
    assert_same_database(ref.output, tiny.output)
    # and the comparison can fail: the input differs from the output
    assert database_rows(scene.database)["matches"] != database_rows(ref.output)["matches"]
    assert not any(p.name.endswith(".miho-run") for p in tmp_path.iterdir())  # stores removed


def test_this_process_filters_while_the_pool_starts(scene, tmp_path, monkeypatch):
    """Chunks filtered here while the pool starts and chunks filtered by the pool make the
    same database as one process (the pool is replaced by calls here that record the
    chunks sent to it)."""
    ref = refine_database(scene.database, scene.image_dir, tmp_path / "one.db", workers=1, device="cpu")
    monkeypatch.setattr(filter_stage, "MAX_CHUNK_MATCHES", 1)  # one pair per chunk
    monkeypatch.setattr(filter_stage, "MIN_PAIRS_PER_WORKER", 1)
    monkeypatch.setattr(filter_stage, "MIN_MATCHES_PER_FILTER_WORKER", 0)

    def starting_for_three_chunks(self):
        left = [3]

        def starting() -> bool:
            left[0] -= 1
            return left[0] >= 0
        return starting

    sent = []

    def submit(self, fn, *args):
        sent.append(fn)
        fut: Future = Future()
        fut.set_result(fn(*args))
        return fut

    monkeypatch.setattr(Runner, "start_in_background", starting_for_three_chunks)
    monkeypatch.setattr(Runner, "submit", submit)
    two = refine_database(scene.database, scene.image_dir, tmp_path / "two.db", workers=2, device="cpu")
    assert two.filter_chunks == 10 and len(sent) == 10 - 3
    assert_same_database(ref.output, two.output)
