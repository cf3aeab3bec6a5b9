"""Minimal samples of a RANSAC run (App. A.3): uniform or local draws whose points are spread at
least t_l apart (plain nearest neighbours would mostly fail the spread test), and the bound."""

from __future__ import annotations

import functools
from typing import TYPE_CHECKING

import numpy as np

from ..enums import Sampling
from ..geometry import draws_for_confidence
from .compiled import sampling as kernels
from .config import FilterConfig
from .homography import triangle_orientations
from .problem import Problem

if TYPE_CHECKING:
    from scipy.spatial import cKDTree

_PAIRS = ((0, 1), (0, 2), (0, 3), (1, 2), (1, 3), (2, 3))  # the 6 point pairs of a sample


def apart_sets(dx: np.ndarray, dy: np.ndarray, t2: float) -> np.ndarray:
    """``(...)`` bool: ``dx * dx + dy * dy >= t2`` in every set, written out over the tiny sets axis
    (reductions over it cost more than the arithmetic); overwrites ``dx``, ``dy``."""
    dx *= dx
    dy *= dy
    dx += dy
    ok = dx[0] >= t2
    for k in range(1, dx.shape[0]):
        ok &= dx[k] >= t2
    return ok


def spread_ok(problem: Problem, sample: np.ndarray, t_l: float) -> np.ndarray:
    """``(B,)`` bool: each sample's 4 points are pairwise at least ``t_l`` px apart in every spread set."""
    assert problem.spread_xy is not None, "sampling runs on the numpy problem"
    px, py = np.take(problem.spread_xy, sample.T, axis=2)  # (sets, 4, B) each
    ok = np.ones(len(sample), dtype=bool)
    for i, j in _PAIRS:
        ok &= apart_sets(px[:, i] - px[:, j], py[:, i] - py[:, j], t_l**2)
    return ok


def checked_samples(problem: Problem, sample: np.ndarray, cfg: FilterConfig,
                    ok: np.ndarray | None = None) -> np.ndarray:
    """The samples ``(B, 4)`` that pass the spread test and, for MOP*, the reflection check."""
    ok = spread_ok(problem, sample, cfg.t_l) if ok is None else ok.copy()
    if cfg.reflection_check and ok.any():
        o1 = triangle_orientations(problem.x1[sample])
        o2 = triangle_orientations(problem.x2[sample])
        ok &= np.all(o1 * o2 > 0, axis=1)
    return sample[ok]


def required_iters(w: float, w_loc: float, local_fraction: float, p: float) -> float:
    """Adaptive bound: draws for confidence ``p`` that one sample is all inliers (``inf`` if none can be)."""
    return draws_for_confidence(local_fraction * w * w_loc**3 + (1.0 - local_fraction) * w**4, p)


def _unknown(idx: np.ndarray, known: np.ndarray) -> np.ndarray:
    """Sorted distinct entries of ``idx`` that are not ``known`` (cheaper than ``np.unique``)."""
    need = np.zeros(known.shape[0], dtype=bool)
    need[idx] = True
    need &= ~known
    return np.flatnonzero(need)


@functools.lru_cache(maxsize=4096)
def _probe_rows(n: int) -> np.ndarray:
    """Up to 256 rows evenly spread over ``n``, cached per ``n`` (read-only)."""
    rows = np.linspace(0, n - 1, min(n, 256)).astype(np.int64)
    rows.flags.writeable = False
    return rows


class LocalCandidates:
    """Candidate neighbours for local sampling, shared by a problem's MOP rounds: each match's ``4
    k`` nearest in ``(x1, x2)`` and whether each is far enough (independent of the pool, so computed
    once)."""

    SEARCH = 4

    def __init__(self, problem: Problem, cfg: FilterConfig, compiled: bool = False) -> None:
        """``compiled``: search a :class:`.compiled.sampling.NearestGrid` instead of scipy's k-d tree."""
        n = len(problem.x1)
        self.compiled = compiled
        assert problem.spread_xy is not None, "local sampling runs on the numpy problem"
        self._sx, self._sy = problem.spread_xy  # (sets, N) each
        self._t2 = cfg.t_l**2
        self.feats = np.concatenate([problem.x1, problem.x2], axis=1)
        # built on the first search
        self._tree: cKDTree | None = None
        self._grid: kernels.NearestGrid | None = None
        self._q = max(min(n, self.SEARCH * cfg.local_neighbours + 1) - 1, 0)
        self._cand = np.full((n, self._q), -1, dtype=np.int64)
        self._far = np.zeros((n, self._q), dtype=bool)
        self._known = np.zeros(n, dtype=bool)
        # The compiled search's full neighbour lists (k global indices a match), kept for
        # the later pools of the rounds (:meth:`lists_for`).
        self._lists = np.full((n, cfg.local_neighbours), -1, dtype=np.int64)
        self._listed = np.zeros(n, dtype=bool)
        self._in_last_pool: np.ndarray | None = None

    def lists_for(self, pool: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``(lists, listed)`` for a search of ``pool``, kept while each pool is a subset of the last."""
        if self._in_last_pool is not None and not self._in_last_pool[pool].all():
            self._listed[:] = False
        self._in_last_pool = np.zeros(len(self._known), dtype=bool)
        self._in_last_pool[pool] = True
        return self._lists, self._listed

    def grid(self) -> kernels.NearestGrid:
        """The compiled search's grid over the problem's ``(x1, x2)`` (built on first use)."""
        if self._grid is None:
            self._grid = kernels.NearestGrid(self.feats)
        return self._grid

    def far(self, a: np.ndarray, b: np.ndarray) -> np.ndarray:
        """Whether matches ``a`` and ``b`` (broadcast) are >= t_l apart in every spread set."""
        sx, sy = self._sx, self._sy
        return apart_sets(np.take(sx, a, axis=1) - np.take(sx, b, axis=1),
                           np.take(sy, a, axis=1) - np.take(sy, b, axis=1), self._t2)

    def get(self, idx: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``(cand, far)``, each ``(len(idx), 4k)``, searched on first request."""
        todo = _unknown(idx, self._known)
        if len(todo) and self._q:
            if self.compiled:
                cand = self.grid().query(todo, self._q + 1)[:, 1:]
            else:
                if self._tree is None:
                    from scipy.spatial import cKDTree

                    self._tree = cKDTree(self.feats)
                cand = self._tree.query(self.feats[todo], k=self._q + 1)[1][:, 1:]
            self._cand[todo] = cand
            self._far[todo] = self.far(cand, todo[:, None])
        self._known[todo] = True
        return self._cand[idx], self._far[idx]


class Sampler:
    """Minimal samples over the pool: uniform, or a ``local_fraction`` drawn one by one among a
    seed's nearest pool matches that are far enough from those drawn."""

    #: Pools of at most this many matches have every match's neighbours searched at the first
    #: call.
    ALL_AT_ONCE = 256

    def __init__(self, problem: Problem, pool: np.ndarray, cfg: FilterConfig,
                 candidates: LocalCandidates | None = None, compiled: bool = False) -> None:
        n = len(pool)
        self.compiled = compiled  # local draws by the compiled kernel (.compiled.sampling.draw_local)
        self.pool = pool
        self.k = cfg.local_neighbours
        self.local = cfg.sampling == Sampling.LOCAL and n > cfg.local_neighbours + 1
        self.fraction = cfg.local_fraction if self.local else 0.0
        self._cands: LocalCandidates | None = None
        if self.local:
            self._cands = (candidates if candidates is not None
                           else LocalCandidates(problem, cfg, compiled=compiled))
            self._pos = np.full(len(problem.x1), -1, dtype=np.int64)  # global -> pool position
            self._pos[pool] = np.arange(n)
        self._pool_tree: cKDTree | None = None
        self._feats: np.ndarray | None = None  # (n, 4) the pool's (x1, x2), compiled search
        # the candidates' kept lists for this pool (compiled search; LocalCandidates.lists_for)
        self._lists: tuple[np.ndarray, np.ndarray] | None = None
        self._nb = np.full((n, self.k), -1, dtype=np.int64)  # -1 = no such neighbour
        # (sets, n) x and y of the spread sets of the pool, for the local draws
        self._spread_x: np.ndarray | None = None
        self._spread_y: np.ndarray | None = None
        if self.local:
            assert problem.spread_xy is not None, "local sampling runs on the numpy problem"
            self._spread_x, self._spread_y = np.take(problem.spread_xy, pool, axis=2)
        self._t2 = cfg.t_l**2
        self._known = np.zeros(n, dtype=bool)

    def neighbours(self, pos: np.ndarray) -> np.ndarray:
        """``(len(pos), k)`` nearest far-enough pool positions of each of ``pos``, -1 padded."""
        if len(self.pool) <= self.ALL_AT_ONCE and not self._known.any():
            # A small pool: a round's draws reach nearly every match, so all are searched in
            # one call (each match's neighbours do not depend on which others are searched).
            todo = np.arange(len(self.pool))
        else:
            todo = _unknown(pos, self._known)
        if len(todo) and self.compiled:
            assert self._cands is not None, "neighbours are searched with local sampling only"
            assert self._spread_x is not None and self._spread_y is not None
            if self._feats is None:
                self._feats = np.ascontiguousarray(self._cands.feats[self.pool])
            q = min(len(self.pool), LocalCandidates.SEARCH * self.k + 1)
            if len(self._cands.feats) <= self.ALL_AT_ONCE:
                # A small problem: the kernel's exhaustive search of the pool costs less than
                # the problem-wide candidates, and finds the same neighbours (the candidates'
                # first k in the pool are the pool's nearest; equidistant ones are the same
                # point, so their order does not change any draw's coordinates).
                cand = np.full((len(todo), 0), -1, dtype=np.int64)
                far = np.zeros((len(todo), 0), dtype=bool)
            else:
                cand, far = self._cands.get(self.pool[todo])
            if self._lists is None:
                self._lists = self._cands.lists_for(self.pool)
            self._nb[todo] = kernels.pool_neighbours(todo, cand, far, self._pos, self._feats,
                                                     self._spread_x, self._spread_y, self._t2,
                                                     self.k, q, self.pool, *self._lists)
            self._known[todo] = True
        elif len(todo):
            assert self._cands is not None, "neighbours are searched with local sampling only"
            cand, far = self._cands.get(self.pool[todo])
            cand_pos = np.where(cand >= 0, self._pos[np.maximum(cand, 0)], -1)
            nb = self._first_k(cand_pos, far & (cand_pos >= 0))
            # Where earlier rounds removed too many of the candidates, search the pool itself.
            short = np.flatnonzero((nb < 0).any(axis=1))
            if len(short):
                nb[short] = self._first_k(*self._pool_candidates(todo[short]))
            self._nb[todo] = nb
            self._known[todo] = True
        return self._nb[pos]

    def _first_k(self, cand: np.ndarray, ok: np.ndarray) -> np.ndarray:
        order = np.argsort(~ok, axis=1, kind="stable")[:, : self.k]
        nb = np.take_along_axis(cand, order, axis=1)
        nb[~np.take_along_axis(ok, order, axis=1)] = -1
        if nb.shape[1] < self.k:
            nb = np.pad(nb, ((0, 0), (0, self.k - nb.shape[1])), constant_values=-1)
        return nb

    def _pool_candidates(self, pos: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Nearest pool matches of ``pos`` and whether each is far enough, from a k-d tree."""
        cands = self._cands
        assert cands is not None, "neighbours are searched with local sampling only"
        if self._pool_tree is None:
            from scipy.spatial import cKDTree

            self._pool_tree = cKDTree(cands.feats[self.pool])
        q = min(len(self.pool), LocalCandidates.SEARCH * self.k + 1)
        cand = self._pool_tree.query(cands.feats[self.pool[pos]], k=q)[1][:, 1:]
        return cand, cands.far(self.pool[cand], self.pool[pos][:, None])

    def local_inlier_fraction(self, mask: np.ndarray | None, count: int) -> float:
        """Share of the best model's inliers among the neighbours of up to 256 of them."""
        if self._cands is None or mask is None or count <= 0:
            return 0.0
        if self.compiled:
            return self._local_fraction_compiled(mask, count)
        inl = np.flatnonzero(mask)
        probe = inl[_probe_rows(len(inl))]
        nb = self.neighbours(probe)
        valid = nb >= 0
        if not valid.any():
            return 0.0
        return float(mask[nb[valid]].mean())

    def _local_fraction_compiled(self, mask: np.ndarray, count: int) -> float:
        """:meth:`local_inlier_fraction` in one compiled call (the same result)."""
        valid, inside = kernels.local_fraction(mask, _probe_rows(count), *self._search_args())
        return inside / valid if valid else 0.0

    def _search_args(self) -> tuple:
        """The arguments :func:`.compiled.sampling.draw_batch` and ``local_fraction`` share."""
        cands = self._cands
        assert cands is not None and self._spread_x is not None and self._spread_y is not None
        if self._feats is None:
            self._feats = np.ascontiguousarray(cands.feats[self.pool])
        if self._lists is None:
            self._lists = cands.lists_for(self.pool)
        # the problem's candidates; a small problem searches the pool alone (as neighbours)
        grid = cands.grid() if len(cands.feats) > self.ALL_AT_ONCE else None
        q = min(len(self.pool), LocalCandidates.SEARCH * self.k + 1)
        return (self.pool, self._pos, self._nb, self._known, len(self.pool) <= self.ALL_AT_ONCE,
                cands._cand, cands._far, cands._known, grid, cands._sx, cands._sy, self._feats,
                self._spread_x, self._spread_y, self._t2, self.k, q, *self._lists)

    def _draw_local(self, rng: np.random.Generator, seeds: np.ndarray) -> np.ndarray:
        """``(L, 3)`` pool positions drawn among the seeds' neighbours, pairwise >= t_l apart."""
        assert self._spread_x is not None and self._spread_y is not None, \
            "local draws need local sampling"
        nb = self.neighbours(seeds)
        if self.compiled:
            # The same keys as the three rng.random calls below, drawn at once.
            keys = rng.random((3,) + nb.shape)
            return kernels.draw_local(nb, keys, seeds, self._spread_x, self._spread_y, self._t2)
        free = nb >= 0  # (L, k) candidates still allowed
        safe = np.maximum(nb, 0)
        # x and y apart, sets first, as apart_sets takes them.
        px = np.take(self._spread_x, safe, axis=1)  # (sets, L, k)
        py = np.take(self._spread_y, safe, axis=1)
        sets = px.shape[0]
        row_start = np.arange(len(seeds)) * nb.shape[1]  # flat index of each row's first
        out = np.empty((len(seeds), 3), dtype=np.int64)
        for j in range(3):
            key = np.where(free, rng.random(free.shape), -1.0)
            at = row_start + np.argmax(key, axis=1)  # flat index of each row's pick
            found = free.reshape(-1).take(at)  # key >= 0 there: a free candidate's key
            out[:, j] = np.where(found, nb.reshape(-1).take(at), seeds)
            if j < 2:  # what the last pick leaves free is not used
                free &= apart_sets(px - px.reshape(sets, -1).take(at, axis=1)[:, :, None],
                                    py - py.reshape(sets, -1).take(at, axis=1)[:, :, None],
                                    self._t2)
        return out

    def draw(self, rng: np.random.Generator, size: int) -> np.ndarray:
        """``(size, 4)`` global match indices, seed match first."""
        n = len(self.pool)
        seeds = rng.integers(0, n, size)
        others = rng.integers(0, n, (size, 3))
        if self.local:
            is_local = np.flatnonzero(rng.random(size) < self.fraction)
            if len(is_local) and self.compiled:
                # the same keys as _draw_local's three rng.random calls, drawn at once
                keys = rng.random((3, len(is_local), self.k))
                return self._draw_compiled(seeds, others, is_local, keys)
            if len(is_local):
                others[is_local] = self._draw_local(rng, seeds[is_local])
        return self.pool[np.concatenate([seeds[:, None], others], axis=1)]

    def _draw_compiled(self, seeds: np.ndarray, others: np.ndarray, local: np.ndarray,
                       keys: np.ndarray) -> np.ndarray:
        """:meth:`draw`'s samples in one compiled call (searches and draws as the numpy path)."""
        return kernels.draw_batch(seeds, others, local, keys, *self._search_args())
