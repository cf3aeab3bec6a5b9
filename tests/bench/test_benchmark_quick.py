"""The evaluation benchmark's quick (CI) mode runs end to end on real pairs and its numbers
behave as the paper's protocol says they must."""

import json

import numpy as np
import pytest

from miho_bench.benchmark import pipeline_names
from miho_bench.benchmark_run import headline, run_benchmark


@pytest.mark.realdata
@pytest.mark.slow
def test_quick_benchmark_writes_tables_and_filters_help(shared_data, tmp_path):
    results = run_benchmark(shared_data, tmp_path, frontends=("sift",), datasets=("oxford", "temple"),
                            quick=True, progress=False)
    sift = results["sift"]
    assert set(sift) == {"oxford", "temple"}
    assert set(sift["oxford"]) == set(pipeline_names(quick=True))
    for name in ("sift.md", "sift.json", "sift_errors.png"):
        assert (tmp_path / name).is_file()
    data = json.loads((tmp_path / "sift.json").read_text())
    assert "auc_H" in data["results"]["oxford"]["mop_miho"]
    assert {"auc_F", "auc_F_magsac", "auc_E"} <= set(data["results"]["temple"]["mop_miho"])
    ox = sift["oxford"]
    # The unfiltered input has outliers (graf, boat, bikes, leuven 1-2: precision 85%); every
    # filter must raise precision while keeping most inliers.
    assert ox["none"]["filtered"] == 0 and ox["none"]["recall"] == pytest.approx(1.0)
    for name in ("magsac", "mop", "mop_miho", "adalam", "colmap"):
        assert ox[name]["precision"] > ox["none"]["precision"] + 0.05, name
        assert ox[name]["recall"] > 0.7, name
    # MOP+MiHo keeps nearly all inliers (loose 15 px planes), unlike MAGSAC at 0.75 px
    assert ox["mop_miho"]["recall"] >= ox["magsac"]["recall"]
    # the homography AUC after MOP+MiHo is far above the unfiltered input's
    mean = lambda d: np.mean(list(d.values()))  # noqa: E731
    assert mean(ox["mop_miho"]["auc_H"]) > mean(ox["none"]["auc_H"]) + 0.3
    assert "| none |" in headline(results)
