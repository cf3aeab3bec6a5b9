"""PNG figures for ``compare`` (matplotlib, Agg backend): pose-error curves, keypoint displacements,
matches kept. Plain arrays in, one PNG path out per function."""

from __future__ import annotations

import contextlib
import functools
from pathlib import Path

import numpy as np

COLORS = {"baseline": "#7f7f7f", "refined": "#d62728"}


def _pyplot():
    from ..extras import require

    matplotlib = require("matplotlib", "plots", "plotting")
    matplotlib.use("Agg", force=False)
    import matplotlib.pyplot as plt

    return plt


@contextlib.contextmanager
def plain_text():
    """Every text made inside is plain (an image name with two ``$`` would be parsed as TeX and raise)."""
    from ..extras import require

    matplotlib = require("matplotlib", "plots", "plotting")
    with matplotlib.rc_context({"text.parse_math": False, "text.usetex": False}):
        yield


def plain_text_figure(func):
    """Decorator: ``func`` draws its figure under :func:`plain_text`."""

    @functools.wraps(func)
    def wrapper(*args, **kwargs):
        with plain_text():
            return func(*args, **kwargs)

    return wrapper


def _save(fig, path: Path) -> None:
    from ..adapters.staged_write import staged_write

    with staged_write(path) as tmp:
        fig.savefig(tmp, dpi=110, format="png")


@plain_text_figure
def plot_pose_error_curves(
    curves: dict[str, dict[str, list[float]]], path: str | Path, *, max_deg: float = 20.0, title: str = ""
) -> Path:
    """Cumulative pose-error curves, one panel per metric of ``curves`` ``{metric: {label:
    errors}}`` (degrees; ``inf``/None = failure); a panel of small errors zooms in below
    ``max_deg``."""
    plt = _pyplot()
    metrics = [m for m in curves if curves[m]]
    fig, axes = plt.subplots(1, max(1, len(metrics)), figsize=(4.2 * max(1, len(metrics)), 3.6), squeeze=False)
    # strict=False: with no metric there is still one (empty) panel, so axes can outnumber metrics
    for ax, metric in zip(axes[0], metrics, strict=False):
        finite = np.array([v for errs in curves[metric].values() for v in errs if v is not None and np.isfinite(v)])
        # zoom in when every error is small: the curve's shape is the information
        hi = max_deg if finite.size == 0 else float(min(max_deg, max(1.0, np.ceil(1.5 * np.quantile(finite, 0.95)))))
        xs = np.linspace(0.0, hi, 401)
        for label, errs in curves[metric].items():
            e = np.array([np.inf if v is None else v for v in errs], dtype=np.float64)
            if e.size == 0:
                continue
            recall = (e[None, :] <= xs[:, None]).mean(axis=1)
            key = label.split()[0] if label else label
            ax.plot(xs, recall, color=COLORS.get(key), lw=2, label=label)
        for t in (5, 10, 20):
            if t <= hi:
                ax.axvline(t, color="#cccccc", lw=0.8, zorder=0)
        ax.set_xlim(0, hi)
        ax.set_ylim(0, 1.02)
        ax.set_xlabel("pose error (deg)")
        ax.set_ylabel("fraction of pairs")
        ax.set_title(metric)
        ax.grid(alpha=0.3)
        ax.legend(loc="lower right", fontsize=8)
    if title:
        fig.suptitle(title)
    fig.tight_layout()
    path = Path(path)
    _save(fig, path)
    plt.close(fig)
    return path


@plain_text_figure
def plot_displacement_histogram(displacements: np.ndarray, path: str | Path, *, max_px: float | None = None,
                                title: str = "") -> Path:
    """Histogram of the moved keypoints' displacements in pixels (empty input says so)."""
    plt = _pyplot()
    d = np.asarray(displacements, dtype=np.float64).reshape(-1)
    fig, ax = plt.subplots(figsize=(5.5, 3.6))
    if d.size:
        hi = max_px if max_px else max(float(np.quantile(d, 0.99)), 1e-3)
        ax.hist(np.clip(d, 0, hi), bins=40, range=(0, hi), color=COLORS["refined"], alpha=0.85)
        ax.axvline(np.median(d), color="k", ls="--", lw=1, label=f"median {np.median(d):.2f} px")
        ax.legend()
        ax.set_xlabel(f"keypoint displacement (px, clipped at {hi:.2f})")
    else:
        ax.text(0.5, 0.5, "no keypoint moved", ha="center", va="center", transform=ax.transAxes)
        ax.set_xlabel("keypoint displacement (px)")
    ax.set_ylabel("keypoints")
    ax.set_title(title or f"{d.size} keypoints moved")
    fig.tight_layout()
    path = Path(path)
    _save(fig, path)
    plt.close(fig)
    return path


#: The most characters of one image name in a tick label: longer names keep their start and
#: end around an ellipsis, so that a pair label fits under the plot (a long name made
#: matplotlib's tight layout give up, with a warning to the user).
MAX_NAME_CHARS = 24


def _shorten(name: str, limit: int = MAX_NAME_CHARS) -> str:
    """``name`` escaped and cut to ``limit`` characters around an ellipsis (keeping the end)."""
    from ..terminal import printable

    name = printable(name)
    if len(name) <= limit:
        return name
    head = (limit - 1) // 3
    return name[:head] + "\u2026" + name[len(name) - (limit - 1 - head):]


def short_labels(labels: list[str]) -> list[str]:
    """'a.png|b.png' labels without the names' common prefix and extension, each name shortened."""
    import os

    from .pair_labels import pair_names

    names = [n for lab in labels for n in pair_names(lab)]
    prefix = os.path.commonprefix(names) if len(names) > 1 else ""
    return ["-".join(_shorten(os.path.splitext(n[len(prefix):])[0] or n) for n in pair_names(lab))
            for lab in labels]


@plain_text_figure
def plot_matches_per_pair(before: dict, after: dict, path: str | Path, *, title: str = "") -> Path:
    """Verified matches per pair before and after (log scale) and the share kept; ``{"a|b": count}``."""
    plt = _pyplot()
    labels = sorted(before, key=lambda k: -before[k])
    b = np.array([before[k] for k in labels], dtype=np.float64)
    a = np.array([after.get(k, 0) for k in labels], dtype=np.float64)
    ticks = short_labels(labels) if len(labels) <= 60 else []
    # the rotated tick labels get their own height (6 pt characters, about 0.6 em wide), so that
    # the plots keep theirs and tight_layout always fits
    label_height_in = max((len(t) for t in ticks), default=0) * 6 * 0.62 / 72
    fig, (ax, ax2) = plt.subplots(2, 1, figsize=(max(6.0, 0.2 * len(labels) + 2), 4.8 + label_height_in),
                                  sharex=True, gridspec_kw={"height_ratios": [2, 1]})
    x = np.arange(len(labels))
    ax.bar(x - 0.2, np.maximum(b, 0.8), color=COLORS["baseline"], label=f"baseline ({int(b.sum())})", width=0.4)
    ax.bar(x + 0.2, np.maximum(a, 0.8), color=COLORS["refined"], label=f"colmap-miho ({int(a.sum())})", width=0.4)
    ax.set_yscale("log")
    # the log axis' default labels are math text ("$\\mathdefault{10^{2}}$"), shown raw under
    # plain_text: plain numbers instead
    from matplotlib.ticker import LogFormatter

    ax.yaxis.set_major_formatter(LogFormatter())
    ax.yaxis.set_minor_formatter(LogFormatter(labelOnlyBase=False))
    ax.set_ylabel("verified matches")
    ax.set_title(title or "matches kept per pair")
    ax.legend(fontsize=8)
    frac = np.where(b > 0, a / np.maximum(b, 1), 0.0)
    ax2.bar(x, 100 * frac, color=COLORS["refined"], width=0.6)
    ax2.axhline(100, color="#999999", lw=0.8)
    ax2.set_ylabel("kept (%)")
    ax2.set_ylim(0, max(105.0, 100 * float(frac.max(initial=0)) + 5))
    ax2.set_xlabel("image pair (sorted by baseline matches)")
    if ticks:
        ax2.set_xticks(x, ticks, rotation=90, fontsize=6)
    fig.tight_layout()
    path = Path(path)
    _save(fig, path)
    plt.close(fig)
    return path
