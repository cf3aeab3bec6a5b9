"""Sparse point clouds: the PLY export, density / outlier figures and pictures.

open3d is an optional extra (``pip install 'colmap-miho[pointcloud]'``); without it, nearest
neighbours come from scipy's cKDTree (open3d's statistical outlier rule reproduced exactly) and
pictures from matplotlib. Units are the reconstruction's. Arrays: ``points`` (N, 3) float64,
``colors`` (N, 3) uint8.
"""

from __future__ import annotations

import logging
import os
from pathlib import Path

import numpy as np

from ..errors import InvalidInput

log = logging.getLogger(__name__)

OPEN3D_MISSING = "open3d is not installed: pip install 'colmap-miho[pointcloud]' (or pip install 'open3d>=0.18')"
_renderer_failed: str | None = None  # why open3d's offscreen renderer did not work, once seen


def have_open3d() -> bool:
    """Whether open3d can be imported."""
    try:
        import open3d  # noqa: F401
    except ImportError:
        return False
    return True


def require_open3d():
    """Return the open3d module or raise ``RuntimeError`` telling how to install it."""
    try:
        import open3d
    except ImportError as exc:
        raise RuntimeError(f"{OPEN3D_MISSING} ({exc})") from None
    return open3d


def _check_points(points: np.ndarray, name: str = "points") -> np.ndarray:
    p = np.asarray(points, dtype=np.float64)
    if p.ndim != 2 or p.shape[1] != 3:
        raise InvalidInput(f"{name} must have shape (N, 3), got {p.shape}")
    if not np.isfinite(p).all():
        raise InvalidInput(f"{name} contain NaN or inf")
    return p


# ---------------------------------------------------------------------------------------------
# PLY


def reconstruction_points(reconstruction) -> tuple[np.ndarray, np.ndarray]:
    """3D points of a ``pycolmap.Reconstruction``: (N, 3) float64 xyz and (N, 3) uint8 RGB,
    in increasing point3D id order."""
    pts = reconstruction.points3D
    ids = sorted(pts)
    if not ids:
        return np.zeros((0, 3)), np.zeros((0, 3), np.uint8)
    xyz = np.array([pts[i].xyz for i in ids], dtype=np.float64)
    rgb = np.array([pts[i].color for i in ids], dtype=np.uint8)
    return xyz, rgb


def export_ply(reconstruction, path: str | Path) -> Path:
    """Write the 3D points of a ``pycolmap.Reconstruction`` with their colours to a binary PLY
    (pycolmap's ``export_PLY``: float x, y, z and uchar red, green, blue). The native writer
    reports no failed write: it writes a staged file whose size is checked against its own
    header before it is renamed onto ``path``. Returns the path.

    Raises:
        RunFailed: disk full (the file came out short); ``path`` is left as it was.
    """
    from ..adapters.staged_write import ply_size, staged_write

    path = Path(path)
    if not path.parent.is_dir():
        raise NotADirectoryError(f"output folder does not exist: {path.parent}")
    with staged_write(path, expected_size=ply_size) as tmp:
        reconstruction.export_PLY(str(tmp))
    return path


# ---------------------------------------------------------------------------------------------
# figures


def _knn_distances(points: np.ndarray, k: int) -> np.ndarray:
    """(N, k) distances to the k nearest points, the point itself (distance 0) included
    (scipy's cKDTree: exact, and faster than a per-point open3d query from Python)."""
    from scipy.spatial import cKDTree

    d, _ = cKDTree(points).query(points, k=k)
    return np.asarray(d, dtype=np.float64).reshape(len(points), k)


def _backend(backend: str) -> str:
    if backend not in ("auto", "open3d", "scipy"):
        raise InvalidInput(f"backend={backend!r} is not one of: auto, open3d, scipy")
    if backend == "auto":
        return "open3d" if have_open3d() else "scipy"
    if backend == "open3d":
        require_open3d()
    return backend


def statistical_outliers(points: np.ndarray, *, nb_neighbors: int = 20, std_ratio: float = 2.0,
                         backend: str = "auto") -> np.ndarray:
    """bool (N,) True for the statistical outliers of open3d's ``remove_statistical_outlier``:
    a point's mean distance to its ``nb_neighbors`` nearest points (itself included, as open3d
    counts it) at or above the cloud's mean of that value + ``std_ratio`` x its standard deviation
    (ddof 1). ``backend``: "open3d" (open3d itself), "scipy" (cKDTree, same rule) or "auto"."""
    p = _check_points(points)
    if nb_neighbors < 1:
        raise InvalidInput(f"nb_neighbors must be >= 1, got {nb_neighbors}")
    if std_ratio <= 0:
        raise InvalidInput(f"std_ratio must be > 0, got {std_ratio}")
    if len(p) <= nb_neighbors:
        return np.zeros(len(p), dtype=bool)
    if _backend(backend) == "open3d":
        o3d = require_open3d()
        _, keep = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(p)).remove_statistical_outlier(
            nb_neighbors=int(nb_neighbors), std_ratio=float(std_ratio))
        out = np.ones(len(p), dtype=bool)
        out[np.asarray(keep, dtype=np.int64)] = False
        return out
    avg = _knn_distances(p, int(nb_neighbors)).mean(axis=1)
    threshold = avg.mean() + std_ratio * avg.std(ddof=1)
    return ~((avg > 0) & (avg < threshold))


def cloud_figures(points: np.ndarray, *, nb_neighbors: int = 20, std_ratio: float = 2.0,
                  backend: str = "auto") -> dict:
    """Density and cleanliness of one cloud.

    Args:
        points: (N, 3) float, any unit.
        nb_neighbors, std_ratio: open3d's statistical-outlier parameters.
        backend: "auto" (open3d when installed), "open3d" or "scipy".

    Returns:
        dict with ``num_points``, ``outlier_share`` (fraction of statistical outliers, see
        :func:`statistical_outliers`, computed by ``backend``), ``spacing_median`` /
        ``spacing_mean`` (distance from each point to its nearest other point, unit of
        ``points``, via cKDTree; NaN below 2 points) and ``backend``.
    """
    p = _check_points(points)
    b = _backend(backend)
    out = {"num_points": int(len(p)), "outlier_share": 0.0, "spacing_median": float("nan"),
           "spacing_mean": float("nan"), "backend": b}
    if len(p) < 2:
        return out
    nn = _knn_distances(p, 2)[:, 1]
    out["spacing_median"], out["spacing_mean"] = float(np.median(nn)), float(nn.mean())
    outliers = statistical_outliers(p, nb_neighbors=nb_neighbors, std_ratio=std_ratio, backend=b)
    out["outlier_share"] = float(outliers.mean())
    return out


# ---------------------------------------------------------------------------------------------
# pictures


def render_cloud_png(points: np.ndarray, colors: np.ndarray | None, path: str | Path, *,
                     width: int = 800, height: int = 600, backend: str = "auto",
                     title: str | None = None) -> str:
    """Draw a cloud to a PNG; returns the backend used ("open3d" or "matplotlib").

    ``backend="auto"`` tries open3d's headless ``OffscreenRenderer`` (it needs EGL or a GPU
    driver; on a plain server it raises, e.g. "Failed to load vulkan library!", and the failure is
    remembered for the process) and falls back to a matplotlib 3-D scatter (Agg, works
    everywhere). Colours: (N, 3) uint8 RGB or None (then coloured by height).
    """
    global _renderer_failed
    p = _check_points(points)
    if backend not in ("auto", "open3d", "matplotlib"):
        raise InvalidInput(f"backend={backend!r} is not one of: auto, open3d, matplotlib")
    c = None if colors is None else np.asarray(colors, dtype=np.float64).reshape(-1, 3) / 255.0
    if c is not None and len(c) != len(p):
        raise InvalidInput(f"colors must have {len(p)} rows, got {len(c)}")
    path = Path(path)
    if backend == "open3d" or (backend == "auto" and _renderer_failed is None and have_open3d()):
        try:
            _render_open3d(p, c, path, width, height)
            return "open3d"
        except RuntimeError as exc:
            if backend == "open3d":
                raise
            _renderer_failed = str(exc)
            log.info("open3d offscreen rendering unavailable (%s); using matplotlib", exc)
    _render_matplotlib(p, c, path, width, height, title)
    return "matplotlib"


def _render_open3d(p, c, path: Path, width: int, height: int) -> None:
    o3d = require_open3d()
    level = o3d.utility.get_verbosity_level()
    o3d.utility.set_verbosity_level(o3d.utility.VerbosityLevel.Error)
    try:
        r = o3d.visualization.rendering.OffscreenRenderer(int(width), int(height))
    finally:
        o3d.utility.set_verbosity_level(level)
    pc = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(p))
    if c is not None:
        pc.colors = o3d.utility.Vector3dVector(c)
    mat = o3d.visualization.rendering.MaterialRecord()
    mat.shader, mat.point_size = "defaultUnlit", 3.0
    r.scene.set_background([1.0, 1.0, 1.0, 1.0])
    r.scene.add_geometry("cloud", pc, mat)
    lo, hi = (p.min(0), p.max(0)) if len(p) else (np.zeros(3), np.ones(3))
    centre, extent = (lo + hi) / 2, float(np.linalg.norm(hi - lo)) or 1.0
    r.setup_camera(60.0, centre, centre + np.array([0.0, -0.3, -1.2]) * extent, [0.0, -1.0, 0.0])
    from ..adapters.staged_write import staged_write

    with staged_write(path) as tmp:
        png = f"{tmp}.png"  # open3d picks the format by the suffix
        try:
            if not o3d.io.write_image(png, r.render_to_image()):
                raise OSError(f"open3d could not write {path}")
            os.replace(png, tmp)
        finally:
            Path(png).unlink(missing_ok=True)


def _render_matplotlib(p, c, path: Path, width: int, height: int, title: str | None) -> None:
    from .plots import plain_text

    with plain_text():  # the title is plain text
        _draw_matplotlib(p, c, path, width, height, title)


def _draw_matplotlib(p, c, path: Path, width: int, height: int, title: str | None) -> None:
    from ..extras import require

    Figure = require("matplotlib.figure", "plots", "drawing a point cloud without open3d").Figure
    dpi = 100
    fig = Figure(figsize=(width / dpi, height / dpi), dpi=dpi)
    ax = fig.add_subplot(projection="3d")
    shown = 0
    if len(p):
        # principal axes: the two widest spread across the picture, the thinnest (a facade's
        # normal, a ground plane's up) is the viewing depth, so structures are seen face-on
        centred = p - p.mean(0)
        axes = np.linalg.svd(centred, full_matrices=False)[2] if len(p) >= 3 else np.eye(3)
        q = centred @ axes.T
        # the 5th-95th percentile box (+25 %): far points are left out, not shrinking the cloud
        lo, hi = np.percentile(q, 5, axis=0), np.percentile(q, 95, axis=0)
        pad = 0.25 * np.maximum(hi - lo, 1e-9)
        lo, hi = lo - pad, hi + pad
        inside = np.all((q >= lo) & (q <= hi), axis=1)
        q = q[inside]
        shown = len(q)
        ax.scatter(q[:, 0], q[:, 2], q[:, 1], s=1.5, c=c[inside] if c is not None else q[:, 1],
                   cmap=None if c is not None else "viridis", linewidths=0, depthshade=False)
        ax.set_xlim(lo[0], hi[0])
        ax.set_ylim(lo[2], hi[2])
        ax.set_zlim(lo[1], hi[1])
        ax.set_box_aspect(tuple(hi[[0, 2, 1]] - lo[[0, 2, 1]]))
        ax.view_init(elev=20, azim=-75)
    ax.set_xlabel("axis 1")
    ax.set_ylabel("axis 3 (depth)")
    ax.set_zlabel("axis 2")
    ax.set_title(title or f"{len(p)} points ({len(p) - shown} far points not drawn)")
    from ..adapters.staged_write import staged_write

    with staged_write(path) as tmp:
        fig.savefig(tmp, dpi=dpi, format="png")
