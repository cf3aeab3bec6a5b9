"""A built-in piecewise-planar "room corner" with exact ground truth, rendered on the fly from
scikit-image's bundled photographs (world: x right, y down, z forward; pixel centres at integers).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..errors import InvalidInput
from .gt_model import CameraPose, write_colmap_model

log = logging.getLogger(__name__)

PX_PER_UNIT = 80.0
"""Texture resolution of the planes (texture pixels per world unit)."""


@dataclass(frozen=True, kw_only=True)
class Plane:
    """A textured 3D rectangle ``origin + a u_axis + b v_axis``, a in [0, width], b in [0, height];
    the ``(h, w, 3)`` uint8 ``texture`` covers it."""

    origin: np.ndarray
    u_axis: np.ndarray
    v_axis: np.ndarray
    width: float
    height: float
    texture: np.ndarray


@dataclass(frozen=True, kw_only=True)
class DemoScene:
    """What :func:`make_demo_scene` wrote: image folder, GT model folder and the poses."""

    root: Path
    image_dir: Path
    gt_dir: Path
    poses: dict[str, CameraPose]


# --------------------------------------------------------------------------- textures
def _rgb(img: np.ndarray) -> np.ndarray:
    img = np.asarray(img)
    if img.ndim == 2:
        img = np.repeat(img[:, :, None], 3, axis=2)
    return np.ascontiguousarray(img[:, :, :3]).astype(np.uint8)


def _tile(img: np.ndarray, w: int, h: int) -> np.ndarray:
    img = _rgb(img)
    blk = np.concatenate([img, img[:, ::-1]], axis=1)
    blk = np.concatenate([blk, blk[::-1]], axis=0)
    reps = (int(np.ceil(h / blk.shape[0])), int(np.ceil(w / blk.shape[1])), 1)
    return np.tile(blk, reps)[:h, :w]


def _paste(canvas: np.ndarray, img: np.ndarray, x: int, y: int, width: int) -> None:
    import cv2

    img = _rgb(img)
    h = int(round(img.shape[0] * width / img.shape[1]))
    img = cv2.resize(img, (width, h), interpolation=cv2.INTER_AREA)
    canvas[y:y + h, x:x + width] = img
    # a dark frame around the picture
    cv2.rectangle(canvas, (x - 3, y - 3), (x + width + 2, y + h + 2), (40, 30, 25), 4)


def _plane(origin, u_axis, v_axis, width, height, texture) -> Plane:
    import cv2

    w, h = int(round(width * PX_PER_UNIT)), int(round(height * PX_PER_UNIT))
    if texture.shape[:2] != (h, w):
        texture = cv2.resize(texture, (w, h), interpolation=cv2.INTER_AREA)
    u = np.asarray(u_axis, float) / np.linalg.norm(u_axis)
    v = np.asarray(v_axis, float) / np.linalg.norm(v_axis)
    return Plane(origin=np.asarray(origin, float), u_axis=u, v_axis=v, width=float(width), height=float(height),
                 texture=texture)


def build_planes() -> list[Plane]:
    """The scene's planes (deterministic: the textures are the bundled photographs)."""
    import cv2

    from ..extras import require

    data = require("skimage.data", "demo", "the demo scene's textures")
    planes = []
    # back wall z = 9: brick, with photographs hung on it
    W, H = 30.0, 12.0
    wall = _tile(data.brick(), int(W * PX_PER_UNIT), int(H * PX_PER_UNIT))
    wall = cv2.convertScaleAbs(wall, alpha=0.9, beta=20)
    for img, (x, y, w) in ((data.astronaut(), (11.0, 5.6, 3.0)), (data.coffee(), (15.2, 6.2, 3.6)),
                           (data.chelsea(), (19.6, 6.4, 3.0)), (data.rocket(), (6.4, 6.4, 3.4)),
                           (data.camera(), (23.6, 6.0, 2.2))):
        _paste(wall, img, int(x * PX_PER_UNIT), int(y * PX_PER_UNIT), int(w * PX_PER_UNIT))
    planes.append(_plane([-15.0, -9.5, 9.0], [1, 0, 0], [0, 1, 0], W, H, wall))
    # floor y = 2.5: gravel
    planes.append(_plane([-15.0, 2.5, 9.0], [1, 0, 0], [0, 0, -1], 30.0, 8.5,
                         _tile(data.gravel(), int(30 * PX_PER_UNIT), int(8.5 * PX_PER_UNIT))))
    # a poster standing on the floor, turned 35 degrees about the vertical axis
    a = np.radians(35.0)
    u = np.array([np.cos(a), 0.0, np.sin(a)])
    poster = _tile(data.grass(), int(2.4 * PX_PER_UNIT), int(3.0 * PX_PER_UNIT))
    _paste(poster, data.astronaut(), int(0.3 * PX_PER_UNIT), int(0.3 * PX_PER_UNIT), int(1.8 * PX_PER_UNIT))
    planes.append(_plane([-3.2, -0.5, 5.6], u, [0, 1, 0], 2.4, 3.0, poster))
    # a box on the floor: front face (coffee) and the face turned to the right (text)
    x0, z0, s, h = 1.2, 5.0, 1.6, 1.6
    planes.append(_plane([x0, 2.5 - h, z0], [1, 0, 0], [0, 1, 0], s, h,
                         cv2.resize(_rgb(data.coffee()), (int(s * PX_PER_UNIT), int(h * PX_PER_UNIT)))))
    page = cv2.resize(_rgb(data.page()), (448, 224), interpolation=cv2.INTER_AREA)
    side = np.concatenate([_rgb(data.text()), page], axis=0)
    planes.append(_plane([x0 + s, 2.5 - h, z0], [0, 0, 1], [0, 1, 0], s, h, side))
    # the box's top (moon)
    planes.append(_plane([x0, 2.5 - h, z0 + s], [1, 0, 0], [0, 0, -1], s, s, _rgb(data.moon())))
    return planes


# --------------------------------------------------------------------------- cameras
def look_at(center: np.ndarray, target: np.ndarray, roll_deg: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
    """World-to-camera (R, t) of a camera at ``center`` looking at ``target`` (y down)."""
    z = np.asarray(target, float) - np.asarray(center, float)
    z /= np.linalg.norm(z)
    x = np.cross([0.0, 1.0, 0.0], z)
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    R = np.stack([x, y, z])
    if roll_deg:
        c, s = np.cos(np.radians(roll_deg)), np.sin(np.radians(roll_deg))
        R = np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]]) @ R
    return R, -R @ np.asarray(center, float)


def demo_cameras(num_images: int = 8, width: int = 640, height: int = 480) -> list[CameraPose]:
    """Cameras on an arc in front of the scene, looking near its centre, with small rolls."""
    f = 0.85 * width
    K = np.array([[f, 0.0, (width - 1) / 2.0], [0.0, f, (height - 1) / 2.0], [0.0, 0.0, 1.0]])
    out = []
    for i, s in enumerate(np.linspace(-1.0, 1.0, num_images)):
        center = np.array([2.6 * s, -0.6 + 0.3 * np.cos(3 * s), -0.6 + 0.8 * s * s])
        target = np.array([0.4 * s, 0.3, 6.5])
        R, t = look_at(center, target, roll_deg=4.0 * np.sin(2.5 * s))
        out.append(CameraPose(name=f"view_{i:02d}.png", K=K, R=R, t=t, width=width, height=height))
    return out


# --------------------------------------------------------------------------- rendering
def render_view(planes: list[Plane], cam: CameraPose, *, noise_std: float = 1.5, seed: int = 0) -> np.ndarray:
    """Render (H, W, 3) uint8 BGR of the planes seen by ``cam`` (nearest plane wins per pixel)."""
    import cv2

    W, H = cam.width, cam.height
    image = np.full((H, W, 3), 90, np.float32)
    depth = np.full((H, W), np.inf, np.float64)
    xs, ys = np.meshgrid(np.arange(W, dtype=np.float64), np.arange(H, dtype=np.float64))
    rays = np.stack([xs, ys, np.ones_like(xs)], axis=-1) @ np.linalg.inv(cam.K).T  # (H, W, 3), z = 1
    for pl in planes:
        o_c = cam.R @ pl.origin + cam.t
        u_c, v_c = cam.R @ pl.u_axis, cam.R @ pl.v_axis
        n_c = np.cross(u_c, v_c)
        if n_c @ o_c > 0:  # the camera sees the back of the plane: flip the normal, still render
            n_c = -n_c
        # texture pixel (a, b) -> camera point o + (a / ppu) u + (b / ppu) v
        A = np.stack([u_c / PX_PER_UNIT, v_c / PX_PER_UNIT, o_c], axis=1)
        H_img = cam.K @ A
        tex = pl.texture.astype(np.float32)
        th, tw = tex.shape[:2]
        warped = cv2.warpPerspective(tex, H_img, (W, H), flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT)
        mask = cv2.warpPerspective(np.ones((th, tw), np.float32), H_img, (W, H), flags=cv2.INTER_LINEAR,
                                   borderMode=cv2.BORDER_CONSTANT)
        # depth of the plane along each pixel ray (z = 1 rays): n . (z r) = n . o
        denom = rays @ n_c
        with np.errstate(divide="ignore", invalid="ignore"):
            z = (n_c @ o_c) / denom
        vis = (mask > 0.5) & (z > 0.05) & (z < depth)
        depth[vis] = z[vis]
        image[vis] = warped[vis] / np.maximum(mask[vis, None], 1e-6)
    if noise_std > 0:
        image += np.random.default_rng(seed).normal(0.0, noise_std, image.shape).astype(np.float32)
    rgb = np.clip(image + 0.5, 0, 255).astype(np.uint8)
    return cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR)


def make_demo_scene(
    out_dir: str | Path, *, num_images: int = 8, width: int = 640, height: int = 480, noise_std: float = 1.5,
    seed: int = 0,
) -> DemoScene:
    """Write ``out_dir/images/*.png`` and the exact GT model ``out_dir/gt_model/``: ``num_images``
    (>= 3) views on an arc, with Gaussian sensor noise ``noise_std`` (grey levels) seeded by
    ``seed``."""
    import cv2

    if num_images < 3:
        raise InvalidInput(f"num_images must be >= 3, got {num_images}")
    if width < 160 or height < 120:
        raise InvalidInput(f"width x height must be at least 160 x 120, got {width} x {height}")
    root = Path(out_dir)
    image_dir = root / "images"
    image_dir.mkdir(parents=True, exist_ok=True)
    planes = build_planes()
    cams = demo_cameras(num_images, width, height)
    for i, cam in enumerate(cams):
        img = render_view(planes, cam, noise_std=noise_std, seed=seed + i)
        if not cv2.imwrite(str(image_dir / cam.name), img):
            raise OSError(f"cannot write {image_dir / cam.name}")
    poses = {c.name: c for c in cams}
    gt_dir = write_colmap_model(poses, root / "gt_model")
    log.info("demo scene: %d views %dx%d in %s, GT model in %s", num_images, width, height, image_dir, gt_dir)
    return DemoScene(root=root, image_dir=image_dir, gt_dir=gt_dir, poses=poses)
