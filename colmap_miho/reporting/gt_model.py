"""Ground-truth poses: COLMAP models, Strecha ``.camera`` files and Middlebury ``_par.txt``, as
``dict[str, CameraPose]`` keyed by image name; the half-pixel shift of COLMAP models happens in
:func:`poses_from_reconstruction` and :func:`write_colmap_model` only."""

from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..adapters.conventions import colmap_to_pixel_centre, pixel_centre_to_colmap
from ..adapters.images import image_size
from ..errors import InvalidInput
from ..geometry import project_to_so3

log = logging.getLogger(__name__)

IMAGE_EXTENSIONS = (".jpg", ".jpeg", ".png", ".ppm", ".pgm", ".bmp", ".tif", ".tiff")


@dataclass(frozen=True, kw_only=True)
class CameraPose:
    """One calibrated, posed image: ``K`` ``(3, 3)`` pixel-centre intrinsics, world-to-camera ``R``,
    ``t`` (``X_cam = R X + t``), size in pixels."""

    name: str
    K: np.ndarray
    R: np.ndarray
    t: np.ndarray
    width: int
    height: int

    @property
    def center(self) -> np.ndarray:
        """(3,) camera centre in world coordinates, ``-R^T t``."""
        return -self.R.T @ self.t


# --------------------------------------------------------------------------- COLMAP models
def poses_from_reconstruction(rec) -> dict[str, CameraPose]:
    """Registered images of a reconstruction by name; K is the camera's pinhole part (distortion ignored)."""
    out: dict[str, CameraPose] = {}
    for image in rec.images.values():
        if not image.has_pose:
            continue
        cam = rec.cameras[image.camera_id]
        K = np.array(cam.calibration_matrix(), dtype=np.float64)
        K[:2, 2] = colmap_to_pixel_centre(K[:2, 2])
        pose = image.cam_from_world()
        out[image.name] = CameraPose(
            name=image.name, K=K, R=np.array(pose.rotation.matrix(), dtype=np.float64),
            t=np.array(pose.translation, dtype=np.float64), width=int(cam.width),
            height=int(cam.height),
        )
    return out


def resolve_model_dir(path: str | Path) -> Path:
    """The COLMAP model folder for ``path``: the folder itself, its ``gt_model/`` or ``0/``."""
    path = Path(path)
    if not path.exists():
        raise FileNotFoundError(f"ground-truth path not found: {path}")
    for cand in (path, path / "gt_model", path / "sparse" / "0", path / "0"):
        if (cand / "images.txt").is_file() or (cand / "images.bin").is_file():
            return cand
    raise InvalidInput(
        f"{path} is not a COLMAP model folder (no images.txt/images.bin in it, its gt_model/ or 0/)"
    )


def load_reconstruction(path: str | Path):
    """Read a COLMAP model folder (text or binary; binary sizes checked first); InvalidInput if damaged."""
    import pycolmap

    from ..adapters.model_files import check_binary_model

    model_dir = resolve_model_dir(path)
    check_binary_model(model_dir)  # a lying count must not reach pycolmap's allocations
    try:
        return pycolmap.Reconstruction(str(model_dir))
    except (RuntimeError, IndexError, ValueError) as exc:  # pycolmap's errors on a truncated file
        msg = " ".join(str(exc).split())
        raise InvalidInput(f"cannot read the COLMAP model in {model_dir} (damaged or truncated file? "
                         f"{msg}); write it again") from None


def load_gt_poses(path: str | Path) -> dict[str, CameraPose]:
    """GT poses by image name from a COLMAP model folder, or a dataset folder holding ``gt_model/``."""
    poses = poses_from_reconstruction(load_reconstruction(path))
    if not poses:
        raise InvalidInput(f"the ground-truth model at {path} has no posed images")
    return poses


def _quat_wxyz(R: np.ndarray) -> np.ndarray:
    import pycolmap

    x, y, z, w = pycolmap.Rotation3d(np.asarray(R, dtype=np.float64)).quat
    q = np.array([w, x, y, z])
    return -q if q[0] < 0 else q


def write_colmap_model(poses: dict[str, CameraPose], out_dir: str | Path) -> Path:
    """Write poses as a COLMAP text model (PINHOLE, shared cameras, ids by sorted name, no points);
    returns the folder."""
    if not poses:
        raise InvalidInput("poses is empty: nothing to write")
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    cameras: dict[tuple, int] = {}
    cam_lines, img_lines = [], []
    for image_id, name in enumerate(sorted(poses), start=1):
        p = poses[name]
        fx, fy = p.K[0, 0], p.K[1, 1]
        cx, cy = pixel_centre_to_colmap(p.K[:2, 2])
        key = (p.width, p.height, round(fx, 9), round(fy, 9), round(cx, 9), round(cy, 9))
        if key not in cameras:
            cameras[key] = len(cameras) + 1
            cam_lines.append(f"{cameras[key]} PINHOLE {p.width} {p.height} {fx:.12g} {fy:.12g} {cx:.12g} {cy:.12g}")
        q = _quat_wxyz(p.R)
        t = p.t
        img_lines.append(
            f"{image_id} {q[0]:.15g} {q[1]:.15g} {q[2]:.15g} {q[3]:.15g} "
            f"{t[0]:.15g} {t[1]:.15g} {t[2]:.15g} {cameras[key]} {name}"
        )
        img_lines.append("")  # no 2D points
    from ..adapters.staged_write import write_text_atomic

    # each file staged, size-checked and renamed: a full disk leaves no empty or short file
    write_text_atomic(out / "cameras.txt", "# CAMERA_ID MODEL WIDTH HEIGHT fx fy cx cy\n" + "\n".join(cam_lines) + "\n")
    write_text_atomic(out / "images.txt", "# IMAGE_ID QW QX QY QZ TX TY TZ CAMERA_ID NAME\n# POINTS2D (none)\n"
                      + "\n".join(img_lines) + "\n")
    write_text_atomic(out / "points3D.txt", "# no points: ground truth has cameras only\n")
    return out


# --------------------------------------------------------------------------- dataset layouts
def list_images(image_dir: str | Path) -> list[str]:
    """Image file names (sorted) in a folder, by extension."""
    image_dir = Path(image_dir)
    if not image_dir.is_dir():
        raise NotADirectoryError(f"image folder not found: {image_dir}")
    return sorted(p.name for p in image_dir.iterdir() if p.suffix.lower() in IMAGE_EXTENSIONS)


def _rescale(K: np.ndarray, size_from: tuple[int, int], size_to: tuple[int, int], name: str) -> np.ndarray:
    if size_from == size_to:
        return K
    sx, sy = size_to[0] / size_from[0], size_to[1] / size_from[1]
    if abs(sx - sy) > 1e-3:
        raise InvalidInput(f"{name}: GT size {size_from} and image size {size_to} differ in aspect")
    log.info("%s: scaling GT intrinsics by %.4g (GT %dx%d, image %dx%d)", name, sx, *size_from, *size_to)
    S = np.diag([sx, sy, 1.0])
    # pixel-centre convention: x' + 0.5 = s (x + 0.5)
    S[0, 2], S[1, 2] = 0.5 * (sx - 1.0), 0.5 * (sy - 1.0)
    return S @ K


def read_strecha_camera(path: str | Path) -> tuple[np.ndarray, np.ndarray, np.ndarray, tuple[int, int]]:
    """``(K, R_w2c, t_w2c, (width, height))`` of one Strecha ``.camera`` file; R projected onto SO(3)."""
    rows = [ln.split() for ln in Path(path).read_text(encoding="utf-8").splitlines() if ln.strip()]
    try:
        vals = [[float(v) for v in r] for r in rows]
        K = np.array(vals[0:3], dtype=np.float64)
        R_c2w = np.array(vals[4:7], dtype=np.float64)
        C = np.array(vals[7], dtype=np.float64)
        w, h = int(vals[8][0]), int(vals[8][1])
    except (IndexError, ValueError) as exc:
        raise InvalidInput(f"{path}: not a Strecha .camera file ({exc})") from None
    if K.shape != (3, 3) or R_c2w.shape != (3, 3) or C.shape != (3,):
        raise InvalidInput(f"{path}: not a Strecha .camera file (bad K/R/C shapes)")
    R = project_to_so3(R_c2w.T)
    return K, R, -R @ C, (w, h)


def strecha_poses(gt_dir: str | Path, image_dir: str | Path) -> dict[str, CameraPose]:
    """GT poses for every image with a ``.camera`` file, intrinsics rescaled to the image's size."""
    gt_dir, image_dir = Path(gt_dir), Path(image_dir)
    out: dict[str, CameraPose] = {}
    for name in list_images(image_dir):
        cam = gt_dir / f"{name}.camera"
        if not cam.is_file():
            log.warning("no GT camera file for %s", name)
            continue
        K, R, t, size = read_strecha_camera(cam)
        img_size = image_size(image_dir / name)
        K = _rescale(K, size, img_size, name)
        out[name] = CameraPose(name=name, K=K, R=R, t=t, width=img_size[0], height=img_size[1])
    if not out:
        raise InvalidInput(f"no <image>.camera file in {gt_dir} matches an image of {image_dir}")
    return out


def _find_par_file(path: Path) -> Path:
    if path.is_file():
        return path
    found = sorted(path.glob("*_par.txt"))
    if len(found) != 1:
        raise InvalidInput(f"expected exactly one *_par.txt in {path}, found {len(found)}")
    return found[0]


def middlebury_poses(par_path: str | Path, image_dir: str | Path) -> dict[str, CameraPose]:
    """GT poses from a Middlebury ``*_par.txt`` (file, or folder holding exactly one)."""
    par = _find_par_file(Path(par_path))
    image_dir = Path(image_dir)
    names = set(list_images(image_dir))
    lines = [ln.split() for ln in par.read_text(encoding="utf-8").splitlines() if ln.strip()]
    out: dict[str, CameraPose] = {}
    for fields in lines[1:]:
        if len(fields) != 22:
            raise InvalidInput(f"{par}: expected 22 fields per line, got {len(fields)}: {' '.join(fields[:3])} ...")
        name = fields[0]
        if name not in names:
            log.warning("%s: %s is not in %s", par.name, name, image_dir)
            continue
        v = np.array([float(x) for x in fields[1:]], dtype=np.float64)
        w, h = image_size(image_dir / name)
        out[name] = CameraPose(
            name=name, K=v[0:9].reshape(3, 3), R=project_to_so3(v[9:18].reshape(3, 3)),
            t=v[18:21], width=w, height=h,
        )
    if not out:
        raise InvalidInput(f"no image of {par} found in {image_dir}")
    return out


def convert_gt(fmt: str, input_path: str | Path, image_dir: str | Path, output: str | Path) -> dict[str, CameraPose]:
    """Convert a dataset's GT (``fmt`` "strecha" or "middlebury") into a COLMAP text model."""
    fmt = str(fmt).lower()
    if fmt == "strecha":
        poses = strecha_poses(input_path, image_dir)
    elif fmt == "middlebury":
        poses = middlebury_poses(input_path, image_dir)
    else:
        raise InvalidInput(f"format={fmt!r} is not one of: strecha, middlebury")
    write_colmap_model(poses, output)
    return poses
