"""The global estimate's positioning from a share of the tracks (the longest, until each image
has ``positioning_tracks_per_image``; a research switch, off by default): the option reaches the
mapper, the estimate is as true as the one from every track on a survey, and where the share
loses images every track is used."""

from __future__ import annotations

import numpy as np
import pycolmap
import pytest

from colmap_miho.adapters.database import ColmapDatabase
from colmap_miho.geometry import rotation_angle_deg
from colmap_miho.sfm.global_estimate import global_estimate
from colmap_miho.verification import MatchCheckConfig
from miho_bench.calibrated_survey import make_calibrated_survey
from miho_bench.variants import variant

CAPPED = variant(MatchCheckConfig(), positioning_tracks_per_image=100)


@pytest.fixture(scope="module")
def survey(tmp_path_factory):
    sc = make_calibrated_survey(tmp_path_factory.mktemp("positioning"), num_images=40, graph="sequential",
                                render_images=False, seed=2)
    with ColmapDatabase(sc.database) as db:
        matches = {(p.image_id1, p.image_id2): db.matches(p.image_id1, p.image_id2, "verified").astype(np.int64)
                   for p in db.pairs("verified")}
    return sc, matches


def _estimate(sc, matches, cfg, monkeypatch):
    seen = {}
    real = pycolmap.global_mapping

    def spy(database, image_path, output_path, options):
        seen["tracks_per_view"] = options.mapper.track_required_tracks_per_view
        return real(database, image_path, output_path, options)

    monkeypatch.setattr(pycolmap, "global_mapping", spy)
    with ColmapDatabase(sc.database) as db:
        est = global_estimate(db, matches, cfg, seed=0, num_threads=1)
    return est, seen["tracks_per_view"]


def _worst_rotation_error_deg(sc, est) -> float:
    gt = {int(i): im.cam_from_world().rotation.matrix() for i, im in sc.gt_reconstruction.images.items()}
    ids = sorted(est.poses)
    worst = 0.0
    for a, b in zip(ids, ids[1:], strict=False):
        r_est = est.poses[b][0] @ est.poses[a][0].T
        r_gt = gt[b] @ gt[a].T
        worst = max(worst, rotation_angle_deg(r_est, r_gt))
    return worst


def test_the_positioning_gets_its_tracks_per_image_and_every_image_is_placed(survey, monkeypatch):
    sc, matches = survey
    est, tracks_per_view = _estimate(sc, matches, CAPPED, monkeypatch)
    assert tracks_per_view == 100
    assert len(est.poses) == 40
    assert _worst_rotation_error_deg(sc, est) < 0.5


def test_the_estimate_is_as_true_as_the_one_from_every_track(survey, monkeypatch):
    sc, matches = survey
    capped, _ = _estimate(sc, matches, CAPPED, monkeypatch)
    every, tracks_per_view = _estimate(sc, matches, MatchCheckConfig(), monkeypatch)
    assert MatchCheckConfig.positioning_tracks_per_image == 0
    assert tracks_per_view > 10**9  # COLMAP's default: every track
    assert _worst_rotation_error_deg(sc, capped) < max(0.5, 2 * _worst_rotation_error_deg(sc, every))
    # the judging's observations come from every track (retriangulated), not only the positioning's
    def observed(est):
        return sum(len(o[0]) for o in est.observations.values())

    assert observed(capped) >= 0.99 * observed(every)


def test_where_the_share_of_tracks_loses_images_every_track_is_used(survey, monkeypatch):
    import colmap_miho.sfm.global_estimate as ge

    sc, matches = survey
    real = ge._run_mapper
    calls = []

    def losing(pc, folder, cfg, seed, num_threads, verbose, tracks_per_image, name="model"):
        calls.append(tracks_per_image)
        recs, failure, steps = real(pc, folder, cfg, seed, num_threads, verbose, tracks_per_image, name)
        if tracks_per_image > 0:  # as on a sparse ring: the positioning's share of the tracks loses an image
            rec = max(recs.values(), key=lambda r: r.num_reg_images())
            rec.deregister_frame(next(iter(rec.reg_frame_ids())))
        return recs, failure, steps

    monkeypatch.setattr(ge, "_run_mapper", losing)
    with ColmapDatabase(sc.database) as db:
        est = global_estimate(db, matches, CAPPED, seed=0, num_threads=1)
    assert calls == [100, 0]
    assert len(est.poses) == 40 and "mapper_every_track" in est.seconds
