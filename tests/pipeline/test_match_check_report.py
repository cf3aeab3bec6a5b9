"""The match check's per-pair removals in the JSON cannot be misread: image names are data, and a
name may hold any character (``|`` joined two names into one key before)."""

from __future__ import annotations

import json

import numpy as np

from colmap_miho.pipeline.match_check_stage import MatchCheckStats
from colmap_miho.reporting.html_report import removed_by_the_check
from colmap_miho.verification.config import MatchCheckConfig
from colmap_miho.verification.match_check import MatchCheckDecision


def test_removed_per_pair_names_each_pair_unambiguously():
    names = {1: "a|b", 2: "c", 3: "a", 4: "b|c"}  # "a|b" + "c" and "a" + "b|c" joined the same
    matches = {(1, 2): np.zeros((3, 2), np.int64), (3, 4): np.zeros((4, 2), np.int64)}
    d = MatchCheckDecision(used=True, rounds=1, failed={(1, 2): np.array([True, False, True]),
                                                        (3, 4): np.array([True, False, False, False])})
    stats = MatchCheckStats.of(d, MatchCheckConfig(), matches, names)
    rows = json.loads(json.dumps(stats.to_dict()))["removed_per_pair"]
    assert rows == [{"images": ["a|b", "c"], "image_ids": [1, 2], "removed": 2},
                    {"images": ["a", "b|c"], "image_ids": [3, 4], "removed": 1}]


def test_the_html_report_reads_both_layouts():
    rows = [{"images": ["b", "a"], "image_ids": [1, 2], "removed": 5},
            {"images": ["a", "c"], "image_ids": [2, 3], "removed": 1}]
    assert removed_by_the_check(rows) == {"a|b": 5, "a|c": 1}
    assert removed_by_the_check({"a|b": 5}) == {"a|b": 5}  # a report written before
    assert removed_by_the_check(None) == {} and removed_by_the_check([]) == {}


def test_pair_keys_of_the_comparison_cannot_collide():
    from colmap_miho.reporting.pair_labels import pair_label, pair_names

    assert pair_label("b.png", "a.png") == "a.png|b.png"  # plain names read as before
    assert pair_label("a|b", "c") != pair_label("a", "b|c")
    for pair in [("a|b", "c"), ("a", "b|c"), ("x\\", "|y"), ("", "\\|")]:
        assert pair_names(pair_label(*pair)) == tuple(sorted(pair))
    rows = [{"images": ["a|b", "c"], "removed": 2}, {"images": ["a", "b|c"], "removed": 1}]
    assert removed_by_the_check(rows) == {pair_label("a|b", "c"): 2, pair_label("a", "b|c"): 1}


def test_match_changes_keep_pairs_whose_names_hold_the_separator_apart(tmp_path):
    """Two pairs ``a|b`` + ``c`` and ``a`` + ``b|c`` in one database: two keys, two counts."""
    import sqlite3

    from colmap_miho.reporting.compare import match_changes
    from colmap_miho.reporting.pair_labels import pair_names
    from miho_bench.synthetic import make_synthetic_scene

    scene = make_synthetic_scene(tmp_path / "s", num_images=4, num_points=40, seed=5)
    con = sqlite3.connect(scene.database)
    ids = [i for (i,) in con.execute("SELECT image_id FROM images ORDER BY image_id")]
    for i, name in zip(ids, ["a|b", "c", "a", "b|c"], strict=True):
        con.execute("UPDATE images SET name = ? WHERE image_id = ?", (name, i))
    con.commit()
    con.close()
    before = match_changes(scene.database, scene.database)["matches_before"]
    assert len(before) == 6 and {pair_names(k) for k in before} >= {("a|b", "c"), ("a", "b|c")}
