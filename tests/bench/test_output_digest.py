"""``output_digest.py --databases``: identical outputs hash the same, one changed match differs."""

from __future__ import annotations

import shutil

import numpy as np
from output_digest import main

from colmap_miho.adapters.database import ColmapDatabase
from miho_bench.synthetic import make_synthetic_scene


def test_databases_compare_their_written_tables(tmp_path, capsys):
    sc = make_synthetic_scene(tmp_path / "s", num_images=3, num_points=40, render_images=False)
    a, b = tmp_path / "a.db", tmp_path / "b.db"
    shutil.copy(sc.database, a)
    shutil.copy(sc.database, b)
    assert main(["--databases", str(a), str(b)]) == 0
    assert capsys.readouterr().out.strip().endswith("identical")
    with ColmapDatabase(b) as db:
        m = db.matches(1, 2, "raw")
        db.handle.delete_matches(1, 2)
        db.handle.write_matches(1, 2, np.ascontiguousarray(m[1:]))
    assert main(["--databases", str(a), str(b)]) == 1
    out = capsys.readouterr().out
    assert out.strip().endswith("DIFFER") and out.count("keypoints=") == 2
