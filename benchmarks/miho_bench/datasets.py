"""Loaders for image pairs with ground truth (the layouts of ``../shared/data``).

Two layouts are supported:

* planar sequences (Oxford affine): ``img1.png .. img6.png`` and ``H1to{j}p`` text files with
  the homography mapping img1 pixels to imgj pixels;
* multi-view scenes with a ``pairs_with_gt.txt`` in the SuperGlue/LoFTR layout
  (``name0 name1 rot0 rot1 K0(9) K1(9) T_0to1(16)``) next to an ``images/`` folder.

Every coordinate is in pixels with integer = pixel centre. The files' own pixel convention
(centre vs corner) differs by at most 0.5 px, which the data README says is negligible at the
evaluation thresholds used here.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from colmap_miho.adapters.images import read_gray_uint8
from colmap_miho.geometry import skew


def load_gray(path: str | Path) -> np.ndarray:
    """Read an image file as (H, W) uint8 grayscale (the package's one image reader,
    :func:`colmap_miho.adapters.images.read_gray_uint8`).

    Raises:
        FileNotFoundError: the file does not exist or cannot be decoded.
    """
    return read_gray_uint8(path)


def fundamental_from_pose(K1: np.ndarray, K2: np.ndarray, T_2from1: np.ndarray) -> np.ndarray:
    """Fundamental matrix F_2from1 with x2^T F x1 = 0 from intrinsics and the relative pose.

    Args:
        K1, K2: (3, 3) intrinsics. T_2from1: (4, 4) or (3, 4), X_cam2 = R X_cam1 + t.
    """
    R, t = T_2from1[:3, :3], T_2from1[:3, 3]
    E = skew(t) @ R
    F = np.linalg.inv(K2).T @ E @ np.linalg.inv(K1)
    return F / np.linalg.norm(F)


@dataclass(frozen=True)
class PairGT:
    """An image pair with its ground truth.

    Attributes:
        name1, name2: image names (file names relative to the scene's image folder).
        path1, path2: image paths.
        K1, K2: (3, 3) intrinsics or None (planar sequences).
        T_2from1: (4, 4) relative pose, X_cam2 = R X_cam1 + t, or None.
        H_2from1: (3, 3) homography mapping image-1 pixels to image-2 pixels, or None.
    """

    name1: str
    name2: str
    path1: Path
    path2: Path
    K1: np.ndarray | None = None
    K2: np.ndarray | None = None
    T_2from1: np.ndarray | None = None
    H_2from1: np.ndarray | None = None

    @property
    def F_2from1(self) -> np.ndarray | None:
        """(3, 3) fundamental matrix (x2^T F x1 = 0), or None when there is no pose."""
        if self.T_2from1 is None or self.K1 is None or self.K2 is None:
            return None
        return fundamental_from_pose(self.K1, self.K2, self.T_2from1)

    @property
    def is_planar(self) -> bool:
        return self.H_2from1 is not None

    @property
    def label(self) -> str:
        folder = self.path1.parent
        scene = folder.parent.name if folder.name == "images" else folder.name
        return f"{scene}/{self.name1}-{self.name2}"

    def image1(self) -> np.ndarray:
        """(H, W) uint8 grayscale of image 1."""
        return load_gray(self.path1)

    def image2(self) -> np.ndarray:
        """(H, W) uint8 grayscale of image 2."""
        return load_gray(self.path2)


def oxford_pairs(seq_dir: str | Path, targets: tuple[int, ...] = (2, 3, 4, 5, 6)) -> list[PairGT]:
    """Pairs img1 -> img{j} of an Oxford affine sequence folder with GT homographies."""
    seq_dir = Path(seq_dir)
    first = next((p for p in sorted(seq_dir.glob("img1.*"))), None)
    if first is None:
        raise FileNotFoundError(f"no img1.* in {seq_dir}")
    pairs = []
    for j in targets:
        other = next(iter(sorted(seq_dir.glob(f"img{j}.*"))), None)
        h_file = seq_dir / f"H1to{j}p"
        if other is None or not h_file.is_file():
            raise FileNotFoundError(f"missing img{j} or {h_file.name} in {seq_dir}")
        H = np.loadtxt(h_file).reshape(3, 3)
        pairs.append(PairGT(first.name, other.name, first, other, H_2from1=H / H[2, 2]))
    return pairs


def multiview_pairs(scene_dir: str | Path, image_dir: str | Path | None = None) -> list[PairGT]:
    """Pairs listed in ``scene_dir/pairs_with_gt.txt`` (38 fields a line, see module doc)."""
    scene_dir = Path(scene_dir)
    image_dir = Path(image_dir) if image_dir is not None else scene_dir / "images"
    pairs_file = scene_dir / "pairs_with_gt.txt"
    if not pairs_file.is_file():
        raise FileNotFoundError(f"no pairs_with_gt.txt in {scene_dir}")
    pairs = []
    for lineno, line in enumerate(pairs_file.read_text().splitlines(), 1):
        fields = line.split()
        if not fields:
            continue
        if len(fields) != 38:
            raise ValueError(f"{pairs_file}:{lineno}: expected 38 fields, got {len(fields)}")
        values = np.array(fields[4:], dtype=np.float64)
        K1, K2 = values[:9].reshape(3, 3), values[9:18].reshape(3, 3)
        T = values[18:].reshape(4, 4)
        pairs.append(
            PairGT(fields[0], fields[1], image_dir / fields[0], image_dir / fields[1], K1=K1, K2=K2, T_2from1=T)
        )
    return pairs
