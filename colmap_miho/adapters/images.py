"""Image files: the one decoder (:func:`read_image`), gray conversions, sizes, and bounded lazy
loading of a database's images (:class:`ImageLoader`, least recently used out)."""

from __future__ import annotations

import logging
from collections import Counter, OrderedDict
from collections.abc import Callable, Iterator, Mapping
from pathlib import Path

import numpy as np

from ..errors import InvalidInput
from .paths import leaves_folder

log = logging.getLogger(__name__)


def read_image(path: str | Path, *, gray8: bool = False) -> np.ndarray | None:
    """Decode one image file (OpenCV; non-ASCII paths work), None if unusable: as stored (BGR(A), no
    EXIF rotation, as COLMAP reads it), or with ``gray8`` as ``cv2.IMREAD_GRAYSCALE``."""
    import cv2

    p = Path(path)
    if not p.is_file():
        return None
    data = np.fromfile(p, dtype=np.uint8)
    if data.size == 0:
        return None
    try:
        return cv2.imdecode(data, cv2.IMREAD_GRAYSCALE if gray8 else cv2.IMREAD_UNCHANGED)
    except cv2.error:  # e.g. a file of 2 GB or more: no decoder takes it
        return None


def read_gray_float(path: str | Path) -> np.ndarray | None:
    """One image as float32 ``(H, W)`` gray in [0, 1] (OpenCV weights, alpha dropped); None if unusable."""
    img = read_image(path)
    return None if img is None else _to_gray_float(img)


def _to_gray_float(img: np.ndarray) -> np.ndarray:
    import cv2

    if img.ndim == 3:
        if img.shape[2] == 4:
            img = cv2.cvtColor(img, cv2.COLOR_BGRA2GRAY)
        elif img.shape[2] == 3:
            img = cv2.cvtColor(img, cv2.COLOR_BGR2GRAY)
        else:
            img = img[:, :, 0]
    scale = 65535.0 if img.dtype == np.uint16 else 255.0 if img.dtype == np.uint8 else 1.0
    return np.ascontiguousarray(img.astype(np.float32) / np.float32(scale))


def read_gray_uint8(path: str | Path) -> np.ndarray:
    """One image as uint8 gray from the decoder (may differ from :func:`read_gray_float` by a level
    or two); FileNotFoundError naming it."""
    img = read_image(path, gray8=True)
    if img is None:
        raise FileNotFoundError(f"cannot read image {path}")
    return img


#: Bytes at the end of a JPEG / PNG file searched for its end marker (EOI / IEND); a file cut
#: short ends inside its compressed data, where the marker cannot occur.
_END_MARKER_WINDOW = 4096


def _truncated(data: np.ndarray) -> bool:
    """True for a JPEG without EOI or a PNG without IEND (OpenCV decodes a cut JPEG silently)."""
    head, tail = data[:8].tobytes(), data[-_END_MARKER_WINDOW:].tobytes()
    if head[:2] == b"\xff\xd8":
        return b"\xff\xd9" not in tail
    if head == b"\x89PNG\r\n\x1a\n":
        return b"IEND" not in tail
    return False


def image_problem(path: str | Path, expected_size: tuple[int, int] | None = None) -> str | None:
    """Why the image at ``path`` cannot be used (missing, empty, truncated, undecodable, not
    ``expected_size``), or None. Decodes the whole image."""
    return _checked_decode(path, expected_size)[1]


#: :func:`_checked_decode` reasons given before any decoding.
_NOT_DECODED = ("missing", "empty", "truncated (the file is cut short)")
#: Why an image whose name is absolute or climbs out with ``..`` is not read.
OUTSIDE = "named outside the image folder (an absolute name or one with '..')"



def _checked_decode(path: str | Path, expected_size: tuple[int, int] | None = None
                    ) -> tuple[np.ndarray | None, str | None]:
    """``(gray float32, None)`` when the file can be used, else ``(None, why)``, in one read."""
    import cv2

    p = Path(path)
    if not p.is_file():
        return None, "missing"
    data = np.fromfile(p, dtype=np.uint8)
    if data.size == 0:
        return None, "empty"
    if _truncated(data):
        return None, "truncated (the file is cut short)"
    img = cv2.imdecode(data, cv2.IMREAD_UNCHANGED)
    if img is None:
        return None, "not a readable image"
    if expected_size and tuple(expected_size) != (img.shape[1], img.shape[0]):
        return None, (f"{img.shape[1]}x{img.shape[0]} pixels but its camera in the database is "
                      f"{expected_size[0]}x{expected_size[1]}")
    return _to_gray_float(img), None


def image_size(path: str | Path) -> tuple[int, int]:
    """``(width, height)`` of an image file by decoding it; FileNotFoundError naming it."""
    img = read_image(path)
    if img is None:
        raise FileNotFoundError(f"cannot read image {path}")
    return int(img.shape[1]), int(img.shape[0])


def header_size(path: str | Path) -> tuple[int, int] | None:
    """``(width, height)`` as stored (no EXIF rotation), from the header where possible; None if unreadable."""
    import warnings

    try:
        from PIL import Image

        with warnings.catch_warnings():  # a header is no decompression bomb
            warnings.simplefilter("ignore", Image.DecompressionBombWarning)
            with Image.open(path) as im:
                return int(im.width), int(im.height)
    except Exception:  # noqa: BLE001 - not a format Pillow reads: the decoder decides
        import cv2

        # only a file whose first bytes OpenCV knows is decoded: a video or an archive among the
        # images was read whole into memory (2 GB and more: a cv2.error)
        if not cv2.haveImageReader(str(path)):
            return None
        img = read_image(path)
        return None if img is None else (int(img.shape[1]), int(img.shape[0]))


def folder_image_sizes(folder: str | Path) -> dict[str, tuple[int, int]]:
    """Every readable image under ``folder`` (all depths): COLMAP image name -> ``(width, height)``."""
    import os

    folder = Path(folder)
    out = {}
    for root, dirs, files in os.walk(folder):
        dirs.sort()
        for f in sorted(files):
            size = header_size(Path(root) / f)
            if size is not None:
                out[(Path(root) / f).relative_to(folder).as_posix()] = size
    return out


class ImageLoader(Mapping):
    """Lazy mapping image_id -> float32 ``(H, W)`` gray in [0, 1], or None (unusable or not its
    camera's size: one warning); ``max_cached`` / ``max_cached_bytes`` bound the LRU cache."""

    def __init__(self, image_dir: str | Path, names: Mapping[int, str], *,
                 max_cached: int | None = 8, max_cached_bytes: int | None = None,
                 expected_sizes: Mapping[int, tuple[int, int]] | None = None) -> None:
        if max_cached is not None and max_cached < 1:
            raise InvalidInput(f"max_cached must be >= 1, got {max_cached}")
        if max_cached_bytes is not None and max_cached_bytes < 0:
            raise InvalidInput(f"max_cached_bytes must be >= 0, got {max_cached_bytes}")
        self.image_dir = Path(image_dir)
        self.names = {int(k): str(v) for k, v in names.items()}
        self.max_cached = None if max_cached is None else int(max_cached)
        self.max_cached_bytes = None if max_cached_bytes is None else int(max_cached_bytes)
        self.expected_sizes = dict(expected_sizes or {})
        self._cache: OrderedDict[int, np.ndarray] = OrderedDict()
        self._cached_bytes = 0
        self.missing: set[int] = set()
        self.problems: dict[int, str] = {}  # image id -> why it is not used
        self.loads = 0
        self.decoded: Counter[int] = Counter()

    @property
    def decodes(self) -> int:
        """Image files decoded so far (the sum of :attr:`decoded`)."""
        return sum(self.decoded.values())

    @property
    def cached_bytes(self) -> int:
        """Bytes of the decoded images held now."""
        return self._cached_bytes

    def state(self) -> dict:
        """Keyword arguments that rebuild this loader (empty cache) in another process."""
        return dict(image_dir=self.image_dir, names=self.names, max_cached=self.max_cached,
                    max_cached_bytes=self.max_cached_bytes, expected_sizes=self.expected_sizes)

    def add_images(self, names: Mapping[int, str],
                   expected_sizes: Mapping[int, tuple[int, int]] | None = None) -> None:
        """Add (or rename) images; the cache is kept, so a worker serves task after task."""
        for k, v in names.items():
            k = int(k)
            if self.names.get(k, str(v)) != str(v):
                self._drop(k)
            self.names[k] = str(v)
        self.expected_sizes.update(expected_sizes or {})

    def path(self, image_id: int) -> Path:
        return self.image_dir / self.names[int(image_id)]

    def image_bytes(self, image_id: int) -> int | None:
        """Bytes the decoded image takes (from its expected size), None when unknown."""
        size = self.expected_sizes.get(int(image_id))
        return None if not size else 4 * int(size[0]) * int(size[1])

    def __getitem__(self, image_id: int) -> np.ndarray | None:
        image_id = int(image_id)
        if image_id not in self.names:
            raise KeyError(image_id)
        if image_id in self.missing:
            return None
        if leaves_folder(self.names[image_id]):
            self._skip(image_id, OUTSIDE)
            return None
        if image_id in self._cache:
            self._cache.move_to_end(image_id)
            return self._cache[image_id]
        img = read_gray_float(self.path(image_id))
        self.loads += 1
        if img is not None or self.path(image_id).is_file():
            self.decoded[image_id] += 1
        size = self.expected_sizes.get(image_id)
        if img is None:
            self._skip(image_id, "missing or unreadable")
            return None
        if size and tuple(size) != (img.shape[1], img.shape[0]):
            self._skip(image_id, f"{img.shape[1]}x{img.shape[0]} pixels but its camera in the "
                                 f"database is {size[0]}x{size[1]}")
            return None
        self._keep(image_id, img, evict=True)
        return img

    def _fits(self, extra_images: int, extra_bytes: int) -> bool:
        return ((self.max_cached is None or len(self._cache) + extra_images <= self.max_cached)
                and (self.max_cached_bytes is None
                     or self._cached_bytes + extra_bytes <= self.max_cached_bytes))

    def _keep(self, image_id: int, img: np.ndarray, *, evict: bool) -> None:
        """Cache ``img``, evicting the least recently used when ``evict``; never one over a bound."""
        if not (self.max_cached_bytes is None or img.nbytes <= self.max_cached_bytes):
            return
        if evict:
            while self._cache and not self._fits(1, img.nbytes):
                self._drop(next(iter(self._cache)))
        if self._fits(1, img.nbytes):
            self._cache[image_id] = img
            self._cached_bytes += img.nbytes

    def clear_cache(self) -> None:
        """Drop every cached image (the work moves to workers with loaders of their own)."""
        self._cache.clear()
        self._cached_bytes = 0

    def _drop(self, image_id: int) -> None:
        img = self._cache.pop(image_id, None)
        if img is not None:
            self._cached_bytes -= img.nbytes

    def _skip(self, image_id: int, why: str) -> None:
        if image_id not in self.missing:
            self.missing.add(image_id)
            self.problems[image_id] = why
            log.warning("image %s is %s; it is skipped (its keypoints are not refined)",
                        self.path(image_id), why)

    def check_all(self, inspect: Callable[[int, np.ndarray], None] | None = None) -> list[int]:
        """Ids of the images that cannot be used (:func:`image_problem`), decoding each once;
        good ones are cached while they fit, in id order. ``inspect`` sees each good image."""
        bad = []
        for image_id in self.names:
            why = self.problems.get(image_id)
            if why is None and leaves_folder(self.names[image_id]):
                why = OUTSIDE
            if why is None and image_id not in self._cache:
                img, why = _checked_decode(self.path(image_id), self.expected_sizes.get(image_id))
                if why not in _NOT_DECODED:
                    self.decoded[image_id] += 1
                if img is not None:
                    self._keep(image_id, img, evict=False)
                    if inspect is not None:
                        inspect(image_id, img)
            if why is not None:
                bad.append(image_id)
                self._skip(image_id, why)
        return bad

    def __iter__(self) -> Iterator[int]:
        return iter(self.names)

    def __len__(self) -> int:
        return len(self.names)
