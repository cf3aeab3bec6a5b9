"""The data of one RANSAC problem of MOP (App. A.3, B): the point sets of its halves (MOP one, MiHo
two via the midpoint) and a stack of hypotheses."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from .homography import array_module


@dataclass(frozen=True)
class Problem:
    """Point sets of one filtering problem, ``(N, 2)`` float64 pixels: per half ``src``/``dst``, the
    ``spread`` sets, ``x1``/``x2``, and ``error_scale`` (2 for MiHo with full-match thresholds)."""

    src: tuple[np.ndarray, ...]
    dst: tuple[np.ndarray, ...]
    spread: tuple[np.ndarray, ...]
    x1: np.ndarray
    x2: np.ndarray
    error_scale: float = 1.0
    # Stacked copies (N, halves or sets, 2) so that a batch needs one gather, not a loop.
    src_all: np.ndarray = field(init=False, repr=False)
    dst_all: np.ndarray = field(init=False, repr=False)
    spread_all: np.ndarray = field(init=False, repr=False)
    # The spread sets by coordinate, (2, sets, N) (numpy only, None for torch): a gather
    # along the last axis (np.take) costs several times less than one of 2-6 float rows.
    spread_xy: np.ndarray | None = field(init=False, repr=False)

    def __post_init__(self) -> None:
        xp = array_module(self.x1)
        object.__setattr__(self, "src_all", xp.stack(self.src, axis=1))
        object.__setattr__(self, "dst_all", xp.stack(self.dst, axis=1))
        object.__setattr__(self, "spread_all", xp.stack(self.spread, axis=1))
        object.__setattr__(self, "spread_xy", np.ascontiguousarray(
            self.spread_all.transpose(2, 1, 0)) if xp is np else None)

    @property
    def num_halves(self) -> int:
        return len(self.src)


@dataclass
class Hypotheses:
    """``K`` hypotheses: ``H``, adjugates ``Hinv`` ``(K, halves, 3, 3)``, signs ``(K, halves)`` and
    samples ``(K, 4)``."""

    H: np.ndarray
    Hinv: np.ndarray
    sign: np.ndarray
    sign_inv: np.ndarray
    sample: np.ndarray

    def __len__(self) -> int:
        return self.H.shape[0]

    def take(self, idx) -> Hypotheses:
        idx = np.atleast_1d(np.asarray(idx))
        return Hypotheses(self.H[idx], self.Hinv[idx], self.sign[idx], self.sign_inv[idx],
                          self.sample[idx])

    def row(self, k: int) -> Hypotheses:
        """Hypothesis ``k`` alone, as views (the stacks are never written in place)."""
        return Hypotheses(self.H[k:k + 1], self.Hinv[k:k + 1], self.sign[k:k + 1],
                          self.sign_inv[k:k + 1], self.sample[k:k + 1])

    @staticmethod
    def concat(items: list[Hypotheses]) -> Hypotheses:
        items = [h for h in items if len(h)]
        if not items:
            return Hypotheses.empty(1)
        return Hypotheses(*(np.concatenate([getattr(h, f) for h in items]) for f in
                            ("H", "Hinv", "sign", "sign_inv", "sample")))

    @staticmethod
    def empty(halves: int) -> Hypotheses:
        return Hypotheses(np.zeros((0, halves, 3, 3)), np.zeros((0, halves, 3, 3)),
                          np.zeros((0, halves)), np.zeros((0, halves)),
                          np.zeros((0, 4), dtype=np.int64))
