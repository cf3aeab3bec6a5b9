"""Every file the run store reads back is checked before it is trusted: a manifest with values
of the wrong type, or a chunk forged with the run's own id (ids or keypoint indices out of
range, offsets that go back, a pair stored twice, arrays of the wrong type or shape), is a
damaged store (:class:`StoreDamaged`, exit 2) naming the file and saying ``--restart``, never a
crash, a wrong count or matches silently lost."""

from __future__ import annotations

import json

import numpy as np
import pytest

from colmap_miho.pipeline.records import PairOutcome
from colmap_miho.pipeline.store import RunStore, StoreDamaged

FINGERPRINT = {"database": "abc", "seed": 0, "recipe": {"filter": {"t_l": 1}}}
PLAN = {"budget": 1}
#: The run's pairs to filter and each image's keypoint count.
PAIRS = [(1, 2), (1, 3), (2, 3)]
KEYPOINTS = {1: 10, 2: 12, 3: 8}
#: The match check's stats as the stage stores them.
META = {"mode": "remove", "used": True, "reason": "", "rounds": 1, "images": 3, "images_registered": 3}


def _outcome(m: int, success: bool = True) -> PairOutcome:
    inliers = np.arange(m) % 3 != 0
    labels = np.where(inliers, np.arange(m) % 2, -1).astype(np.int64)
    return PairOutcome(inliers=inliers, labels=labels, patch_homographies=np.tile(np.eye(3), (2, 2, 1, 1)),
                       success=success)


def _matches(m: int) -> np.ndarray:
    return np.stack([np.arange(m), np.arange(m)[::-1]], axis=1).astype(np.uint32)


def _store(folder):
    """A store of two filter chunks ((1, 2), (1, 3) | (2, 3)) and one refine group."""
    store = RunStore.open(folder, FINGERPRINT)
    store.save_filter_chunk(0, PAIRS[:2], [_matches(6), _matches(4)], [_outcome(6), _outcome(4, False)])
    store.save_filter_chunk(1, PAIRS[2:], [_matches(5)], [_outcome(5)])
    store.refine_groups(PLAN)
    store.save_group(0, {1: (np.array([0, 3]), np.full((2, 2), 1.5)), 3: (np.array([7]), np.ones((1, 2)))},
                     {"moved": 3})
    store.save_stage("match_check", {"pairs": np.array([[1, 2]]), "offsets": np.array([0, 4]),
                                     "failed": np.zeros(4, bool), "wrong": np.zeros((0, 2), np.int64),
                                     "restored_pairs": np.array([[1, 3]]), "restored_offsets": np.array([0, 2]),
                                     "restored_rows": np.array([0, 5])}, META)
    store.close()


def _forge(folder, name: str, **changes) -> None:
    """Rewrite ``name`` with ``changes`` (None: the array left out), tied to the run as the store
    ties its own files (its ``run_id`` and file name): a forgery the ties cannot tell."""
    path = folder / name
    with np.load(path) as z:
        arrays = {k: z[k] for k in z.files}
    for key, value in changes.items():
        if value is None:
            arrays.pop(key)
        else:
            arrays[key] = np.asarray(value)
    np.savez(path, **arrays)


def _resume(folder) -> RunStore:
    store = RunStore.open(folder, FINGERPRINT, resume=True)
    store.expect(PAIRS, KEYPOINTS)
    return store


def _damaged(folder, name: str, why: str = ""):
    return pytest.raises(StoreDamaged, match=rf"{folder / name} is damaged \({why}.*--restart")


def test_an_untouched_store_is_read_back(tmp_path):
    _store(tmp_path)
    store = _resume(tmp_path)
    assert store.filtered_pairs() == set(PAIRS)
    counts = store.filter_counts()
    assert (counts.pairs, counts.pairs_ok, counts.matches_in, counts.matches_kept) == (3, 2, 11, 4 + 3)
    filtered = store.load_filtered()
    assert sorted(filtered) == [(1, 2), (2, 3)] and len(filtered[(1, 2)][0]) == 6
    groups = store.refine_groups(PLAN)
    assert sorted(groups[0][0]) == [1, 3] and groups[0][1] == {"moved": 3}
    arrays, meta = store.load_stage("match_check")
    assert meta == META
    from colmap_miho.pipeline.match_check_stage import _read_back

    failed, wrong, restored, _ = _read_back(store, arrays, meta)
    assert list(failed) == [(1, 2)] and not wrong
    assert list(restored) == [(1, 3)] and restored[(1, 3)].tolist() == [0, 5]
    store.close()


# -- the manifest -------------------------------------------------------------------------------
@pytest.mark.parametrize("field, value", [
    ("fingerprint", 1), ("fingerprint", [1, 2]), ("fingerprint", "abc"), ("fingerprint", None),
    ("recipe", 1), ("recipe", [1]), ("recipe", {"filter": 1}), ("recipe", {"filter": [1, 2]}),
    ("run_id", None), ("run_id", 5), ("run_id", ""), ("run_id", ["x"]), ("refine_plan", 1), ("refine_plan", [1]),
])
@pytest.mark.parametrize("resume", [False, True])
def test_a_manifest_value_of_the_wrong_type_is_a_damaged_store(field, value, resume, tmp_path):
    _store(tmp_path)
    path = tmp_path / "manifest.json"
    manifest = json.loads(path.read_text())
    if field == "recipe":
        manifest["fingerprint"]["recipe"] = value
    else:
        manifest[field] = value
    path.write_text(json.dumps(manifest))
    with _damaged(tmp_path, "manifest.json", "its"):
        RunStore.open(tmp_path, FINGERPRINT, resume=resume)
    RunStore.open(tmp_path, FINGERPRINT, restart=True).close()  # --restart is the way out


def test_a_manifest_without_run_id_is_a_damaged_store(tmp_path):
    """``run_id`` missing would switch off the check that each file is this run's own."""
    _store(tmp_path)
    path = tmp_path / "manifest.json"
    manifest = json.loads(path.read_text())
    del manifest["run_id"]
    path.write_text(json.dumps(manifest))
    with _damaged(tmp_path, "manifest.json", "its"):
        RunStore.open(tmp_path, FINGERPRINT, resume=True)


#: JSON nested deeper than Python's parser recurses (a RecursionError, "unexpected", at the CLI).
DEEP = "[" * 100_000 + "]" * 100_000


def test_a_manifest_nested_past_reading_is_a_damaged_store(tmp_path):
    _store(tmp_path)
    (tmp_path / "manifest.json").write_text(DEEP)
    with _damaged(tmp_path, "manifest.json", "maximum recursion"):
        RunStore.open(tmp_path, FINGERPRINT, resume=True)


def test_stats_and_meta_nested_past_reading_are_a_damaged_store(tmp_path):
    _store(tmp_path)
    _forge(tmp_path, "group-000000.npz", stats=np.array(DEEP))
    _forge(tmp_path, "stage-match_check.npz", meta=np.array(DEEP))
    store = _resume(tmp_path)
    with _damaged(tmp_path, "group-000000.npz", "its stats"):
        store.refine_groups(PLAN)
    with _damaged(tmp_path, "stage-match_check.npz", "maximum recursion"):
        store.load_stage("match_check")
    store.close()


def test_work_without_a_manifest_is_a_damaged_store(tmp_path):
    _store(tmp_path)
    (tmp_path / "manifest.json").unlink()
    with _damaged(tmp_path, "manifest.json", "it is missing"):
        RunStore.open(tmp_path, FINGERPRINT, resume=True)


# -- filter chunks ------------------------------------------------------------------------------
def _chunk_forgeries():
    big = 10**12
    return {
        "huge id": ({"pairs": [[big, 2], [1, 3]]}, "expect", "pair"),
        "id of no pair of the run": ({"pairs": [[2, 1], [1, 3]]}, "expect", "pair"),
        "huge index": ({"matches": np.vstack([[[4_000_000_000, 0]], _matches(5)]).astype(np.uint32)},
                       "expect", "keypoint"),
        "index beyond the image": ({"matches": np.vstack([[[10, 0]], _matches(5)]).astype(np.uint32)},
                                   "expect", "keypoint"),
        "negative index": ({"matches": np.vstack([[[-1, 0]], _matches(5)]).astype(np.int64)}, "open", "matches"),
        "reversed offsets": ({"offsets": [0, 6, 0]}, "open", "offsets"),
        "offsets past the end": ({"offsets": [0, 6, 9]}, "open", "offsets"),
        "offsets not from 0": ({"offsets": [1, 6, 6]}, "open", "offsets"),
        "rows for a failed pair": ({"offsets": [0, 3, 6]}, "open", "offsets"),
        "pair twice in one chunk": ({"pairs": [[1, 2], [1, 2]]}, "open", "twice"),
        "pair of another chunk": ({"pairs": [[2, 3], [1, 3]]}, "open", "filter-000000.npz holds too"),
        "pairs of floats": ({"pairs": [[1.0, 2.0], [1.0, 3.0]]}, "open", "pairs"),
        "pairs of another shape": ({"pairs": [1, 2, 1, 3]}, "open", "pairs"),
        "success of ints": ({"success": [1, 0]}, "open", "success"),
        "success too short": ({"success": [True]}, "open", "success"),
        "matches of floats": ({"matches": _matches(6).astype(float)}, "open", "matches"),
        "matches of three columns": ({"matches": np.zeros((6, 3), np.uint32)}, "open", "matches"),
        "inliers too short": ({"inliers": np.ones(5, bool)}, "open", "inliers"),
        "label past the homographies": ({"labels": [5, 0, 0, 0, 0, 0]}, "open", "labels"),
        "an inlier without a homography": ({"labels": [0, -1, 0, 0, 0, 0]}, "open", "labels"),
        "kept more than the inliers": ({"kept": [6, 0]}, "open", "kept"),
        "homography offsets reversed": ({"hom_offsets": [0, 2, 1]}, "open", "hom_offsets"),
        "homographies of another shape": ({"patch_homographies": np.zeros((2, 3, 3))}, "open", "patch_homographies"),
        "homography not finite": ({"patch_homographies": np.full((2, 2, 3, 3), np.nan)}, "open", "patch_homographies"),
        "an array missing": ({"kept": None}, "open", "no array"),
    }


@pytest.mark.parametrize("case", sorted(_chunk_forgeries()))
def test_a_forged_filter_chunk_is_a_damaged_store(case, tmp_path):
    changes, when, why = _chunk_forgeries()[case]
    _store(tmp_path)
    _forge(tmp_path, "filter-000000.npz", **changes)
    name = "filter-000001.npz" if "holds too" in why else "filter-000000.npz"
    with _damaged(tmp_path, name, f".*{why}"):
        store = RunStore.open(tmp_path, FINGERPRINT, resume=True)
        assert when == "expect", "should have been refused on opening"
        store.expect(PAIRS, KEYPOINTS)


def test_a_chunk_changed_after_opening_is_a_damaged_store(tmp_path):
    """A file is checked each time it is read, not once."""
    _store(tmp_path)
    store = _resume(tmp_path)
    _forge(tmp_path, "filter-000001.npz", offsets=[0, 2], matches=_matches(2), inliers=np.ones(2, bool),
           labels=np.zeros(2, np.int64), kept=[2])
    with _damaged(tmp_path, "filter-000001.npz", ".*changed"):
        store.load_filtered()
    store.close()


# -- refine groups ------------------------------------------------------------------------------
def _group_forgeries():
    return {
        "image of no pair": ({"image_ids": [1, 99]}, "image"),
        "huge image id": ({"image_ids": [1, 10**15]}, "image"),
        "image twice": ({"image_ids": [1, 1]}, "image"),
        "index beyond the image": ({"idx": [0, 3, 8]}, "keypoint"),
        "negative index": ({"idx": [-1, 3, 7]}, "keypoint"),
        "reversed offsets": ({"offsets": [0, 3, 2]}, "offsets"),
        "offsets past the end": ({"offsets": [0, 2, 4]}, "offsets"),
        "ids of floats": ({"image_ids": [1.0, 3.0]}, "image_ids"),
        "positions of another shape": ({"xy": np.zeros((3, 3))}, "xy"),
        "positions not finite": ({"xy": np.full((3, 2), np.inf)}, "xy"),
        "stats not an object": ({"stats": np.array("[1, 2]")}, "stats"),
        "stats not JSON": ({"stats": np.array("{")}, "stats"),
        "a stat not a number": ({"stats": np.array('{"moved": "3"}')}, "stats"),
        "a negative stat": ({"stats": np.array('{"moved": -1}')}, "stats' moved is -1, not a count"),
        "a stat not finite": ({"stats": np.array('{"seconds": NaN}')}, "stats' seconds is nan, not a count"),
        "decodes not per image": ({"stats": np.array('{"decoded_by_image": {"x": 1}}')}, "stats"),
    }


@pytest.mark.parametrize("case", sorted(_group_forgeries()))
def test_a_forged_refine_group_is_a_damaged_store(case, tmp_path):
    changes, why = _group_forgeries()[case]
    _store(tmp_path)
    _forge(tmp_path, "group-000000.npz", **changes)
    store = _resume(tmp_path)
    with _damaged(tmp_path, "group-000000.npz", f".*{why}"):
        store.refine_groups(PLAN)
    store.close()


#: Each image's (width, height) pixels.
SIZES = {1: (640, 480), 2: (640, 480), 3: (0, 0)}  # image 3's size unknown: not checked


@pytest.mark.parametrize("x", [1e300, -1e6, 640 + 100.0])
def test_a_group_moving_a_keypoint_far_outside_its_image_is_a_damaged_store(x, tmp_path):
    """A forged position (1e300 was written into the output as an infinite keypoint)."""
    _store(tmp_path)
    _forge(tmp_path, "group-000000.npz", xy=[[1.5, 1.5], [x, 2.0], [1.0, 1.0]])
    store = _resume(tmp_path)
    with _damaged(tmp_path, "group-000000.npz", ".*image 1 .*outside the 640x480 image"):
        store.refine_groups(PLAN, SIZES)
    store.close()


def test_a_group_moving_a_keypoint_a_little_past_the_border_is_read_back(tmp_path):
    _store(tmp_path)
    _forge(tmp_path, "group-000000.npz", xy=[[-3.0, 1.5], [639.5 + 10, 479.5], [1e6, 1e6]])
    store = _resume(tmp_path)
    groups = store.refine_groups(PLAN, SIZES)
    assert groups[0][0][1][1].tolist() == [[-3.0, 1.5], [649.5, 479.5]]
    store.close()


def test_a_group_of_no_group_of_the_plan_is_a_damaged_store(tmp_path):
    from colmap_miho.pipeline.refine_keypoints import check_resumed_groups

    _store(tmp_path)
    (tmp_path / "group-000000.npz").rename(tmp_path / "group-000005.npz")
    _forge(tmp_path, "group-000005.npz", file_name="group-000005.npz")
    store = _resume(tmp_path)
    done = store.refine_groups(PLAN)
    with _damaged(tmp_path, "group-000005.npz", ".*group 5 .*3 groups"):
        check_resumed_groups(store, done, 3)
    store.close()


# -- once-per-run stages ------------------------------------------------------------------------
@pytest.mark.parametrize("changes, why", [
    ({"offsets": [4, 0]}, "offsets"), ({"offsets": [0, 9]}, "offsets"), ({"pairs": [[1.0, 2.0]]}, "pairs"),
    ({"failed": np.zeros(4, np.int64)}, "failed"), ({"wrong": [1, 2]}, "wrong"),
    ({"restored_rows": np.array([0, -1])}, "restored rows"),
    ({"restored_offsets": np.array([0, 3])}, "restored_offsets"),
    ({"restored_pairs": np.array([[1, 3], [1, 3]])}, "restored"),
    ({"restored_rows": np.array([0.5, 1.0])}, "restored_rows"),
    ({"pairs": [[1, 2], [1, 2]], "offsets": [0, 2, 4]}, "twice"),
])
def test_a_forged_match_check_result_is_a_damaged_store(changes, why, tmp_path):
    from colmap_miho.pipeline.match_check_stage import _read_back

    _store(tmp_path)
    _forge(tmp_path, "stage-match_check.npz", **changes)
    store = _resume(tmp_path)
    arrays, meta = store.load_stage("match_check")
    with _damaged(tmp_path, "stage-match_check.npz", f".*{why}"):
        _read_back(store, arrays, meta)
    store.close()


@pytest.mark.parametrize("change", [{"used": "yes"}, {"rounds": 1.5}, {"wrong_pairs": 5}, {"images_trusted": [1]},
                                    {"wrong_pairs": [{"images": 1}]}, {"round_seconds": [{"mapper": "x"}]},
                                    {"unknown": 1}])
def test_forged_match_check_stats_are_a_damaged_store(change, tmp_path):
    from colmap_miho.pipeline.match_check_stage import _read_back

    _store(tmp_path)
    store = _resume(tmp_path)
    arrays, meta = store.load_stage("match_check")
    with _damaged(tmp_path, "stage-match_check.npz", ".*"):
        _read_back(store, arrays, {**meta, **change})
    store.close()
