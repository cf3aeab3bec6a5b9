"""report.html: the page's pieces on synthetic models, and the demo's page in a real browser.

The browser test drives the system's Chromium (Debian's ``chromium`` package) with Playwright
(the ``test`` extra); it skips, saying why, where either is missing or the browser cannot start.
"""

from __future__ import annotations

import html
import io
import json
import logging
import os
import re
import shutil
import sys

import numpy as np
import pytest

from colmap_miho.cli import main
from colmap_miho.reporting import html_report as hr
from colmap_miho.reporting import model_view as mv
from colmap_miho.reporting.tables import Verdict, comparison_groups, comparison_rows, verdict_summary

pytest.importorskip("plotly")

# float32 storage of the drawn coordinates: ~1e-7 relative; the synthetic scenes span ~10 units
COORD_TOL = 1e-4
# a blank (or failed) WebGL canvas is one flat colour; points, frusta and shading give hundreds
MIN_DISTINCT_COLOURS = 20


def _scene(num_points=300, num_frames=5, seed=0):
    import pycolmap

    opts = pycolmap.SyntheticDatasetOptions(num_rigs=1, num_cameras_per_rig=1, num_frames_per_rig=num_frames,
                                            num_points3D=num_points)
    return pycolmap.synthesize_dataset(opts)


def _table(text: str) -> str:
    return re.search(r'<table class="metrics" id="metrics">(.*?)</table>', text, re.S).group(1)


def _page_rows(text: str) -> list[list[str]]:
    """The metric rows of the page's table (group headings left out), cell texts."""
    rows = re.findall(r"<tr>(.*?)</tr>", _table(text).split("</thead>", 1)[1])
    return [[html.unescape(c) for c in re.findall(r"<td[^>]*>(.*?)</td>", row)] for row in rows]


def _page_groups(text: str) -> list[str]:
    return re.findall(r'<tr class="group"><th[^>]*>(.*?)</th></tr>', _table(text))


# --------------------------------------------------------------------------- pieces
def test_decimate_keeps_all_or_a_seeded_sorted_subset():
    assert np.array_equal(mv.decimate(5, 10), np.arange(5))
    idx = mv.decimate(1000, 100, seed=3)
    assert len(idx) == 100 and len(np.unique(idx)) == 100 and np.all(np.diff(idx) > 0) and idx.max() < 1000
    assert np.array_equal(idx, mv.decimate(1000, 100, seed=3))
    assert not np.array_equal(idx, mv.decimate(1000, 100, seed=4))
    with pytest.raises(ValueError, match="budget"):
        mv.decimate(10, 0)


def test_frusta_start_at_the_camera_and_reach_the_image_corners():
    rec = _scene()
    size = 0.5
    lines = mv.camera_frusta(rec, size)
    chunks = np.split(lines, np.where(np.isnan(lines[:, 0]))[0])
    chunks = [c[~np.isnan(c[:, 0])] for c in chunks if np.isfinite(c).any()]
    images = sorted((im for im in rec.images.values() if im.has_pose), key=lambda im: im.name)
    assert len(chunks) == len(images) == 5
    for path, im in zip(chunks, images, strict=True):
        cam = rec.cameras[im.camera_id]
        centre = np.asarray(im.projection_center())
        assert np.allclose(path[0], centre, atol=1e-9)
        corners = path[[1, 2, 4, 5]]
        assert np.allclose(np.linalg.norm(corners - centre, axis=1), size, rtol=1e-9)
        pose = im.cam_from_world()
        in_cam = corners @ np.asarray(pose.rotation.matrix()).T + np.asarray(pose.translation)
        px = np.asarray(cam.img_from_cam(in_cam))
        w, h = cam.width, cam.height
        assert np.allclose(px, [[0, 0], [w, 0], [w, h], [0, h]], atol=1e-6)


def test_refined_model_is_drawn_in_the_baseline_frame():
    import pycolmap

    base = _scene()
    moved = pycolmap.Reconstruction(base)
    q = np.array([0.1, 0.2, 0.3, 0.9])
    moved.transform(pycolmap.Sim3d(2.5, pycolmap.Rotation3d(q / np.linalg.norm(q)), np.array([1.0, -2.0, 3.0])))
    s, R, t = mv.alignment(moved, base)
    got = s * mv.model_points(moved) @ R.T + t
    assert np.allclose(got, mv.model_points(base), atol=COORD_TOL)
    # fewer than three shared images: no alignment, each model in its own frame
    assert mv.alignment(moved, pycolmap.Reconstruction()) is None


def _reports(rec):
    from colmap_miho.reporting.report import build_report

    rep = build_report(reconstruction=rec)
    rep["pairs"] = [{"name1": "a", "name2": "b", "model": 0.4}, {"name1": "a", "name2": "c", "model": None}]
    rep["model_pose_auc"] = {"auc5": 0.5, "auc10": 0.5, "auc20": 0.5}
    return rep


def test_comparison_page_is_self_contained_with_the_table_and_the_budget(tmp_path):
    base, ref = _scene(num_points=400), _scene(num_points=400)
    baseline, refined = _reports(base), _reports(ref)
    refined["reconstruction"]["num_points3D"] = 399  # a difference the table must show
    changes = {"matches_before": {"a|b": 100, "a|c": 50}, "matches_after": {"a|b": 90},
               "displacements": np.array([0.1, 0.2, 0.5])}
    path = hr.write_comparison_html(tmp_path / "report.html", baseline, refined, {"recipe": "r"}, changes,
                                    models={"baseline": base, "refined": ref}, budget=100)
    text = path.read_text()
    assert [r[:3] for r in _page_rows(text)] == [list(r) for r in comparison_rows(baseline, refined)]
    assert ["3D points", "400", "399", "-1 (-0.2%)"] in _page_rows(text)  # a count: no verdict
    assert ["registered images", "5", "5", "same"] in _page_rows(text)
    assert _page_groups(text) == ["reconstruction", "model pose"]
    summary = html.escape(verdict_summary(comparison_groups(baseline, refined)))
    assert f'<p class="verdict" id="verdict">{summary}</p>' in text
    assert not re.search(r"<script[^>]+src=", text)  # nothing fetched: the bundle is inline
    assert text.count("Plotly.newPlot") == 4  # pose curves, matches, displacement, 3D
    assert "baseline points (100 of 400)" in text and "colmap-miho points (100 of 400)" in text


def _side(median_px, auc5, points, reg=(10, 10, 10), wrong=None):
    rep = {"reconstruction": {"num_reg_images": reg[0], "num_points3D": points},
           "model_pose_auc": {"auc5": auc5, "auc10": 0.9, "auc20": 0.95},
           "keypoint_accuracy": {"residual_median_px": median_px, "num_measured_tracks": 500}}
    if wrong is not None:
        rep["keypoint_accuracy"]["wrong_track_share"] = wrong
    if reg[1:] != (reg[0], reg[0]):
        rep["repeats"] = {"num_runs": 3, "seeds": [0, 1, 2], "median": {"reconstruction": {"num_reg_images": reg[0]}},
                          "min": {"reconstruction": {"num_reg_images": reg[1]}},
                          "max": {"reconstruction": {"num_reg_images": reg[2]}}}
    return rep


def test_change_column_knows_which_way_each_metric_improves():
    """Lower is better for residuals, higher for AUCs; counts get a change but no verdict;
    equal printed values are the same; overlapping [min-max] ranges of repeated runs are
    within the spread; a value missing on one side has no change."""
    baseline = _side(0.200, 0.80, 1000, reg=(10, 9, 10))
    refined = _side(0.120, 0.75, 990, reg=(11, 10, 11), wrong=0.01)
    groups = comparison_groups(baseline, refined)
    assert [g for g, _ in groups] == ["reconstruction", "model pose", "keypoints against GT"]
    rows = {r.metric: r for _, group in groups for r in group}
    assert (rows["GT track residual median (px)"].verdict, rows["GT track residual median (px)"].change) == (
        Verdict.BETTER, "-0.080 (-40%)")
    assert (rows["model pose AUC@5 (%)"].verdict, rows["model pose AUC@5 (%)"].change) == (Verdict.WORSE, "-5.0 pts")
    assert rows["model pose AUC@10 (%)"].verdict is Verdict.SAME
    assert (rows["3D points"].verdict, rows["3D points"].change) == (Verdict.NONE, "-10 (-1.0%)")
    assert rows["registered images"].verdict is Verdict.SPREAD  # 9-10 against 10-11
    assert rows["GT tracks measured"].verdict is Verdict.SAME
    assert (rows["wrong tracks > 4 px (%)"].change, rows["wrong tracks > 4 px (%)"].verdict) == ("-", Verdict.NONE)
    # ranges apart: a verdict
    apart = comparison_groups(_side(0.2, 0.8, 1000, reg=(8, 7, 8)), _side(0.2, 0.8, 1000, reg=(10, 10, 11)))
    assert apart[0][1][0].verdict is Verdict.BETTER
    # the same metric read the other way round
    back = {r.metric: r.verdict for _, g in comparison_groups(refined, baseline) for r in g}
    assert back["GT track residual median (px)"] is Verdict.WORSE and back["model pose AUC@5 (%)"] is Verdict.BETTER


def test_comparison_page_groups_rows_and_marks_better_and_worse(tmp_path):
    baseline, refined = _side(0.200, 0.80, 1000), _side(0.120, 0.75, 990)
    path = hr.write_comparison_html(tmp_path / "report.html", baseline, refined, {}, {}, models={})
    text = path.read_text()
    assert _page_groups(text) == ["reconstruction", "model pose", "keypoints against GT"]
    rows = {r[0]: r for r in _page_rows(text)}
    assert rows["GT track residual median (px)"][3] == "-0.080 (-40%) better"
    assert rows["model pose AUC@5 (%)"][3] == "-5.0 pts worse"
    assert re.search(r'<td class="num change better">-0.080 \(-40%\) better</td>', text)
    assert re.search(r'<td class="num change worse">-5.0 pts worse</td>', text)
    assert "better in 1 row, worse in 1 (model pose AUC@5 (%)), the same in 4." in text


def test_model_page_from_the_cli(tmp_path):
    rec = _scene()
    model = tmp_path / "model"
    model.mkdir()
    rec.write(str(model))
    page = tmp_path / "out" / "one.html"
    assert main(["report", "--model", str(model), "--html", str(page), "-q"]) == 0
    text = page.read_text()
    rows = dict((r[0], r[1]) for r in _page_rows(text))
    assert rows["registered images"] == "5" and rows["3D points"] == str(rec.num_points3D())
    assert "model cameras (5)" in text


def test_without_plotly_the_page_is_skipped_with_one_line(tmp_path, monkeypatch):
    monkeypatch.setitem(sys.modules, "plotly", None)
    monkeypatch.setitem(sys.modules, "plotly.graph_objects", None)
    records: list[logging.LogRecord] = []
    handler = logging.Handler(logging.WARNING)
    handler.emit = records.append  # type: ignore[method-assign]
    hr.log.addHandler(handler)  # on the module's logger: whatever an earlier CLI run did to its parents
    try:
        assert hr.write_model_html(tmp_path / "x.html", {}, None) is None
    finally:
        hr.log.removeHandler(handler)
    assert not (tmp_path / "x.html").exists()
    lines = [r.getMessage() for r in records]
    assert len(lines) == 1 and "pip install 'colmap-miho[plots]'" in lines[0]


# --------------------------------------------------------------------------- real browser
def _chromium() -> str:
    for name in (os.environ.get("COLMAP_MIHO_CHROMIUM", ""), "chromium", "chromium-browser", "google-chrome"):
        if name and (found := shutil.which(name)):
            return found
    pytest.skip("no Chromium on PATH (Debian: apt-get install chromium)")


@pytest.mark.slow
def test_demo_page_in_headless_chromium(demo_run):
    sync_api = pytest.importorskip("playwright.sync_api", reason="playwright is not installed (test extra)")
    from PIL import Image

    rc, out = demo_run
    assert rc == 0
    page_file = out / "report.html"
    table = json.loads((out / "compare.json").read_text())["rows"]
    expected = [[r["metric"], r["baseline"], r["refined"]] for r in table]
    executable = _chromium()
    problems: list[str] = []
    with sync_api.sync_playwright() as pw:
        try:
            # software WebGL (SwiftShader): the 3D view needs it on a machine without a GPU
            browser = pw.chromium.launch(executable_path=executable, args=[
                "--no-sandbox", "--use-angle=swiftshader", "--enable-unsafe-swiftshader"])
        except Exception as exc:  # noqa: BLE001 - any launch failure is a reason to skip
            pytest.skip(f"Chromium at {executable} did not start: {' '.join(str(exc).split())[:200]}")
        try:
            page = browser.new_page(viewport={"width": 1280, "height": 900})
            page.on("console", lambda m: problems.append(m.text) if m.type == "error" else None)
            page.on("pageerror", lambda e: problems.append(str(e)))
            page.goto(page_file.as_uri())
            page.wait_for_selector("#models3d canvas", timeout=30_000)
            page.wait_for_timeout(1500)  # the WebGL scene draws after the layout
            rows = page.eval_on_selector_all("#metrics tbody tr:not(.group)",
                                             "rows => rows.map(r => Array.from(r.cells, c => c.textContent.trim()))")
            groups = page.eval_on_selector_all("#metrics tr.group th", "cells => cells.map(c => c.textContent)")
            verdicts = page.eval_on_selector_all(
                "#metrics td.change", "cells => cells.map(c => [c.className, getComputedStyle(c).color])")
            shot = page.locator("#models3d canvas").first.screenshot()  # the WebGL canvas alone
            # the model buttons switch the traces: "baseline" leaves the baseline's points and cameras
            page.locator("#models3d .updatemenu-button").nth(1).click()
            page.wait_for_timeout(300)
            visible = page.evaluate("() => document.getElementById('models3d').data.map(t => t.visible)")
        finally:
            browser.close()
    assert problems == []
    assert [r[:3] for r in rows] == expected
    assert groups == ["reconstruction", "model pose", "two-view pose", "keypoints against GT"]
    # the demo's refined side has better keypoints: green "better" cells, coloured apart from the others
    colours = {cls: colour for cls, colour in verdicts}
    assert "num change better" in colours and colours["num change better"] != colours.get("num change")
    assert visible == [True, True, False, False]
    pixels = np.asarray(Image.open(io.BytesIO(shot)).convert("RGB")).reshape(-1, 3)
    colours = np.unique(pixels, axis=0)
    assert len(colours) >= MIN_DISTINCT_COLOURS, f"3D view looks blank: {len(colours)} colours"
    # the refined model's points and cameras (red) are drawn
    red = (pixels[:, 0] > 150) & (pixels[:, 1] < 110) & (pixels[:, 2] < 110)
    assert red.sum() > 200


EVIL = ['<a href="https://example.com">x.png', "<b>bold</b>.png", "<span style='color:red'>s</span>.png",
        "line<br>break.png"]


def test_names_are_text_in_every_label_hover_and_menu():
    """plotly renders a subset of HTML in labels, hovers and menus: an image name is shown as
    text (escaped), never as a link, bold or a line break."""
    import plotly.graph_objects as go

    before = {f"{a}|{b}": 10 for a, b in zip(EVIL, EVIL[1:], strict=False)}
    figs = [hr._matches_figure(go, before, before),
            hr._displacement_figure(go, np.array([0.1, 0.2]), [(name, np.zeros((2, 2)), np.ones((2, 2)))
                                                               for name in EVIL], (100, 100))]
    shown = json.dumps([json.loads(f.to_json()) for f in figs])
    assert "<a href" not in shown and "<b>" not in shown and "<span" not in shown and "line<br>" not in shown
    assert "&lt;a href=\\\"https://example.com\\\"&gt;x.png" in shown
    assert "&lt;b&gt;bold&lt;/b&gt;.png" in shown


def test_comparison_page_shows_evil_names_as_text(tmp_path):
    base = _scene(num_points=50)
    baseline = _reports(base)
    changes = {"matches_before": {f"{EVIL[0]}|{EVIL[1]}": 100}, "matches_after": {f"{EVIL[0]}|{EVIL[1]}": 90},
               "displacements": np.array([0.1])}
    text = hr.write_comparison_html(tmp_path / "report.html", baseline, baseline, {"recipe": "r"}, changes,
                                    models={"baseline": base}, budget=50).read_text()
    assert "&lt;a href=" in text
    assert "\\u003ca href" not in text and '<a href="https://example.com"' not in text


def test_matches_per_pair_split_the_removals_between_the_filter_and_the_match_check():
    go = pytest.importorskip("plotly.graph_objects")
    before, after, checked = {"a|b": 100, "a|c": 50}, {"a|b": 70, "a|c": 50}, {"a|b": 20}
    fig = hr._matches_figure(go, before, after, checked)
    names = [t.name for t in fig.data]
    assert names == ["baseline (150)", "colmap-miho (120)", "removed by the match check (20)"]
    refined = fig.data[1]
    split = {row[0]: (int(row[2]), int(row[3])) for row in refined.customdata}
    assert split == {"a - b": (10, 20), "a - c": (0, 0)}  # 100 - 70 - 20 by the filter
    assert len(hr._matches_figure(go, before, after).data) == 2  # the check off: no third bar
