"""Compiled (numba) kernels of :mod:`..sampling`: spread test, local draws and neighbour lists, a
batch's draws in one call, the local inlier fraction, and :class:`NearestGrid` (the compiled
neighbour search; numpy keeps scipy's k-d tree). Same decisions and bits as numpy's."""

from __future__ import annotations

from typing import Any

import numpy as np

from ...compiled import Kernels, jit, jit_helpers


def _spread_ok(spread_xy, sample, t2):
    B = sample.shape[0]
    sets = spread_xy.shape[1]
    ok = np.ones(B, dtype=np.bool_)
    for b in range(B):
        good = True
        for i in range(3):
            a = sample[b, i]
            for j in range(i + 1, 4):
                c = sample[b, j]
                for s in range(sets):
                    dx = spread_xy[0, s, a] - spread_xy[0, s, c]
                    dy = spread_xy[1, s, a] - spread_xy[1, s, c]
                    dx *= dx
                    dy *= dy
                    dx += dy
                    if not dx >= t2:
                        good = False
                        break
                if not good:
                    break
            if not good:
                break
        ok[b] = good
    return ok


def _draw_local(nb, keys, seeds, spread_x, spread_y, t2):
    return _draw_local_rows(nb, keys, seeds, spread_x, spread_y, t2)


def _draw_local_rows(nb, keys, seeds, spread_x, spread_y, t2):
    L, k = nb.shape
    sets = spread_x.shape[0]
    out = np.empty((L, 3), dtype=np.int64)
    free = np.empty(k, dtype=np.bool_)
    for r in range(L):
        for c in range(k):
            free[c] = nb[r, c] >= 0
        for j in range(3):
            best = -2.0
            at = 0
            for c in range(k):
                key = keys[j, r, c] if free[c] else -1.0
                if key > best:
                    best = key
                    at = c
            if not free[at]:
                out[r, j] = seeds[r]
                # nothing is free: later picks find nothing either
                for jj in range(j + 1, 3):
                    out[r, jj] = seeds[r]
                break
            pick = nb[r, at]
            out[r, j] = pick
            if j < 2:
                for c in range(k):
                    if not free[c]:
                        continue
                    q = nb[r, c]
                    for s in range(sets):
                        dx = spread_x[s, q] - spread_x[s, pick]
                        dy = spread_y[s, q] - spread_y[s, pick]
                        dx *= dx
                        dy *= dy
                        dx += dy
                        if not dx >= t2:
                            free[c] = False
                            break
    return out


def _far(sx, sy, a, b, t2) -> bool:
    """Matches ``a`` and ``b`` are at least ``sqrt(t2)`` apart in every spread set."""
    for s in range(sx.shape[0]):
        dx = sx[s, a] - sx[s, b]
        dy = sy[s, a] - sy[s, b]
        dx *= dx
        dy *= dy
        dx += dy
        if not dx >= t2:
            return False
    return True


def _push_nearest(best_d, best_j, filled, d, j) -> int:
    """Push candidate ``j`` at squared distance ``d`` into the sorted buffers; returns the new ``filled``."""
    q = best_d.shape[0]
    if filled == q and not (d < best_d[q - 1] or (d == best_d[q - 1] and j < best_j[q - 1])):
        return filled
    at = filled if filled < q else q - 1
    while at > 0 and (best_d[at - 1] > d or (best_d[at - 1] == d and best_j[at - 1] > j)):
        best_d[at] = best_d[at - 1]
        best_j[at] = best_j[at - 1]
        at -= 1
    best_d[at] = d
    best_j[at] = j
    return filled + 1 if filled < q else filled


def _neighbours(todo, cand, far, pos, feats, sx, sy, t2, k, q, pool, lists, listed):
    return _neighbour_rows(todo, cand, far, False, pos, feats, sx, sy, t2, k, q, pool, lists,
                           listed)


def _neighbour_rows(todo, cand, far, by_match, pos, feats, sx, sy, t2, k, q, pool, lists,
                    listed):
    """:func:`pool_neighbours`; ``by_match``: candidates read at each row's global index."""
    m = todo.shape[0]
    n = feats.shape[0]
    dims = feats.shape[1]
    nb = np.full((m, k), -1, dtype=np.int64)
    best_d = np.empty(q)
    best_j = np.empty(q, dtype=np.int64)
    # the exhaustive search's coordinates, one contiguous row per dimension, and the
    # squared distances of one match to every pool match (made on the first search)
    cols = np.empty((0, n))
    dist = np.empty(n)
    for r in range(m):
        a_all = pool[todo[r]]
        if listed[a_all]:
            kept = True
            for c in range(k):
                if pos[lists[a_all, c]] < 0:
                    kept = False
                    break
            if kept:
                for c in range(k):
                    nb[r, c] = pos[lists[a_all, c]]
                continue
        cnt = 0
        cr = a_all if by_match else r
        for c in range(cand.shape[1]):
            g = cand[cr, c]
            if g < 0 or not far[cr, c]:
                continue
            p = pos[g]
            if p < 0:
                continue
            nb[r, cnt] = p
            cnt += 1
            if cnt == k:
                break
        if cnt == k:
            _keep_list(nb, r, pool, lists, listed, a_all)
            continue
        # Too few left in the pool: the q nearest pool matches (the first is the match
        # itself), nearest first, ties by position.
        a = todo[r]
        if cols.shape[0] == 0:
            cols = np.ascontiguousarray(feats.T)
        # the distances dimension by dimension over contiguous rows (the sum of squares in
        # the order of the dimensions, as scipy's k-d tree sums it)
        dist[:] = 0.0
        for e in range(dims):
            fa = feats[a, e]
            col = cols[e]
            for j in range(n):
                t = col[j] - fa
                dist[j] += t * t
        filled = 0
        for j in range(n):
            d = dist[j]
            # in the order of j a later candidate loses ties: only a nearer one enters
            if filled == q and not d < best_d[q - 1]:
                continue
            filled = _push_nearest(best_d, best_j, filled, d, j)
        cnt = 0
        for c in range(1, filled):
            j = best_j[c]
            if _far(sx, sy, j, a, t2):
                nb[r, cnt] = j
                cnt += 1
                if cnt == k:
                    break
        for c in range(cnt, k):
            nb[r, c] = -1
        if cnt == k:
            _keep_list(nb, r, pool, lists, listed, a_all)
        else:
            listed[a_all] = False
    return nb


def _keep_list(nb, r, pool, lists, listed, a):
    """Keep row ``r`` of ``nb`` as match ``a``'s list (global indices) for later pools."""
    for c in range(nb.shape[1]):
        lists[a, c] = pool[nb[r, c]]
    listed[a] = True


def _nearest(feats, todo, q, x0, y0, cell, nx, ny, start, members):
    return _nearest_rows(feats, todo, q, x0, y0, cell, nx, ny, start, members)


def _nearest_rows(feats, todo, q, x0, y0, cell, nx, ny, start, members):
    m = todo.shape[0]
    dims = feats.shape[1]
    out = np.empty((m, q), dtype=np.int64)
    best_d = np.empty(q)
    best_j = np.empty(q, dtype=np.int64)
    for r in range(m):
        a = todo[r]
        ax, ay = feats[a, 0], feats[a, 1]
        cx = min(max(int((ax - x0) / cell), 0), nx - 1)
        cy = min(max(int((ay - y0) / cell), 0), ny - 1)
        filled = 0
        ring = 0
        while True:
            for gy in range(cy - ring, cy + ring + 1):
                if gy < 0 or gy >= ny:
                    continue
                edge = gy == cy - ring or gy == cy + ring
                step = 1 if edge else 2 * ring
                gx = cx - ring
                while gx <= cx + ring:
                    if 0 <= gx < nx:
                        c = gy * nx + gx
                        for t in range(start[c], start[c + 1]):
                            j = members[t]
                            d = 0.0
                            for e in range(dims):
                                v = feats[j, e] - feats[a, e]
                                d += v * v
                            filled = _push_nearest(best_d, best_j, filled, d, j)
                    gx += step if ring > 0 else 1
            if ring >= nx and ring >= ny:
                break
            if filled == q:
                # every point not searched yet lies outside the searched square of cells
                margin = min(ax - (x0 + (cx - ring) * cell), x0 + (cx + ring + 1) * cell - ax,
                             ay - (y0 + (cy - ring) * cell), y0 + (cy + ring + 1) * cell - ay)
                if margin > 0 and margin * margin > best_d[q - 1]:
                    break
            ring += 1
        for c in range(q):
            out[r, c] = best_j[c]
    return out


def _search_needed(need, pool, pos, nb, known, cand, far, cknown, by_match, sx_all, sy_all,
                   feats_all, x0, y0, cell, nx, ny, start, members, pool_feats, sx, sy, t2, k,
                   q, lists, listed):
    """Search the neighbour lists of the positions where ``need``, ascending, and mark them ``known``."""
    n = pool.shape[0]
    m = 0
    for p in range(n):
        if need[p]:
            m += 1
    if m:
        todo = np.empty(m, dtype=np.int64)
        m = 0
        for p in range(n):
            if need[p]:
                todo[m] = p
                m += 1
        if by_match:
            # the problem's candidates of the matches not searched yet (LocalCandidates.get)
            new = np.empty(m, dtype=np.int64)
            c_new = 0
            for i in range(m):
                g = pool[todo[i]]
                if not cknown[g]:
                    new[c_new] = g
                    c_new += 1
            qc = cand.shape[1]
            if c_new and qc:
                found = _nearest_rows(feats_all, new[:c_new], qc + 1, x0, y0, cell, nx, ny,
                                      start, members)
                for i in range(c_new):
                    g = new[i]
                    for c in range(qc):
                        j = found[i, c + 1]
                        cand[g, c] = j
                        far[g, c] = _far(sx_all, sy_all, j, g, t2)
            for i in range(c_new):
                cknown[new[i]] = True
        rows = _neighbour_rows(todo, cand, far, by_match, pos, pool_feats, sx, sy, t2, k, q,
                               pool, lists, listed)
        for i in range(m):
            for c in range(k):
                nb[todo[i], c] = rows[i, c]
            known[todo[i]] = True


def _need_of(probes, known, n, all_at_once):
    """``(n,)`` bool: the positions whose lists a draw or probe of ``probes`` needs searched."""
    fresh = True
    for p in range(n):
        if known[p]:
            fresh = False
            break
    need = np.zeros(n, dtype=np.bool_)
    if all_at_once and fresh:
        need[:] = True
    else:
        for i in range(probes.shape[0]):
            if not known[probes[i]]:
                need[probes[i]] = True
    return need


def _local_fraction(mask, rows, pool, pos, nb, known, all_at_once, cand, far, cknown,
                    by_match, sx_all, sy_all, feats_all, x0, y0, cell, nx, ny, start, members,
                    pool_feats, sx, sy, t2, k, q, lists, listed):
    n = pool.shape[0]
    m = rows.shape[0]
    probe = np.empty(m, dtype=np.int64)
    r = 0
    c = 0
    for p in range(n):  # the inliers' positions at the chosen ranks (ascending)
        if mask[p]:
            while r < m and rows[r] == c:
                probe[r] = p
                r += 1
            c += 1
    need = _need_of(probe, known, n, all_at_once)
    _search_needed(need, pool, pos, nb, known, cand, far, cknown, by_match, sx_all, sy_all,
                   feats_all, x0, y0, cell, nx, ny, start, members, pool_feats, sx, sy, t2, k,
                   q, lists, listed)
    valid = 0
    inside = 0
    for i in range(m):
        for j in range(k):
            v = nb[probe[i], j]
            if v >= 0:
                valid += 1
                if mask[v]:
                    inside += 1
    return valid, inside


def _draw_batch(seeds, others, local, keys, pool, pos, nb, known, all_at_once, cand, far,
                cknown, by_match, sx_all, sy_all, feats_all, x0, y0, cell, nx, ny, start,
                members, pool_feats, sx, sy, t2, k, q, lists, listed):
    n = pool.shape[0]
    size = seeds.shape[0]
    L = local.shape[0]
    if L:
        # the seeds' neighbour lists not searched yet (all of a small pool at its first draw)
        probes = np.empty(L, dtype=np.int64)
        for i in range(L):
            probes[i] = seeds[local[i]]
        need = _need_of(probes, known, n, all_at_once)
        _search_needed(need, pool, pos, nb, known, cand, far, cknown, by_match, sx_all, sy_all,
                       feats_all, x0, y0, cell, nx, ny, start, members, pool_feats, sx, sy, t2,
                       k, q, lists, listed)
        lnb = np.empty((L, k), dtype=np.int64)
        lseeds = np.empty(L, dtype=np.int64)
        for i in range(L):
            lseeds[i] = seeds[local[i]]
            for c in range(k):
                lnb[i, c] = nb[lseeds[i], c]
        picked = _draw_local_rows(lnb, keys, lseeds, sx, sy, t2)
        for i in range(L):
            for j in range(3):
                others[local[i], j] = picked[i, j]
    out = np.empty((size, 4), dtype=np.int64)
    for b in range(size):
        out[b, 0] = pool[seeds[b]]
        for j in range(3):
            out[b, j + 1] = pool[others[b, j]]
    return out


def _jit_all() -> dict[str, Any]:
    jit_helpers(globals(), (_far, _push_nearest, _keep_list, _draw_local_rows, _neighbour_rows, _nearest_rows,
                            _search_needed, _need_of))
    j = jit()
    return {f.__name__: j(f) for f in (_spread_ok, _draw_local, _neighbours, _nearest, _draw_batch, _local_fraction)}


#: the jitted kernels by name (compiled, or loaded from numba's cache, on first use).
KERNELS = Kernels(_jit_all)


def spread_ok(spread_xy: np.ndarray, sample: np.ndarray, t2: float) -> np.ndarray:
    """``(B,)`` bool: each sample's 4 matches are pairwise at least ``sqrt(t2)`` px apart in every spread set."""
    return KERNELS()["_spread_ok"](spread_xy, sample, float(t2))


def draw_local(nb: np.ndarray, keys: np.ndarray, seeds: np.ndarray, spread_x: np.ndarray,
               spread_y: np.ndarray, t2: float) -> np.ndarray:
    """``(L, 3)`` pool positions drawn one by one among each seed's neighbours ``nb`` by the largest
    key, each leaving free only those far enough from it; the seed where none is free."""
    return KERNELS()["_draw_local"](nb, keys, seeds, spread_x, spread_y, float(t2))


def draw_batch(seeds: np.ndarray, others: np.ndarray, local: np.ndarray, keys: np.ndarray,
               pool: np.ndarray, pos: np.ndarray, nb: np.ndarray, known: np.ndarray,
               all_at_once: bool, cand: np.ndarray, far: np.ndarray, cknown: np.ndarray,
               grid: NearestGrid | None, sx_all: np.ndarray, sy_all: np.ndarray,
               pool_feats: np.ndarray, sx: np.ndarray, sy: np.ndarray, t2: float, k: int,
               q: int, lists: np.ndarray, listed: np.ndarray) -> np.ndarray:
    """``(B, 4)`` global indices of one batch of local sampling, the same samples as
    ``Sampler.draw``; unknown neighbour lists are searched first and updated in place."""
    if grid is None:
        empty = np.empty(0, dtype=np.int64)
        x0 = y0 = cell = 0.0
        nx = ny = 0
        feats_all, start, members = np.empty((0, 4)), empty, empty
        cand, far = np.empty((0, 0), dtype=np.int64), np.empty((0, 0), dtype=np.bool_)
    else:
        x0, y0, cell, nx, ny = grid.x0, grid.y0, grid.cell, grid.nx, grid.ny
        feats_all, start, members = grid.feats, grid.start, grid.members
    return KERNELS()["_draw_batch"](
        seeds, others, local, keys, pool, pos, nb, known, bool(all_at_once), cand, far,
        cknown, grid is not None, sx_all, sy_all, feats_all, float(x0), float(y0), float(cell),
        int(nx), int(ny), start, members, pool_feats, sx, sy, float(t2), int(k), int(q), lists,
        listed)


def local_fraction(mask: np.ndarray, rows: np.ndarray, pool: np.ndarray, pos: np.ndarray,
                   nb: np.ndarray, known: np.ndarray, all_at_once: bool, cand: np.ndarray,
                   far: np.ndarray, cknown: np.ndarray, grid: NearestGrid | None,
                   sx_all: np.ndarray, sy_all: np.ndarray, pool_feats: np.ndarray,
                   sx: np.ndarray, sy: np.ndarray, t2: float, k: int, q: int,
                   lists: np.ndarray, listed: np.ndarray) -> tuple[int, int]:
    """``(valid, inside)``: how many neighbours the inliers at ``rows`` have and how many are
    inliers; unknown lists are searched first."""
    grid_args = _grid_args(grid, cand, far)
    return KERNELS()["_local_fraction"](
        mask, rows, pool, pos, nb, known, bool(all_at_once), *grid_args[:2], cknown,
        grid is not None, sx_all, sy_all, *grid_args[2:], pool_feats, sx, sy, float(t2),
        int(k), int(q), lists, listed)


def _grid_args(grid: NearestGrid | None, cand: np.ndarray, far: np.ndarray) -> tuple:
    """The compiled search's arguments for ``grid`` (empty for a problem without candidates)."""
    if grid is None:
        empty = np.empty(0, dtype=np.int64)
        return (np.empty((0, 0), dtype=np.int64), np.empty((0, 0), dtype=np.bool_),
                np.empty((0, 4)), 0.0, 0.0, 0.0, 0, 0, empty, empty)
    return (cand, far, grid.feats, float(grid.x0), float(grid.y0), float(grid.cell),
            int(grid.nx), int(grid.ny), grid.start, grid.members)


def pool_neighbours(todo: np.ndarray, cand: np.ndarray, far: np.ndarray, pos: np.ndarray,
                    feats: np.ndarray, spread_x: np.ndarray, spread_y: np.ndarray, t2: float,
                    k: int, q: int, pool: np.ndarray, lists: np.ndarray,
                    listed: np.ndarray) -> np.ndarray:
    """``(m, k)`` nearest pool matches at least ``sqrt(t2)`` from each of ``todo`` in every spread
    set (-1 padded), from the candidates or by exhaustive search; ``lists``/``listed`` reuse the
    lists of earlier pools that contain this one (the caller clears them otherwise)."""
    return KERNELS()["_neighbours"](todo, cand, far, pos, feats, spread_x, spread_y,
                                      float(t2), int(k), int(q), pool, lists, listed)


class NearestGrid:
    """Exact ``q`` nearest neighbours of ``feats`` ``(N, dims)`` among themselves (summed as scipy's
    k-d tree), by a grid over the first two coordinates searched ring by ring; ties by index."""

    PER_CELL = 4
    MAX_CELLS = 1024

    def __init__(self, feats: np.ndarray) -> None:
        self.feats = np.ascontiguousarray(feats, dtype=np.float64)
        xy = self.feats[:, :2]
        lo, hi = xy.min(axis=0), xy.max(axis=0)
        span = np.maximum(hi - lo, 1e-9)
        # at most MAX_CELLS cells a side: every point lies in the cell of its coordinates
        self.cell = float(max(np.sqrt(span[0] * span[1] * self.PER_CELL / len(xy)),
                              span.max() / self.MAX_CELLS, 1e-9))
        self.nx, self.ny = (int(v) for v in span // self.cell + 1)
        self.x0, self.y0 = float(lo[0]), float(lo[1])
        gx = np.clip(((xy[:, 0] - self.x0) / self.cell).astype(np.int64), 0, self.nx - 1)
        gy = np.clip(((xy[:, 1] - self.y0) / self.cell).astype(np.int64), 0, self.ny - 1)
        cell_of = gy * self.nx + gx
        self.members = np.argsort(cell_of, kind="stable")
        self.start = np.searchsorted(cell_of[self.members], np.arange(self.nx * self.ny + 1))

    def query(self, todo: np.ndarray, q: int) -> np.ndarray:
        """``(len(todo), q)`` int64 nearest points of each ``todo``, nearest (itself) first."""
        return KERNELS()["_nearest"](self.feats, np.asarray(todo, np.int64), int(q), self.x0,
                                       self.y0, self.cell, self.nx, self.ny, self.start,
                                       self.members)
