"""Lazy, bounded loading of the images named in a COLMAP database.

:class:`ImageLoader` is a read-only mapping ``image_id -> float32 (H, W) grayscale in
[0, 1]`` (or ``None`` for a missing or unreadable image). Images are read on first access and
at most ``max_cached`` are kept (least recently used first out), so memory stays bounded on
large scenes. Colour images are converted to gray (OpenCV's BGR -> gray weights), 16-bit
images are scaled to [0, 1], an alpha channel is dropped. A missing or unreadable image gives
one warning naming it, then ``None``.
"""

from __future__ import annotations

import logging
from collections import OrderedDict
from collections.abc import Iterator, Mapping
from pathlib import Path

import numpy as np

log = logging.getLogger(__name__)


def read_gray_float(path: str | Path) -> np.ndarray | None:
    """Read one image as float32 (H, W) grayscale in [0, 1]; None if missing or unreadable."""
    import cv2

    p = Path(path)
    if not p.is_file():
        return None
    data = np.fromfile(p, dtype=np.uint8)  # works with non-ASCII paths, unlike cv2.imread
    if data.size == 0:
        return None
    img = cv2.imdecode(data, cv2.IMREAD_UNCHANGED)
    if img is None:
        return None
    if img.ndim == 3:
        if img.shape[2] == 4:
            img = cv2.cvtColor(img, cv2.COLOR_BGRA2GRAY)
        elif img.shape[2] == 3:
            img = cv2.cvtColor(img, cv2.COLOR_BGR2GRAY)
        else:
            img = img[:, :, 0]
    scale = 65535.0 if img.dtype == np.uint16 else 255.0 if img.dtype == np.uint8 else 1.0
    return np.ascontiguousarray(img.astype(np.float32) / np.float32(scale))


class ImageLoader(Mapping):
    """Mapping image_id -> float32 (H, W) gray image in [0, 1], or None, loaded lazily.

    Args:
        image_dir: folder the database's image names are relative to.
        names: image_id -> file name (as stored in the database).
        max_cached: most images kept in memory at once (>= 1).
        expected_sizes: optional image_id -> (width, height) from the database's cameras;
            an image of another size gives a warning (keypoints may not belong to it) but is
            still returned.
    """

    def __init__(self, image_dir: str | Path, names: Mapping[int, str], *, max_cached: int = 8,
                 expected_sizes: Mapping[int, tuple[int, int]] | None = None) -> None:
        if max_cached < 1:
            raise ValueError(f"max_cached must be >= 1, got {max_cached}")
        self.image_dir = Path(image_dir)
        self.names = {int(k): str(v) for k, v in names.items()}
        self.max_cached = int(max_cached)
        self.expected_sizes = dict(expected_sizes or {})
        self._cache: OrderedDict[int, np.ndarray | None] = OrderedDict()
        self.missing: set[int] = set()
        self.loads = 0

    def path(self, image_id: int) -> Path:
        return self.image_dir / self.names[int(image_id)]

    def __getitem__(self, image_id: int) -> np.ndarray | None:
        image_id = int(image_id)
        if image_id not in self.names:
            raise KeyError(image_id)
        if image_id in self.missing:
            return None
        if image_id in self._cache:
            self._cache.move_to_end(image_id)
            return self._cache[image_id]
        img = read_gray_float(self.path(image_id))
        self.loads += 1
        if img is None:
            self.missing.add(image_id)
            log.warning("image %s is missing or unreadable; its keypoints are not refined",
                        self.path(image_id))
            return None
        size = self.expected_sizes.get(image_id)
        if size and tuple(size) != (img.shape[1], img.shape[0]):
            log.warning("image %s is %dx%d but its camera says %dx%d", self.path(image_id),
                        img.shape[1], img.shape[0], size[0], size[1])
        self._cache[image_id] = img
        while len(self._cache) > self.max_cached:
            self._cache.popitem(last=False)
        return img

    def check_all(self) -> list[int]:
        """Find the missing/unreadable images without decoding them all (existence and a
        header read); returns their ids (each warned once)."""
        import cv2

        bad = []
        for image_id in self.names:
            p = self.path(image_id)
            ok = p.is_file() and p.stat().st_size > 0
            if ok and cv2.haveImageReader(str(p)) is False:
                ok = False
            if not ok:
                bad.append(image_id)
                if image_id not in self.missing:
                    self.missing.add(image_id)
                    log.warning("image %s is missing or unreadable; its keypoints are not refined", p)
        return bad

    def __iter__(self) -> Iterator[int]:
        return iter(self.names)

    def __len__(self) -> int:
        return len(self.names)
