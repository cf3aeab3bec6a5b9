"""The keypoint refinement stage over groups of tracks (``pipeline.track_groups.walk_groups``):
bit-identical keypoints whatever the runner and its slots, the same moves whatever the image
budget; resume from finished groups; each group reported once; images decoded once per group
at most."""

from __future__ import annotations

import numpy as np
import pytest

from colmap_miho.adapters.database import ColmapDatabase
from colmap_miho.adapters.images import ImageLoader
from colmap_miho.filtering.api import filter_matches
from colmap_miho.pipeline import track_groups
from colmap_miho.pipeline.executor import open_runner
from colmap_miho.refinement.config import NCCConfig, TrackConfig
from miho_bench.synthetic import make_synthetic_scene

NCC = NCCConfig.pairwise(device="cpu", template_radius=6)
TRACKS = TrackConfig()


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    """6 rendered images; every pair's verified matches filtered by MOP+MiHo."""
    sc = make_synthetic_scene(tmp_path_factory.mktemp("stage"), num_images=6, num_points=160,
                              outlier_ratio=0.1, noise_px=1.0, seed=3)
    with ColmapDatabase(sc.database) as db:
        images = db.images()
        kps = {im.image_id: db.keypoints(im.image_id) for im in images}
        pairs = {}
        for p in db.pairs("verified"):
            m = db.matches(p.image_id1, p.image_id2, "verified")
            res = filter_matches(kps[p.image_id1][m[:, 0]], kps[p.image_id2][m[:, 1]], seed=1)
            if res.success:
                pairs[(p.image_id1, p.image_id2)] = (m, res)
    names = {im.image_id: im.name for im in images}
    sizes = {im.image_id: (im.width, im.height) for im in images}
    return sc, kps, pairs, names, sizes


def _loader(scene, **kw):
    sc, _, _, names, sizes = scene
    return ImageLoader(sc.image_dir, names, expected_sizes=sizes, **kw)


def _run(scene, runner, budget, **kw):
    _, kps, pairs, _, sizes = scene
    return track_groups.walk_groups(_loader(scene, max_cached=None), kps, pairs, None, NCC, TRACKS,
                                   runner=runner, image_budget_bytes=budget, **kw)


def _image_bytes(scene):
    w, h = next(iter(scene[4].values()))
    return 4 * w * h


def test_same_keypoints_whatever_the_runner_and_budget(scene, monkeypatch):
    """Bit-identical keypoints in this process and in 2 worker processes, and with another
    budget (other groups, hence other refine calls: a match's NCC does not depend on them)."""
    monkeypatch.setattr(track_groups, "MIN_MATCHES_PER_REFINE_WORKER", 20)  # several groups, 2 workers
    monkeypatch.setattr(track_groups, "MIN_MATCHES_TO_START_WORKERS", 0)
    one = _image_bytes(scene)
    with open_runner(1) as inline:
        ref, ref_stats, used = _run(scene, inline, 3 * one)
        assert used == 1 and ref_stats["moved"] > 100 and ref_stats["groups"] > 1
        tiny, tiny_stats, _ = _run(scene, inline, 2 * one)
        assert tiny_stats["group_max_images"] == 2 and tiny_stats["groups"] >= ref_stats["groups"]
    with open_runner(2) as pool:
        par, par_stats, used = _run(scene, pool, 3 * one)
    assert used == 2
    kps = scene[1]
    for i in kps:
        np.testing.assert_array_equal(par[i], ref[i])
        np.testing.assert_array_equal(tiny[i] != kps[i], ref[i] != kps[i])
        np.testing.assert_array_equal(tiny[i], ref[i])
    for key in ("moved", "refined", "rejected"):
        assert tiny_stats[key] == par_stats[key] == ref_stats[key]
    assert sum(int(np.any(ref[i] != kps[i], 1).sum()) for i in kps) == ref_stats["moved"]


def test_resume_skips_done_groups_and_reports_each_group_once(scene, monkeypatch):
    monkeypatch.setattr(track_groups, "MIN_MATCHES_PER_REFINE_WORKER", 20)
    monkeypatch.setattr(track_groups, "MIN_MATCHES_TO_START_WORKERS", 0)
    budget = 3 * _image_bytes(scene)
    seen: dict = {}
    with open_runner(1) as inline:
        full, stats, _ = _run(scene, inline, budget, on_group=lambda g, m, st: seen.setdefault(g, (m, st)))
        n = stats["groups"]
        assert sorted(seen) == list(range(n)) and n >= 3
        kps = scene[1]
        for m, _ in seen.values():
            for i, (idx, xy) in m.items():
                assert idx.dtype == np.int64 and xy.shape == (idx.size, 2)
                np.testing.assert_array_equal(full[i][idx], xy)
        done = {g: seen[g] for g in range(0, n, 2)}
        again: list = []
        resumed, rstats, _ = _run(scene, inline, budget, done=done,
                                  on_group=lambda g, m, st: again.append(g))
    assert again == [g for g in range(n) if g not in done] and rstats["groups_resumed"] == len(done)
    for i in kps:
        np.testing.assert_array_equal(resumed[i], full[i])
    assert rstats["moved"] == stats["moved"]
    with pytest.raises(ValueError, match="resumed group"), open_runner(1) as inline:
        _run(scene, inline, budget, done={n + 5: seen[0]})


def test_each_image_decoded_once_when_the_budget_holds_the_tracks(scene, monkeypatch):
    """Points of this scene are seen by all 6 images: with a budget of 6 images the run is
    several groups (bounded in matches) that share all images, and the images the read
    stage's check decoded are the walk's: every image is decoded once in the whole run. With a
    budget under a track's image count, its group's walk reloads images (counted)."""
    monkeypatch.setattr(track_groups, "MIN_MATCHES_PER_REFINE_WORKER", 20)
    monkeypatch.setattr(track_groups, "MIN_MATCHES_TO_START_WORKERS", 0)
    _, kps, pairs, _, _ = scene
    for n_images in (6, 2):
        budget = n_images * _image_bytes(scene)
        loader = _loader(scene, max_cached=None, max_cached_bytes=budget)
        assert loader.check_all() == []
        with open_runner(1) as inline:
            _, stats, _ = track_groups.walk_groups(loader, kps, pairs, None, NCC, TRACKS,
                                                  runner=inline, image_budget_bytes=budget)
        assert stats["groups"] > 1 and stats["image_decodes"] == loader.decodes - len(kps)
        if n_images == 6:
            assert stats["image_decodes"] == 0 and loader.decodes == len(kps)
        else:
            assert stats["image_decodes"] > len(kps)


def test_max_images_for_the_budget_and_the_loader(scene):
    one = _image_bytes(scene)
    ids = list(scene[4])
    assert track_groups.max_images_for(_loader(scene, max_cached=None), ids, 5 * one + 7, 8) == 5
    assert track_groups.max_images_for(_loader(scene, max_cached=3), ids, 5 * one, 8) == 3
    assert track_groups.max_images_for(_loader(scene, max_cached=None), ids, one, 8) == 2
    assert track_groups.max_images_for(_loader(scene, max_cached=None), ids, None, 8) == 8
    assert track_groups.max_images_for(_loader(scene, max_cached=None, max_cached_bytes=4 * one), ids,
                                 None, 8) == 4
