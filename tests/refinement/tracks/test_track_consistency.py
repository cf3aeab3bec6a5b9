"""Every match that reaches the output database belongs to the graph the walk sees: pairs
passed through unfiltered (fewer than ``pipeline.min_matches`` matches) join the tracks."""

from __future__ import annotations

import numpy as np

from colmap_miho.adapters.database import ColmapDatabase
from colmap_miho.pipeline.refine_job import refine_database
from colmap_miho.recipe import load_recipe
from miho_bench.synthetic import make_synthetic_scene


def _output_tracks(db_path):
    """(tracks with >= 2 keypoints over all verified matches of the output, matches)."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    with ColmapDatabase(db_path) as db:
        n = {im.image_id: len(db.keypoints(im.image_id)) for im in db.images()}
        offset = dict(zip(sorted(n), np.cumsum([0] + [n[i] for i in sorted(n)])[:-1], strict=True))
        ea, eb = [], []
        for p in db.pairs("verified"):
            m = db.matches(p.image_id1, p.image_id2, "verified").astype(np.int64)
            ea.append(offset[p.image_id1] + m[:, 0])
            eb.append(offset[p.image_id2] + m[:, 1])
    ea, eb = np.concatenate(ea), np.concatenate(eb)
    total = sum(n.values())
    _, comp = connected_components(coo_matrix((np.ones(ea.size), (ea, eb)), shape=(total, total)),
                                   directed=False)
    return np.unique(comp[np.concatenate([ea, eb])]).size, ea.size


def test_unfiltered_pairs_join_the_walked_tracks(tmp_path):
    scene = make_synthetic_scene(tmp_path / "scene", num_images=4, num_points=80,
                                 outlier_ratio=0.0, noise_px=1.0, seed=3)
    small = 30  # matches left on two pairs, below the threshold: they pass through unfiltered
    with ColmapDatabase(scene.database) as db:
        pairs = db.pairs("verified")
        for p in pairs[:2]:
            m = db.matches(p.image_id1, p.image_id2, "verified")[:small]
            db.write_pair(p.image_id1, p.image_id2, m, db.keypoints(p.image_id1)[m[:, 0]],
                          db.keypoints(p.image_id2)[m[:, 1]])
    rec = load_recipe(None, [f"pipeline.min_matches={small + 1}"])
    s = refine_database(scene.database, scene.image_dir, tmp_path / "out.db", recipe=rec,
                        workers=1)
    assert s.pairs_passed == 2 and s.pairs_filtered == len(pairs) - 2
    assert s.keypoints_moved > 0
    n_tracks, _ = _output_tracks(s.output)
    # the walk's tracks are exactly the output's tracks
    assert s.refine_stats["tracks"] == n_tracks
    with ColmapDatabase(s.output) as db:  # the match check judges those pairs too: what is left of them
        passed = sum(len(db.matches(p.image_id1, p.image_id2, "verified")) for p in pairs[:2])
    assert 2 * small - 2 <= passed <= 2 * small
    # the unfiltered pairs' matches and those the match check restored have no homography
    assert s.refine_stats["unrefinable_matches"] == passed + s.match_check["matches_restored"]
