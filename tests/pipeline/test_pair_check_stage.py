"""The pair-check stage inside ``refine``: removed pairs leave the output, flagged ones stay, the
report says which and why."""

from __future__ import annotations

import json

import numpy as np
import pytest
from doppelganger import FOCAL, HEIGHT, WIDTH, make_doppelganger_scene

from colmap_miho.adapters.database import ColmapDatabase
from colmap_miho.pipeline.run import refine_database
from colmap_miho.recipe import load_recipe


@pytest.fixture(scope="module")
def dopp_db(tmp_path_factory):
    """A database of a synthetic doppelganger scene (verified matches = the scene's matches),
    its image folder, and the scene."""
    root = tmp_path_factory.mktemp("dopp")
    scene = make_doppelganger_scene(seed=1, fooled_prob=0.3)
    path = root / "database.db"
    with ColmapDatabase.create(path) as db:
        cam, rig = db.add_camera("PINHOLE", WIDTH, HEIGHT, FOCAL)
        ids = {i: db.add_image(f"{i:03d}.png", cam, rig) for i in sorted(scene.keypoints)}
        assert all(ids[i] == i for i in ids)
        for i, kp in scene.keypoints.items():
            db.add_keypoints(i, kp)
        for (i, j), m in scene.matches.items():
            db.add_matches(i, j, m.astype(np.uint32), as_inliers=True)
    (root / "images").mkdir()
    return path, root / "images", scene


def _pairs(path, tmp_path):
    copy = tmp_path / "copy.db"
    copy.write_bytes(path.read_bytes())
    with ColmapDatabase(copy) as db:
        return {(p.image_id1, p.image_id2) for p in db.pairs("verified")}


def _run(dopp_db, tmp_path, *sets):
    path, images, _ = dopp_db
    rec = load_recipe(None, ["pipeline.refine=false", "match_check.mode=off", *sets])
    out = tmp_path / "out.db"
    summary = refine_database(path, images, out, recipe=rec, workers=1, json_path=tmp_path / "s.json")
    return summary, json.loads((tmp_path / "s.json").read_text())


def test_removed_pairs_leave_the_output(dopp_db, tmp_path):
    _, _, scene = dopp_db
    summary, report = _run(dopp_db, tmp_path, "pair_check.enabled=true")
    pc = report["pair_check"]
    removed = {tuple(w["image_ids"]) for w in pc["wrong_pairs"]}
    assert pc["mode"] == "remove" and pc["pairs_removed"] == len(removed) > 0 and pc["pairs_flagged"] == 0
    assert all(scene.wrong[p] for p in removed)  # only doppelganger pairs
    left = _pairs(tmp_path / "out.db", tmp_path)
    assert not removed & left and len(left) == pc["pairs_checked"] - len(removed)
    assert all(w["reason"] and w["images"] == [f"{i:03d}.png" for i in w["image_ids"]] for w in pc["wrong_pairs"])
    assert "pair_check" in summary.seconds and "pair check:" in summary.format()


#: ``pipeline.min_matches`` above every pair's size: nothing is filtered, every pair is written
#: back unchanged (the pair check then reads them all from the database); faster.
UNFILTERED = "pipeline.min_matches=100000"


def test_unfiltered_pairs_removed_too(dopp_db, tmp_path):
    _, _, scene = dopp_db
    _, report = _run(dopp_db, tmp_path, "pair_check.enabled=true", UNFILTERED)
    pc = report["pair_check"]
    removed = {tuple(w["image_ids"]) for w in pc["wrong_pairs"]}
    assert report["pairs_filtered"] == 0 and pc["pairs_checked"] == len(scene.matches) and removed
    assert not removed & _pairs(tmp_path / "out.db", tmp_path)


def test_flag_mode_keeps_the_pairs(dopp_db, tmp_path):
    _, report = _run(dopp_db, tmp_path, "pair_check.enabled=true", "pair_check.mode=flag", UNFILTERED)
    pc = report["pair_check"]
    assert pc["pairs_removed"] == 0 and pc["pairs_flagged"] == len(pc["wrong_pairs"]) > 0
    assert len(_pairs(tmp_path / "out.db", tmp_path)) == pc["pairs_checked"]


def test_off_by_default_and_report_unchanged(dopp_db, tmp_path):
    summary, report = _run(dopp_db, tmp_path, UNFILTERED)
    assert report["pair_check"] == {} and "pair_check" not in summary.seconds
    assert "pair check" not in summary.format()
