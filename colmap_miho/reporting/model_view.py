"""The 3D view of ``report.html``: sparse models as decimated points and camera frusta, drawn in the
first model's frame (a similarity fitted on shared camera centres; with fewer than three, a model
keeps its own frame)."""

from __future__ import annotations

from typing import Any

import numpy as np

__all__ = ["POINT_BUDGET", "alignment", "camera_frusta", "decimate", "model_figure", "model_points", "moved_keypoints"]

POINT_BUDGET = 50_000
"""Most 3D points drawn per model (a seeded random subset beyond that)."""

MAX_IMAGES_SHOWN = 24
"""Images offered in the keypoint-displacement view (the ones with most moved keypoints)."""

COLORS = {"baseline": "#7f7f7f", "refined": "#d62728", "model": "#1f77b4", "checked": "#ff7f0e"}
SIDE_LABEL = {"baseline": "baseline", "refined": "colmap-miho"}


def decimate(num: int, budget: int = POINT_BUDGET, seed: int = 0) -> np.ndarray:
    """``(min(num, budget),)`` int64: all indices, or a seeded random increasing subset."""
    if budget < 1:
        raise ValueError(f"budget must be >= 1, got {budget}")
    if num <= budget:
        return np.arange(num, dtype=np.int64)
    rng = np.random.default_rng(seed)
    return np.sort(rng.choice(num, size=budget, replace=False)).astype(np.int64)


def _poses(rec) -> dict[str, tuple[np.ndarray, np.ndarray, Any]]:
    out = {}
    for image in rec.images.values():
        if not image.has_pose:
            continue
        pose = image.cam_from_world()
        out[image.name] = (np.array(pose.rotation.matrix(), dtype=np.float64),
                           np.array(pose.translation, dtype=np.float64), rec.cameras[image.camera_id])
    return out


def _centres(poses: dict) -> dict[str, np.ndarray]:
    return {n: -R.T @ t for n, (R, t, _) in poses.items()}


def camera_frusta(rec, size: float, transform=None) -> np.ndarray:
    """``(M, 3)`` polyline vertices of every registered camera's frustum (NaN rows between cameras),
    of depth ``size``, optionally mapped by ``transform`` ``(s, R, t)``."""
    chunks = []
    for _, (R, t, cam) in sorted(_poses(rec).items()):
        w, h = float(cam.width), float(cam.height)
        corners_px = np.array([[0.0, 0.0], [w, 0.0], [w, h], [0.0, h]])
        rays = np.asarray(cam.cam_from_img(corners_px), dtype=np.float64)  # (4, 2) normalised
        corners = np.c_[rays, np.ones(4)]
        corners *= size / np.linalg.norm(corners, axis=1, keepdims=True)
        c = -R.T @ t
        world = corners @ R + c  # R^T X_cam + C, row-wise
        # apex -> each corner, then the image rectangle
        path = np.stack([c, world[0], world[1], c, world[2], world[3], c, world[0], world[3], world[2], world[1]])
        chunks += [path, np.full((1, 3), np.nan)]
    if not chunks:
        return np.zeros((0, 3))
    out = np.concatenate(chunks)
    if transform is not None:
        s, Rt, tt = transform
        out = s * out @ Rt.T + tt
    return out


def alignment(rec_from, rec_to):
    """Similarity mapping ``rec_from``'s world onto ``rec_to``'s, from shared camera centres; None
    if fewer than three."""
    from .model_errors import umeyama

    a, b = _centres(_poses(rec_from)), _centres(_poses(rec_to))
    common = sorted(set(a) & set(b))
    if len(common) < 3:
        return None
    src, dst = np.array([a[n] for n in common]), np.array([b[n] for n in common])
    if np.linalg.matrix_rank(src - src.mean(0), tol=1e-9 * max(1.0, float(np.abs(src).max()))) < 2:
        return None  # collinear centres leave a rotation free
    return umeyama(src, dst)


def model_points(rec, transform=None) -> np.ndarray:
    pts = rec.points3D
    if not len(pts):
        return np.zeros((0, 3))
    xyz = np.array([pts[i].xyz for i in sorted(pts)], dtype=np.float64)
    if transform is not None:
        s, R, t = transform
        xyz = s * xyz @ R.T + t
    return xyz


def _frustum_size(rec, points: np.ndarray) -> float:
    """Frustum depth: a fifth of the cameras' spread, at least 6% of the median camera-point distance."""
    centres = np.array(list(_centres(_poses(rec)).values()))
    spread = float(np.median(np.linalg.norm(centres - centres.mean(0), axis=1))) if len(centres) > 1 else 0.0
    depth = 0.0
    if len(points):
        origin = centres.mean(0) if len(centres) else points.mean(0)
        depth = float(np.median(np.linalg.norm(points - origin, axis=1)))
    size = max(0.2 * spread, 0.06 * depth)
    return size if size > 0 else 1.0


def _viewpoint(rec) -> dict:
    """plotly's scene camera: along the cameras' mean viewing direction, their mean up on screen."""
    poses = _poses(rec)
    if not poses:
        return {}
    look = np.mean([R[2] for R, _, _ in poses.values()], axis=0)  # camera z axis in world
    up = -np.mean([R[1] for R, _, _ in poses.values()], axis=0)
    if np.linalg.norm(look) < 1e-9 or np.linalg.norm(up) < 1e-9:
        return {}
    look, up = look / np.linalg.norm(look), up / np.linalg.norm(up)
    eye = -1.6 * look + 0.6 * up
    return {"eye": dict(zip("xyz", map(float, eye), strict=True)), "up": dict(zip("xyz", map(float, up), strict=True))}


def model_figure(go, models: dict[str, Any], *, budget: int = POINT_BUDGET, seed: int = 0):
    """``(figure, note)``: each model's decimated points and frusta in the first one's frame, with
    show/hide buttons; ``note`` says how the models were aligned."""
    tags = list(models)
    ref = models[tags[0]]
    transforms: dict[str, object] = {tags[0]: None}
    aligned = True
    for tag in tags[1:]:
        transforms[tag] = alignment(models[tag], ref)
        aligned &= transforms[tag] is not None
    all_xyz = {tag: model_points(models[tag], transforms[tag]) for tag in tags}
    size = _frustum_size(ref, all_xyz[tags[0]])
    fig = go.Figure()
    traces_of: dict[str, list[int]] = {}
    for k, tag in enumerate(tags):
        xyz = all_xyz[tag]
        keep = decimate(len(xyz), budget, seed + k) if len(xyz) else np.zeros(0, np.int64)
        p = xyz[keep].astype(np.float32)
        color = COLORS.get(tag, None)
        name = SIDE_LABEL.get(tag, tag)
        shown = f"{len(keep)} of {len(xyz)}" if len(keep) < len(xyz) else f"{len(xyz)}"
        fig.add_trace(go.Scatter3d(x=p[:, 0], y=p[:, 1], z=p[:, 2], mode="markers", name=f"{name} points ({shown})",
                                   legendgroup=tag, marker={"size": 1.6, "color": color, "opacity": 0.8},
                                   hoverinfo="skip"))
        fr = camera_frusta(models[tag], size, transforms[tag]).astype(np.float32)
        n_cams = sum(1 for im in models[tag].images.values() if im.has_pose)
        fig.add_trace(go.Scatter3d(x=fr[:, 0], y=fr[:, 1], z=fr[:, 2], mode="lines", name=f"{name} cameras ({n_cams})",
                                   legendgroup=tag, line={"color": color, "width": 3}, hoverinfo="skip",
                                   connectgaps=False))
        traces_of[tag] = [2 * k, 2 * k + 1]
    n = 2 * len(tags)
    buttons = [{"label": "both" if len(tags) == 2 else "all", "method": "restyle", "args": [{"visible": [True] * n}]}]
    if len(tags) > 1:
        for tag in tags:
            vis = [i in traces_of[tag] for i in range(n)]
            buttons.append({"label": SIDE_LABEL.get(tag, tag), "method": "restyle", "args": [{"visible": vis}]})
    # the buttons sit top left, clear of plotly's mode bar (top right), the legend under them
    fig.update_layout(
        scene_camera=_viewpoint(ref),
        height=640, margin={"l": 0, "r": 0, "t": 50, "b": 0},
        legend={"itemsizing": "constant", "x": 0, "y": 0.98, "bgcolor": "rgba(255,255,255,0.7)"},
        scene={"aspectmode": "data", "xaxis": {"visible": False}, "yaxis": {"visible": False},
               "zaxis": {"visible": False}},
        updatemenus=[{"type": "buttons", "direction": "right", "x": 0, "xanchor": "left", "y": 1.0,
                      "yanchor": "bottom", "buttons": buttons, "showactive": True}] if len(tags) > 1 else [],
    )
    if len(tags) == 1:
        note = "Model units. Drag to turn, scroll to zoom; click a legend entry to hide it."
    elif aligned:
        note = (f"The {SIDE_LABEL[tags[1]] if tags[1] in SIDE_LABEL else tags[1]} model is drawn in the "
                f"{SIDE_LABEL.get(tags[0], tags[0])} model's frame (similarity fitted on the camera centres of "
                "the images both registered). Drag to turn, scroll to zoom; the buttons or the legend show one "
                "model or both.")
    else:
        note = "Fewer than three images are registered in both models: each model is drawn in its own frame."
    return fig, note


def moved_keypoints(models: dict[str, Any]) -> list[tuple[str, np.ndarray, np.ndarray]]:
    """Per image registered in both models: baseline positions ``(K, 2)`` of the moved keypoints and
    their displacements, most moved first (``point2D`` rows follow keypoint order)."""
    if set(models) != {"baseline", "refined"}:
        return []
    base = {im.name: im for im in models["baseline"].images.values() if im.has_pose}
    out = []
    for im in models["refined"].images.values():
        b = base.get(im.name)
        if b is None or not im.has_pose or len(b.points2D) != len(im.points2D) or not len(im.points2D):
            continue
        p0 = np.array([p.xy for p in b.points2D], dtype=np.float64)
        d = np.array([p.xy for p in im.points2D], dtype=np.float64) - p0
        moved = np.linalg.norm(d, axis=1) > 1e-6
        if moved.any():
            out.append((im.name, p0[moved], d[moved]))
    out.sort(key=lambda r: (-len(r[1]), r[0]))
    return out[:MAX_IMAGES_SHOWN]
