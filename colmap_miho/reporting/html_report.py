"""``report.html``: one self-contained page (plotly, its JavaScript embedded, opens offline) to read
a comparison or one model; without plotly the writers log one line and return None."""

from __future__ import annotations

import html
import logging
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from ..adapters.staged_write import write_text_atomic
from .model_view import COLORS, POINT_BUDGET, SIDE_LABEL, model_figure, moved_keypoints
from .tables import ComparedRow, Verdict, comparison_groups, verdict_summary

__all__ = ["write_comparison_html", "write_model_html"]

log = logging.getLogger(__name__)

_CSS = """
body{font-family:system-ui,-apple-system,Segoe UI,Roboto,sans-serif;margin:0 auto;max-width:1200px;
padding:0 16px 40px;color:#222}
h1{font-size:1.5em;margin:18px 0 4px}h2{font-size:1.15em;margin:28px 0 6px;border-bottom:1px solid #ddd}
p.note{color:#555;font-size:.92em;margin:4px 0}
table.metrics{border-collapse:collapse;font-size:.92em}
table.metrics th,table.metrics td{padding:3px 12px;border-bottom:1px solid #eee}
table.metrics td.num{text-align:right;font-variant-numeric:tabular-nums}
table.metrics th{text-align:left;background:#f5f5f5}
table.metrics tr.group th{background:#e8eef6;padding-top:8px}
table.metrics td.change{color:#666}
table.metrics td.change.better{color:#146c2e;font-weight:600}
table.metrics td.change.worse{color:#b3261e;font-weight:600}
p.verdict{font-weight:600;margin:6px 0}
"""

_PLOT_CONFIG = {"displaylogo": False, "responsive": True}


def _plotly():
    from ..extras import MissingExtraError, require

    try:
        require("plotly", "plots", "report.html")
        import plotly.graph_objects as go
    except MissingExtraError as exc:
        log.warning("%s; the page is skipped", exc)
        return None
    return go


# --------------------------------------------------------------------------- charts
_CURVE_METRICS = (("model poses (all GT pairs)", "model", "model_pose_auc"),
                  ("two-view E", "E", "two_view_pose_auc_E"),
                  ("two-view F (+MAGSAC)", "F", "two_view_pose_auc_F"))


def _pose_curves_figure(go, reports: dict[str, dict], max_deg: float = 20.0):
    """Cumulative pose-error curves, one panel per metric; None when no report has per-pair errors."""
    from plotly.subplots import make_subplots

    panels = []
    for title, key, sec in _CURVE_METRICS:
        series = {}
        for tag, rep in reports.items():
            errs = [p.get(key) for p in rep.get("pairs", []) if key in p]
            if errs:
                series[tag] = (np.array([np.inf if e is None else e for e in errs], dtype=np.float64), rep.get(sec))
        if series:
            panels.append((title, series))
    if not panels:
        return None
    fig = make_subplots(rows=1, cols=len(panels), subplot_titles=[t for t, _ in panels], horizontal_spacing=0.06)
    for col, (_, series) in enumerate(panels, start=1):
        finite = np.concatenate([e[np.isfinite(e)] for e, _ in series.values()])
        # zoom in when every error is small: the curve's shape is the information
        hi = max_deg if finite.size == 0 else float(min(max_deg, max(1.0, np.ceil(1.5 * np.quantile(finite, 0.95)))))
        xs = np.linspace(0.0, hi, 401)
        for tag, (e, auc) in series.items():
            recall = (e[None, :] <= xs[:, None]).mean(axis=1)
            aucs = "" if not auc else "<br>AUC@5/10/20 " + "/".join(
                "-" if auc.get(k) is None else f"{100 * auc[k]:.1f}" for k in ("auc5", "auc10", "auc20"))
            name = SIDE_LABEL.get(tag, tag)
            fig.add_trace(go.Scatter(x=xs.astype(np.float32), y=recall.astype(np.float32), mode="lines",
                                     name=name, legendgroup=tag, showlegend=col == 1,
                                     line={"color": COLORS.get(tag), "width": 2},
                                     hovertemplate=f"{name}: %{{y:.1%}} of pairs within %{{x:.2f}} deg"
                                                   f"{aucs}<extra></extra>"),
                          row=1, col=col)
        fig.update_xaxes(title_text="pose error (deg)", range=[0, hi], row=1, col=col)
        fig.update_yaxes(range=[0, 1.02], row=1, col=col, tickformat=".0%")
    fig.update_yaxes(title_text="pairs with error <= x", row=1, col=1)
    fig.update_layout(height=380, margin={"l": 60, "r": 20, "t": 40, "b": 50},
                      legend={"orientation": "h", "y": -0.2})
    return fig


def plotly_text(text: str) -> str:
    """``text`` escaped for plotly, which renders a subset of HTML in labels and hovers."""
    return html.escape(str(text), quote=False)


def _matches_figure(go, before: dict, after: dict, checked: dict | None = None):
    """Verified matches per pair, baseline vs refined (and the match check's removals, when ``checked``)."""
    labels = sorted(before, key=lambda k: (-before[k], k))
    b = np.array([before[k] for k in labels], dtype=np.float64)
    a = np.array([after.get(k, 0) for k in labels], dtype=np.float64)
    c = np.array([(checked or {}).get(k, 0) for k in labels], dtype=np.float64)
    kept = np.where(b > 0, 100 * a / np.maximum(b, 1), 0.0)
    by_filter = np.maximum(b - a - c, 0)
    from .pair_labels import pair_names
    from .plots import short_labels

    names = [plotly_text(" - ".join(pair_names(k))) for k in labels]
    short = [plotly_text(label) for label in short_labels(labels)]
    x = short if len(set(short)) == len(labels) else names
    fig = go.Figure()
    fig.add_trace(go.Bar(x=x, y=b, name=f"baseline ({int(b.sum())})", marker_color=COLORS["baseline"],
                         customdata=names, hovertemplate="%{customdata}<br>baseline %{y:d}<extra></extra>"))
    fig.add_trace(go.Bar(x=x, y=a, name=f"colmap-miho ({int(a.sum())})", marker_color=COLORS["refined"],
                         customdata=np.c_[np.array(names, dtype=object), np.round(kept, 1), by_filter, c],
                         hovertemplate="%{customdata[0]}<br>colmap-miho %{y:d} (%{customdata[1]}% kept)<br>"
                                       "removed by the filter %{customdata[2]:d}, by the match check "
                                       "%{customdata[3]:d}<extra></extra>"))
    if checked:
        fig.add_trace(go.Bar(x=x, y=c, name=f"removed by the match check ({int(c.sum())})",
                             marker_color=COLORS["checked"], customdata=names,
                             hovertemplate="%{customdata}<br>match check removed %{y:d}<extra></extra>"))
    fig.update_layout(barmode="group", height=380, margin={"l": 60, "r": 20, "t": 20, "b": 50},
                      yaxis={"type": "log", "title": "verified matches"},
                      xaxis={"title": "image pair (sorted by baseline matches; hover for names)", "type": "category"},
                      legend={"orientation": "h", "y": 1.08})
    return fig


def _displacement_figure(go, displacements: np.ndarray, per_image: list, size: tuple[int, int] | None):
    """Histogram of displacements (px) and, per image, where the moved keypoints lie."""
    from plotly.subplots import make_subplots

    d = np.asarray(displacements, dtype=np.float64).reshape(-1)
    cols = 2 if per_image else 1
    titles = [f"{d.size} keypoints moved"] + (["where they moved (image coordinates, px)"] if per_image else [])
    fig = make_subplots(rows=1, cols=cols, subplot_titles=titles, horizontal_spacing=0.1)
    hi = max(float(np.quantile(d, 0.99)), 1e-3) if d.size else 1.0
    fig.add_trace(go.Histogram(x=np.clip(d, 0, hi).astype(np.float32), nbinsx=40, marker_color=COLORS["refined"],
                               name="keypoints", showlegend=False,
                               hovertemplate="%{x} px: %{y} keypoints<extra></extra>"), row=1, col=1)
    fig.update_xaxes(title_text=f"displacement (px, clipped at {hi:.2f})", row=1, col=1)
    fig.update_yaxes(title_text="keypoints", row=1, col=1)
    buttons = []
    for k, (raw_name, p0, dd) in enumerate(per_image):
        name = plotly_text(raw_name)
        mag = np.linalg.norm(dd, axis=1)
        fig.add_trace(go.Scattergl(
            x=p0[:, 0].astype(np.float32), y=p0[:, 1].astype(np.float32), mode="markers", name=name,
            visible=k == 0, showlegend=False,
            marker={"size": 5, "color": mag.astype(np.float32), "colorscale": "Viridis", "cmin": 0, "cmax": hi,
                    "colorbar": {"title": {"text": "px"}, "x": 1.02}},
            customdata=np.c_[dd, mag].astype(np.float32),
            hovertemplate="(%{x:.1f}, %{y:.1f}) moved %{customdata[2]:.3f} px<br>"
                          "dx %{customdata[0]:.3f}, dy %{customdata[1]:.3f}<extra></extra>"), row=1, col=2)
        vis = [True] + [j == k for j in range(len(per_image))]
        buttons.append({"label": f"{name} ({len(p0)})", "method": "restyle", "args": [{"visible": vis}]})
    if per_image:
        if size is not None:
            fig.update_xaxes(range=[0, size[0]], row=1, col=2)
            fig.update_yaxes(range=[size[1], 0], row=1, col=2)
        else:
            fig.update_yaxes(autorange="reversed", row=1, col=2)
        fig.update_yaxes(scaleanchor="x2", row=1, col=2)
        fig.update_layout(updatemenus=[{"buttons": buttons, "direction": "down", "x": 1.0, "xanchor": "right",
                                        "y": 1.18, "showactive": True}])
    fig.update_layout(height=440, margin={"l": 60, "r": 20, "t": 70, "b": 50})
    return fig


# --------------------------------------------------------------------------- page
def _table_html(groups: Sequence[tuple[str, Sequence[tuple[str, ...]]]], header: tuple[str, ...],
                last_cell_classes: Sequence[str] = ()) -> str:
    """The metrics table, one ``<tbody>`` per group; ``last_cell_classes`` style each row's change cell."""
    head = "".join(f"<th>{html.escape(h)}</th>" for h in header)
    extra = iter(last_cell_classes)
    bodies = []
    for group, rows in groups:
        body = [f'<tr class="group"><th colspan="{len(header)}" scope="colgroup">{html.escape(group)}</th></tr>']
        for row in rows:
            classes = ["num"] * (len(row) - 1)
            if last_cell_classes:
                classes[-1] += " " + next(extra)
            cells = [f"<td>{html.escape(row[0])}</td>"]
            cells += [f'<td class="{cls}">{html.escape(c)}</td>' for cls, c in zip(classes, row[1:], strict=True)]
            body.append("<tr>" + "".join(cells) + "</tr>")
        bodies.append(f'<tbody data-group="{html.escape(group)}">{"".join(body)}</tbody>')
    return f'<table class="metrics" id="metrics"><thead><tr>{head}</tr></thead>{"".join(bodies)}</table>'


def _change_cell(row: ComparedRow) -> tuple[str, str]:
    """The change column's text and class: the change and its verdict ("same" alone)."""
    if row.verdict is Verdict.SAME:
        return "same", "change"
    text = f"{row.change} {row.verdict}" if row.verdict is not Verdict.NONE else row.change
    return text, f"change {row.verdict}" if row.verdict in (Verdict.BETTER, Verdict.WORSE) else "change"


def _figure_html(fig, div_id: str) -> str:
    return fig.to_html(full_html=False, include_plotlyjs=False, div_id=div_id, config=_PLOT_CONFIG)


def _page(title: str, sections: list[str]) -> str:
    from plotly.offline import get_plotlyjs

    return ("<!DOCTYPE html>\n<html lang=\"en\"><head><meta charset=\"utf-8\">"
            f"<title>{html.escape(title)}</title><style>{_CSS}</style>"
            f"<script type=\"text/javascript\">{get_plotlyjs()}</script></head><body>"
            f"<h1>{html.escape(title)}</h1>{''.join(sections)}</body></html>\n")


def _section(title: str, body: str, note: str = "", section_id: str = "") -> str:
    sid = f' id="{section_id}"' if section_id else ""
    note_html = f'<p class="note">{html.escape(note)}</p>' if note else ""
    return f"<section{sid}><h2>{html.escape(title)}</h2>{note_html}{body}</section>"


def _load_model(path):
    from .gt_model import load_reconstruction

    if path is None:
        return None
    if not isinstance(path, (str, Path)):
        return path
    try:
        return load_reconstruction(path)
    except (FileNotFoundError, ValueError) as exc:
        log.info("3D view: model %s skipped (%s)", path, exc)
        return None


def _image_size(models: dict) -> tuple[int, int] | None:
    for rec in models.values():
        for cam in rec.cameras.values():
            return int(cam.width), int(cam.height)
    return None


def write_comparison_html(path: str | Path, baseline: dict, refined: dict, refine: dict, changes: dict, *,
                          models: dict | None = None, budget: int = POINT_BUDGET,
                          title: str = "colmap-miho comparison") -> Path | None:
    """Write the comparison page; returns the path, or None without plotly.

    ``changes``: :func:`colmap_miho.reporting.compare.match_changes`'s dict. ``models``: both sides'
    model folders or reconstructions (default ``baseline/model``, ``refined/model`` beside
    ``path``); a missing one is left out of the 3D view. ``budget``: most points drawn per model."""
    go = _plotly()
    if go is None:
        return None
    path = Path(path)
    if models is None:
        models = {tag: path.parent / tag / "model" for tag in ("baseline", "refined")}
    recs = {tag: rec for tag, m in models.items() if (rec := _load_model(m)) is not None}
    groups = comparison_groups(baseline, refined)
    cells = [(g, [(r.metric, r.baseline, r.refined, _change_cell(r)[0]) for r in rows]) for g, rows in groups]
    table = _table_html(cells, ("metric", "baseline", "colmap-miho", "change"),
                        [_change_cell(r)[1] for _, rows in groups for r in rows])
    verdict = f'<p class="verdict" id="verdict">{html.escape(verdict_summary(groups))}</p>'
    sections = [_section("Side by side", verdict + table, _summary_note(baseline, refine), "table")]
    curves = _pose_curves_figure(go, {"baseline": baseline, "refined": refined})
    if curves is not None:
        sections.append(_section("Pose error", _figure_html(curves, "pose-curves"),
                                 "Fraction of image pairs whose relative-pose error is at most x degrees "
                                 "(max of rotation and translation-direction errors; higher is better).",
                                 "pose"))
    before, after = changes.get("matches_before", {}), changes.get("matches_after", {})
    if before:
        checked = removed_by_the_check((refine.get("match_check") or {}).get("removed_per_pair"))
        sections.append(_section("Matches per pair", _figure_html(_matches_figure(go, before, after, checked),
                                                                  "matches"),
                                 "Verified matches of each image pair in the two databases (log scale); hover a "
                                 "pair for what the filter and the match check removed.", "pairs"))
    disp = np.asarray(changes.get("displacements", np.zeros(0)))
    sections.append(_section("Keypoint displacement",
                             _figure_html(_displacement_figure(go, disp, moved_keypoints(recs), _image_size(recs)),
                                          "displacement"),
                             "How far refinement moved keypoints, and where in each image (pick an image above "
                             "the right panel; only registered images of both models are offered).", "keypoints"))
    if recs:
        fig, note = model_figure(go, recs, budget=budget)
        sections.append(_section("Sparse models", _figure_html(fig, "models3d"), note, "models"))
    write_text_atomic(path, _page(title, sections))
    return path


def removed_by_the_check(removed_per_pair) -> dict[str, int]:
    """``match_check.removed_per_pair`` keyed like the comparison's pairs (older dicts taken as they are)."""
    from .pair_labels import pair_label

    if isinstance(removed_per_pair, dict):
        return {str(k): int(v) for k, v in removed_per_pair.items()}
    out: dict[str, int] = {}
    for entry in removed_per_pair or ():
        key = pair_label(*entry["images"])
        out[key] = out.get(key, 0) + int(entry["removed"])
    return out


def _summary_note(baseline: dict, refine: dict) -> str:
    parts = []
    runs = baseline.get("repeats", {}).get("num_runs")
    if runs:
        parts.append(f"Mapping figures: median [min-max] of {runs} runs per side.")
    if refine:
        parts.append(f"Recipe {refine.get('recipe', '')}: {refine.get('matches_kept', 0)} of "
                     f"{refine.get('matches_in', 0)} matches kept, {refine.get('keypoints_moved', 0)} keypoints moved.")
        mc = refine.get("match_check") or {}
        if mc:
            parts.append(match_check_note(mc))
    return " ".join(parts)


def match_check_note(mc: dict, *, label: str = "Match check", timing: bool = False, sep: str = " ") -> str:
    """The match check's sentence after ``label``, then one per hinge after ``sep``."""
    verb = "removed" if mc.get("mode") == "remove" else "flagged"
    timed = f" ({mc.get('rounds', 0)} round(s), {mc.get('seconds', 0):.1f} s)" if timing else ""
    if not mc.get("used"):
        text = f"the global estimate of the cameras was not used ({mc.get('reason', '')}); nothing {verb}{timed}."
    else:
        untrusted = ", ".join(mc.get("images_untrusted") or [])
        text = (f"global estimate of {mc.get('images_registered', 0)} of {mc.get('images', 0)} images, "
                f"{len(mc.get('images_trusted') or [])} trusted" + (f" (not: {untrusted})" if untrusted else "")
                + f"; {mc.get('matches_removed', 0)} of {mc.get('matches_judged', 0)} judged matches {verb} "
                f"(farther than {mc.get('threshold_px', 0):.2f} px from their epipolar line under it), "
                f"{mc.get('pairs_removed', 0)} pairs ({mc.get('matches_in_removed_pairs', 0)} matches) {verb} whole "
                f"(most of their matches off it){timed}." + restored_note(mc))
    return f"{label}: {text}" + "".join(sep + hinge_note(h) for h in mc.get("hinges") or [])


def restored_note(mc: dict) -> str:
    """The match check's sentence on the filter's removals it gave back ("" when none)."""
    n = mc.get("matches_restored", 0)
    if not n:
        return ""
    revived = mc.get("pairs_revived", 0)
    return (f" {n} matches the filter removed restored in {mc.get('pairs_restored', 0)} pairs"
            + (f" ({revived} of them emptied by the filter)" if revived else "")
            + ": on their epipolar line under it and confirmed by a third image.")


def hinge_note(h: dict) -> str:
    """One sentence on a hinge the match check found: its two groups, the verdict and the action."""
    a, b = h.get("images_a") or [], h.get("images_b") or []
    small, large = (a, b) if len(a) <= len(b) else (b, a)
    shown = ", ".join(small[:6]) + (f" and {len(small) - 6} more" if len(small) > 6 else "")
    ne, nm = len(h.get("estimate_pairs") or []), len(h.get("mode_pairs") or [])
    evidence = (f"coverage of the pairs across it: {h.get('estimate_coverage', 0):.2f} for the estimate's "
                f"{ne}, {h.get('mode_coverage', 0):.2f} for the other hypothesis' {nm}")
    side = {"estimate": "sided with the estimate", "mode": "sided with the other hypothesis",
            "undecided": "did not decide"}.get(h.get("verdict", ""), "did not decide")
    done = {"kept": "the estimate was kept",
            "estimated again": f"the estimate was made again without the estimate's {ne} cross pairs",
            "judged less": f"the {h.get('pairs_unjudged', 0)} pairs ({h.get('matches_unjudged', 0)} matches) "
                           f"between the groups were left unjudged"}.get(h.get("action", ""), "")
    return (f"Hinge in round {h.get('round', 1)}'s estimate: {len(small)} images ({shown}) turned "
            f"{h.get('angle_deg', 0):.1f} deg against the other {len(large)}; the evidence ({evidence}) {side}, "
            f"so {done}.")


def write_model_html(path: str | Path, report: dict, model, *, budget: int = POINT_BUDGET,
                     title: str = "colmap-miho report") -> Path | None:
    """Write the page of one model (table, curves with GT, 3D view); returns the path, or None without plotly."""
    go = _plotly()
    if go is None:
        return None
    path = Path(path)
    groups = [(g, [(r.metric, r.baseline) for r in rows]) for g, rows in comparison_groups(report, {})]
    sections = [_section("Report", _table_html(groups, ("metric", "value")), "", "table")]
    curves = _pose_curves_figure(go, {"model": report})
    if curves is not None:
        sections.append(_section("Pose error", _figure_html(curves, "pose-curves"),
                                 "Fraction of image pairs whose relative-pose error is at most x degrees.", "pose"))
    rec = _load_model(model)
    if rec is not None:
        fig, note = model_figure(go, {"model": rec}, budget=budget)
        sections.append(_section("Sparse model", _figure_html(fig, "models3d"), note, "models"))
    write_text_atomic(path, _page(title, sections))
    return path
