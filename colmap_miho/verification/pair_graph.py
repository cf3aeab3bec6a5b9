"""Pair check core: find the image pairs that the rest of the pair graph contradicts.

A wrong pair (two windows of one facade, two sides of a symmetric building) holds matches
that agree with one homography or epipolar geometry, so no filter that looks at the pair alone
can reject them. The other pairs can. In a triangle of the pair graph (images i, j, k matched
pairwise) each pair's matches are carried into the third image by the other two pairs
(:func:`triangle_transfer`): through their matches (the scene point's track must reach one
keypoint of the third image, not two copies of a repeated structure), or, where they do not
match the point, by epipolar transfer (the fundamental matrices are fitted here from the
matches: no intrinsics needed). With three correct pairs the transfers land on the right
keypoints; one wrong pair sends them all astray.

Each transfer that fails blames the two pairs that carried it, each that works supports them
(:func:`carrier_votes`); the pairs with the most blame are removed first, and each removal takes
its triangles' votes off the other pairs, so the correct pairs that shared triangles with a
wrong one recover (:func:`check_pairs`). Votes are weighted by trust (:func:`settle_trust`), so
wrong pairs that agree with each other stop supporting each other, and a removed pair whose
tracks the kept, trusted pairs confirm in several triangles is kept after all
(:func:`confirming_triangles`). A pair without counted transfers is kept (there is no
evidence against it), and a pair is only removed while one of its triangles is still present:
its two images stay joined through the triangle's third image, so no removal splits the pair
graph. The work grows with the triangles present (each pair intersects its two images'
neighbour sets), not with the cube of the number of images.

Pure: arrays in, a small result out; no I/O.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping
from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

from ..geometry import fit_fundamental, spread_rows, transfer
from ..types import Pair
from .config import PairCheckConfig

#: Grid cells per image side for :attr:`PairVerdict.coverage`.
COVERAGE_GRID = 8


@dataclass(frozen=True, kw_only=True)
class PairVerdict:
    """What the pair check found for one pair.

    Attributes:
        matches: the pair's matches.
        strength: ``matches`` over the median match count of the pairs of its two images
            (both images' pairs pooled, this one included); 1 = a typical pair of theirs.
        coverage: share of the 8 x 8 grid cells over each image's keypoint extent that hold
            one of the pair's matches, the smaller of the two images, in [0, 1].
        triangles: triangles of the pair graph that contain the pair.
        triangles_broken: of those, the ones where every pair's transfers mostly fail.
        blame / support: votes of its triangles (see :func:`carrier_votes`), before any
            removal.
        transfers_closed / transfers_broken: the pair's own matches carried into the third
            images of its triangles: the tracks it makes that stay consistent / that join two
            places of one image (track conflicts).
        confirmed_triangles: triangles, among those whose two other pairs are kept and
            trusted after the removals, in which the pair's tracks stay consistent (see
            :func:`confirming_triangles`).
        wrong: removed (``mode = "remove"``) or flagged (``"flag"``).
        reason: why, in words ("" for a pair kept).
    """

    matches: int
    strength: float
    coverage: float
    triangles: int
    triangles_broken: int
    blame: int
    support: int
    transfers_closed: int
    transfers_broken: int
    confirmed_triangles: int
    wrong: bool
    reason: str

    def to_dict(self) -> dict:
        """JSON-ready values (floats rounded to 3 decimals)."""
        out = dataclasses.asdict(self)
        out["strength"], out["coverage"] = round(self.strength, 3), round(self.coverage, 3)
        return out


@dataclass(frozen=True, kw_only=True)
class PairCheckResult:
    """The pair check's verdicts.

    Attributes:
        verdicts: pair -> :class:`PairVerdict`, every input pair (keys image_id1 < image_id2).
        wrong: the pairs found wrong, in the order they were taken out.
        triangles / triangles_decided / triangles_broken: of the whole pair graph, before any
            removal.
    """

    verdicts: dict[Pair, PairVerdict]
    wrong: list[Pair]
    triangles: int
    triangles_decided: int
    triangles_broken: int


class _Lookup:
    """Keypoint of one image -> the keypoint of the other image it is matched to (the first
    match of a keypoint matched several times)."""

    def __init__(self, src: np.ndarray, dst: np.ndarray) -> None:
        order = np.argsort(src, kind="stable")
        keys, vals = src[order], dst[order]
        first = np.ones(len(keys), bool)
        first[1:] = keys[1:] != keys[:-1]
        self.keys, self.vals = keys[first], vals[first]

    def __call__(self, query: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``(values (Q,), found bool (Q,))``; values are 0 where not found."""
        if not len(self.keys) or not len(query):
            return np.zeros(len(query), np.int64), np.zeros(len(query), bool)
        pos = np.minimum(np.searchsorted(self.keys, query), len(self.keys) - 1)
        found = self.keys[pos] == query
        return np.where(found, self.vals[pos], 0), found


class _Graph:
    """The pair graph: each pair's matches (both orientations), its fitted ``F_jfromi``, and a
    search tree over every image's keypoints."""

    def __init__(self, matches: Mapping[Pair, np.ndarray], keypoints: Mapping[int, np.ndarray],
                 cfg: PairCheckConfig) -> None:
        self.edges: list[Pair] = []
        self.index: dict[Pair, int] = {}
        self.oriented: dict[tuple[int, int], np.ndarray] = {}  # (a, b) -> int64 (M, 2) in a, b order
        self.F: dict[tuple[int, int], np.ndarray] = {}  # (a, b) -> F_bfroma (3, 3)
        self.look: dict[tuple[int, int], _Lookup] = {}
        self.adj: dict[int, set[int]] = {}
        self.keypoints = {int(k): np.asarray(v, np.float64)[:, :2] for k, v in keypoints.items()}
        for (a, b), m in sorted(matches.items()):
            if a == b:
                raise ValueError(f"pair ({a}, {b}) joins an image to itself")
            m = np.asarray(m, np.int64).reshape(-1, 2)
            i, j = (a, b) if a < b else (b, a)
            if (i, j) in self.index:
                raise ValueError(f"pair ({i}, {j}) is given twice")
            if a > b:
                m = m[:, ::-1]
            self.index[(i, j)] = len(self.edges)
            self.edges.append((i, j))
            self.oriented[(i, j)], self.oriented[(j, i)] = m, m[:, ::-1]
            self.look[(i, j)], self.look[(j, i)] = _Lookup(m[:, 0], m[:, 1]), _Lookup(m[:, 1], m[:, 0])
            rng = np.random.default_rng([cfg.seed, i, j])
            F = None
            if len(m) >= cfg.min_f_matches:
                F = fit_fundamental(self.keypoints[i][m[:, 0]], self.keypoints[j][m[:, 1]], rng,
                                    threshold_px=cfg.f_threshold_px)
            if F is not None:
                self.F[(i, j)], self.F[(j, i)] = F, F.T
            self.adj.setdefault(i, set()).add(j)
            self.adj.setdefault(j, set()).add(i)
        self.trees: dict[int, cKDTree] = {}
        self.boxes: dict[int, tuple[np.ndarray, np.ndarray]] = {}
        self._carried: dict[tuple[tuple[int, int], int], np.ndarray] = {}

    def carried(self, pair: tuple[int, int], cap: int) -> np.ndarray:
        """At most ``cap`` of the oriented pair's matches, spread over its rows: int64
        ``(<= cap, 2)``, taken once per oriented pair."""
        if (pair, cap) not in self._carried:
            m = self.oriented[pair]
            self._carried[(pair, cap)] = m[spread_rows(len(m), cap)]
        return self._carried[(pair, cap)]

    def box(self, image: int) -> tuple[np.ndarray, np.ndarray]:
        """The image's keypoint extent (min ``(2,)``, max ``(2,)``) in pixels, computed once."""
        if image not in self.boxes:
            kp = self.keypoints[image]
            self.boxes[image] = (kp.min(0), kp.max(0))
        return self.boxes[image]

    def tree(self, image: int) -> tuple[cKDTree, tuple[np.ndarray, np.ndarray]]:
        """The image's keypoint search tree and keypoint extent (min, max), built once."""
        if image not in self.trees:
            self.trees[image] = cKDTree(self.keypoints[image])
        return self.trees[image], self.box(image)

    def triangles(self) -> list[tuple[int, int, int]]:
        """Every triangle (i < j < k) once: each pair's two neighbour sets intersected."""
        out: list[tuple[int, int, int]] = []
        for i, j in self.edges:
            a, b = self.adj[i], self.adj[j]
            common = a & b if len(a) <= len(b) else b & a
            out.extend((i, j, k) for k in sorted(common) if k > j)
        return out


def _within(xy_a: np.ndarray, xy_b: np.ndarray, tol: float) -> np.ndarray:
    return np.sum((xy_a - xy_b) ** 2, axis=1) <= tol * tol


def triangle_transfer(graph: _Graph, tri: tuple[int, int, int], cfg: PairCheckConfig) -> np.ndarray:
    """Closed and broken transfers of one triangle, each pair's matches carried into the third
    image: int64 ``(3, 4)``, rows for the pairs i-j, i-k, j-k of ``tri = (i, j, k)``, columns
    (closed, broken) through the tracks, then (closed, broken) by epipolar transfer.

    A match (p, q) of the pair x-y lands in the third image z in one of two ways:

    - through the other two pairs' matches (the track of the scene point): q's match r in y-z
      and p's match r' in x-z must be one keypoint of z, or two within ``transfer_tol_px``;
      with only one of them matched, the keypoint it reaches must lead back (through the other
      pair) to within ``transfer_tol_px`` of p or q. A wrong pair joins two copies of a
      repeated structure, so its tracks reach z at both copies.
    - otherwise by epipolar transfer: the intersection of p's epipolar line from x-z and q's
      from y-z must lie within ``transfer_tol_px`` of a keypoint of z (it lands anywhere when
      one of the three pairs is wrong). Not counted where the two lines meet at less than
      ``min_angle_deg`` (nearly collinear camera centres: the usual case for photos taken
      along a street or around an object at one height) or outside z's keypoint extent, or
      when a pair has no fitted F.

    At most ``max_transfers`` matches per pair are carried (spread over its rows).
    """
    out = np.zeros((3, 4), np.int64)
    i, j, k = tri
    kp = graph.keypoints
    min_sin = np.sin(np.deg2rad(cfg.min_angle_deg))
    tol = cfg.transfer_tol_px
    for row, (x, y, z) in enumerate(((i, j, k), (i, k, j), (j, k, i))):
        m = graph.carried((x, y), cfg.max_transfers)
        p, q = m[:, 0], m[:, 1]
        r_y, has_y = graph.look[(y, z)](q)  # through y-z
        r_x, has_x = graph.look[(x, z)](p)  # through x-z
        state = np.full(len(m), -1, np.int8)  # -1 not counted, 0 broken, 1 closed
        both = has_x & has_y
        state[both] = _within(kp[z][r_y[both]], kp[z][r_x[both]], tol)
        only_y = np.flatnonzero(has_y & ~has_x)
        back, ok = graph.look[(z, x)](r_y[only_y])
        state[only_y[ok]] = _within(kp[x][back[ok]], kp[x][p[only_y[ok]]], tol)
        only_x = np.flatnonzero(has_x & ~has_y)
        back, ok = graph.look[(z, y)](r_x[only_x])
        state[only_x[ok]] = _within(kp[y][back[ok]], kp[y][q[only_x[ok]]], tol)
        out[row, :2] = np.count_nonzero(state == 1), np.count_nonzero(state == 0)
        rest = np.flatnonzero(state < 0)
        Fx, Fy = graph.F.get((x, z)), graph.F.get((y, z))
        if len(rest) and Fx is not None and Fy is not None and (x, y) in graph.F:
            pts, sin = transfer(Fx, Fy, kp[x][p[rest]], kp[y][q[rest]])
            tree, (lo, hi) = graph.tree(z)
            ok = (sin >= min_sin) & np.isfinite(pts).all(1)
            ok[ok] &= ((pts[ok] >= lo) & (pts[ok] <= hi)).all(1)
            if ok.any():
                d, _ = tree.query(pts[ok], k=1, distance_upper_bound=tol)
                state[rest[ok]] = np.isfinite(d)
        out[row, 2:] = np.count_nonzero(state[rest] == 1), np.count_nonzero(state[rest] == 0)
    return out


def triangle_state(cb: np.ndarray, cfg: PairCheckConfig) -> int:
    """-1 undecided, 0 closed, 1 broken, from a triangle's ``(3, 2)`` closed / broken counts:
    broken when the transfers of each of its pairs with at least ``min_transfers`` counted
    mostly fail (closed share below ``min_closed_share``). One wrong pair breaks all three
    transfers (it is used in each); a single failing transfer is more often a weak pair's
    inaccurate F, or two wrong pairs that agree with each other (then the third pair's
    matches are the ones that fail)."""
    n = cb.sum(1)
    counted = n >= cfg.min_transfers
    if not counted.any():
        return -1
    share = cb[counted, 0] / n[counted]
    return int(share.max() < cfg.min_closed_share)


def carrier_votes(cb: np.ndarray, cfg: PairCheckConfig) -> np.ndarray:
    """Votes of one triangle on its pairs i-j, i-k, j-k: int64 ``(3, 2)`` (blame, support).

    A pair's matches are carried into the third image by the other two pairs. When at least
    ``min_transfers`` of them are counted, the two carriers get one blame if the closed share
    is below ``min_closed_share``, else one support; with ``transferred_votes`` the pair
    transferred gets the same vote (a transfer is a loop through all three pairs: when it
    fails, any of them may be the wrong one). One wrong pair is a carrier of two of the three
    transfers and is transferred in the third, so all three fail and every pair is blamed;
    two wrong pairs that agree (both join the same copies) carry each other's matches
    correctly but not the correct pair's: each gets blame and support, the correct pair
    mostly support. The transfers of a wrong pair whose images lie far apart often count
    only its own (the others land outside its images), so without ``transferred_votes`` its
    failures blame only the two correct carriers.
    """
    out = np.zeros((3, 2), np.int64)
    carriers = ((1, 2), (0, 2), (0, 1))  # row r (pair r transferred) is carried by these pairs
    n = cb.sum(1)
    counted = n >= cfg.min_transfers
    share = np.where(counted, cb[:, 0] / np.maximum(n, 1), 0.0)
    for r in range(3):
        if counted[r]:
            fail = share[r] < cfg.min_closed_share
            for c in carriers[r] + ((r,) if cfg.transferred_votes else ()):
                out[c, 0 if fail else 1] += 1
    return out


#: Row r of a triangle (pair r) and its two other pairs: the carriers of its transfer, and the
#: pairs whose trust weighs the triangle's votes on pair r.
_OTHERS = np.array([[1, 2], [0, 2], [0, 1]])


def _weighted_votes(votes: np.ndarray, tri_edges: np.ndarray, alive_tri: np.ndarray,
                    trust: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Blame and support ``(E,)`` of every pair, each present triangle's votes on a pair
    weighted by the product of the trust of the triangle's two other pairs."""
    w = trust[tri_edges[:, _OTHERS[:, 0]]] * trust[tri_edges[:, _OTHERS[:, 1]]] * alive_tri[:, None]
    blame = np.zeros(len(trust))
    support = np.zeros(len(trust))
    np.add.at(blame, tri_edges.ravel(), (votes[:, :, 0] * w).ravel())
    np.add.at(support, tri_edges.ravel(), (votes[:, :, 1] * w).ravel())
    return blame, support


def settle_trust(votes: np.ndarray, tri_edges: np.ndarray, alive_tri: np.ndarray, alive: np.ndarray,
                 cfg: PairCheckConfig) -> np.ndarray:
    """Trust of every pair in [0, 1] ``(E,)``: ``cfg.trust_iterations`` rounds of
    ``trust = (1 - weighted blame share) ** cfg.trust_power`` from all ones (removed pairs: 0).

    This is loop-consistency inference in the spirit of Zach et al. (2010), "Disambiguating
    visual relations using loop constraints", on the triangles of the pair graph: a closed
    triangle is evidence that its pairs are right only if the pairs that closed it are
    themselves trusted. Two wrong pairs that join the same copies of a repeated structure
    close their shared triangles (they agree), so counted votes alone let them support each
    other; each is also blamed by the triangles it shares with correct pairs, its trust drops,
    and the support it gives the other fades with it. A correct pair is blamed mostly by
    triangles holding a wrong pair, whose weight fades the same way.

    Args:
        votes: float ``(T, 3, 2)``, per triangle and pair (rows i-j, i-k, j-k): blame, support.
        tri_edges: int ``(T, 3)`` pair indices of each triangle.
        alive_tri / alive: bool ``(T,)`` / ``(E,)``: triangles and pairs still present.
    """
    trust = alive.astype(np.float64)
    for _ in range(cfg.trust_iterations):
        blame, support = _weighted_votes(votes, tri_edges, alive_tri, trust)
        trust = np.where(alive, (1.0 - blame / np.maximum(blame + support, 1e-12)) ** cfg.trust_power, 0.0)
    return trust


def _remove_worst_first(blame: np.ndarray, support: np.ndarray, strength: np.ndarray, votes: np.ndarray,
                        tri_edges: np.ndarray, edge_tris: list[list[int]],
                        cfg: PairCheckConfig) -> tuple[np.ndarray, list[int], dict[int, str]]:
    """Remove the pair with the highest trust-weighted blame share (ties: more blame, then the
    weaker pair) while one has at least ``min_blame`` blames and a weighted share of at least
    ``min_blame_share``; its triangles' votes leave the other pairs' counts (``blame``,
    ``support`` ``(E,)``, the unweighted counts, are updated in place) and the trust of every
    pair is settled again (:func:`settle_trust`; with ``trust_iterations = 0`` every vote
    counts fully). A pair with blame is in a triangle still present, so its two images stay
    joined through the triangle's third image: no removal disconnects the graph.

    Returns:
        ``(alive bool (E,), removed edge indices in order, edge index -> reason)``.
    """
    n_edges = len(blame)
    alive_tri = np.ones(len(tri_edges), bool)
    alive = np.ones(n_edges, bool)
    fvotes = votes.astype(np.float64)
    removed: list[int] = []
    why: dict[int, str] = {}
    while True:
        trust = settle_trust(fvotes, tri_edges, alive_tri, alive, cfg)
        w_blame, w_support = _weighted_votes(fvotes, tri_edges, alive_tri, trust)
        share = w_blame / np.maximum(w_blame + w_support, 1e-12)
        share[w_blame <= 0] = 0.0
        cand = alive & (blame >= cfg.min_blame) & (share >= cfg.min_blame_share)
        if not cand.any():
            break
        idx = np.flatnonzero(cand)
        e = int(idx[np.lexsort((strength[idx], -blame[idx], -share[idx]))[0]])
        why[e] = (f"{int(blame[e])} of the {int(blame[e] + support[e])} votes of its triangles blame it, "
                  f"{share[e]:.2f} of their weight (relative strength {strength[e]:.2f})")
        alive[e] = False
        removed.append(e)
        for t in edge_tris[e]:
            if alive_tri[t]:
                alive_tri[t] = False
                np.subtract.at(blame, tri_edges[t], votes[t, :, 0])
                np.subtract.at(support, tri_edges[t], votes[t, :, 1])
    return alive, removed, why


def confirming_triangles(tracks: np.ndarray, votes: np.ndarray, tri_edges: np.ndarray, alive: np.ndarray,
                         cfg: PairCheckConfig) -> np.ndarray:
    """Per pair ``(E,)``: the triangles in which its own matches, carried into the third image
    through the matches of the two other pairs, reach one keypoint there (consistent tracks,
    no track conflict): at least ``min_transfers`` closed and a closed share of at least
    ``confirm_share``, where both other pairs are kept (``alive``) and trusted (at least
    ``confirm_trust`` after the removals, :func:`settle_trust`).

    This is the track-conflict test of Wilson & Snavely (2013) and Heinly et al. (2014) in its
    positive form, on the pairs the vote removed. A wrong pair joins the tracks of two
    different scene points, so two correct pairs never carry its matches to one keypoint;
    only other wrong pairs that join the same copies can, hence the count of triangles. A
    correct pair removed because its fundamental matrix, fitted to few matches, carries
    other pairs' points astray by epipolar transfer, still has its tracks confirmed by the
    strong pairs around it.

    Args:
        tracks: int ``(T, 3, 2)``: per triangle and pair, its transfers through the tracks
            (closed, broken).
        votes: float ``(T, 3, 2)``: the triangles' votes (blame, support), for the trust.
        tri_edges: int ``(T, 3)``; alive: bool ``(E,)``, the pairs kept.
    """
    both = alive[tri_edges].all(1)
    trust = settle_trust(votes, tri_edges, both, alive, cfg)
    ok = alive & (trust >= cfg.confirm_trust)
    carriers_ok = ok[tri_edges[:, _OTHERS[:, 0]]] & ok[tri_edges[:, _OTHERS[:, 1]]]
    closed, broken = tracks[:, :, 0], tracks[:, :, 1]
    good = carriers_ok & (closed >= cfg.min_transfers) & (closed >= cfg.confirm_share * (closed + broken))
    out = np.zeros(len(alive), np.int64)
    np.add.at(out, tri_edges.ravel(), good.ravel().astype(np.int64))
    return out


def _coverage(graph: _Graph, pair: Pair) -> float:
    """Smaller share of grid cells (over each image's keypoint extent) holding a match of
    ``pair``."""
    m = graph.oriented[pair]
    shares = []
    for image, idx in ((pair[0], m[:, 0]), (pair[1], m[:, 1])):
        kp = graph.keypoints[image]
        if not len(kp) or not len(idx):
            return 0.0
        lo, hi = graph.box(image)
        cell = np.floor((kp[idx] - lo) / np.maximum(hi - lo, 1e-9) * COVERAGE_GRID).clip(0, COVERAGE_GRID - 1)
        shares.append(len(np.unique(cell[:, 0] * COVERAGE_GRID + cell[:, 1])) / COVERAGE_GRID**2)
    return float(min(shares))


def check_pairs(matches: Mapping[Pair, np.ndarray], keypoints: Mapping[int, np.ndarray],
                cfg: PairCheckConfig) -> PairCheckResult:
    """Judge every pair of a pair graph by the triangles it is in.

    Args:
        matches: (image_id1, image_id2) -> int ``(M, 2)`` keypoint indices in that order
            (the matches that reach the output; either order of the two ids, each pair once).
        keypoints: image id -> float ``(N, 2)`` keypoint positions in pixels, for every image
            of ``matches``.
        cfg: the thresholds (``mode`` is not used here: the caller removes or flags).

    Returns:
        A :class:`PairCheckResult` over all pairs (keys with image_id1 < image_id2).

    Raises:
        ValueError: a pair of one image with itself, or a pair given twice.
    """
    graph = _Graph(matches, keypoints, cfg)
    n_edges = len(graph.edges)
    tris = graph.triangles()
    total = np.zeros(n_edges, np.int64)
    own = np.zeros((n_edges, 2), np.int64)  # the pair's own transfers: closed, broken
    tri_edges = np.zeros((len(tris), 3), np.int64)
    tri_state = np.full(len(tris), -1, np.int8)  # -1 undecided, 0 closed, 1 broken
    votes = np.zeros((len(tris), 3, 2), np.int64)  # per triangle and pair: blame, support
    tracks = np.zeros((len(tris), 3, 2), np.int64)  # per triangle and pair: closed, broken through tracks
    edge_tris: list[list[int]] = [[] for _ in range(n_edges)]
    for t, (i, j, k) in enumerate(tris):
        es = [graph.index[(i, j)], graph.index[(i, k)], graph.index[(j, k)]]
        tri_edges[t] = es
        cb4 = triangle_transfer(graph, (i, j, k), cfg)
        tracks[t] = cb4[:, :2]
        cb = cb4[:, :2] + cb4[:, 2:]
        tri_state[t] = triangle_state(cb, cfg)
        votes[t] = carrier_votes(cb, cfg)
        for r, e in enumerate(es):
            edge_tris[e].append(t)
            total[e] += 1
            own[e] += cb[r]
    blame = np.zeros(n_edges, np.int64)
    support = np.zeros(n_edges, np.int64)
    np.add.at(blame, tri_edges.ravel(), votes[:, :, 0].ravel())
    np.add.at(support, tri_edges.ravel(), votes[:, :, 1].ravel())
    blame0, support0 = blame.copy(), support.copy()
    broken_tris = np.zeros(n_edges, np.int64)
    np.add.at(broken_tris, tri_edges.ravel(), np.repeat(tri_state == 1, 3))

    sizes = np.array([len(graph.oriented[e]) for e in graph.edges], np.int64)
    per_image: dict[int, list[int]] = {}
    for e, (i, j) in enumerate(graph.edges):
        per_image.setdefault(i, []).append(int(sizes[e]))
        per_image.setdefault(j, []).append(int(sizes[e]))
    strength = np.array([sizes[e] / max(float(np.median(per_image[i] + per_image[j])), 1.0)
                         for e, (i, j) in enumerate(graph.edges)])

    alive, removed, why = _remove_worst_first(blame, support, strength, votes, tri_edges, edge_tris, cfg)
    confirmed = confirming_triangles(tracks, votes.astype(np.float64), tri_edges, alive, cfg)
    if cfg.confirm_triangles:
        kept = [e for e in removed if confirmed[e] >= cfg.confirm_triangles]
        alive[kept] = True
        removed = [e for e in removed if not alive[e]]

    verdicts = {}
    for e, (i, j) in enumerate(graph.edges):
        verdicts[(i, j)] = PairVerdict(
            matches=int(sizes[e]), strength=float(strength[e]), coverage=_coverage(graph, (i, j)),
            triangles=int(total[e]), triangles_broken=int(broken_tris[e]),
            blame=int(blame0[e]), support=int(support0[e]),
            transfers_closed=int(own[e, 0]), transfers_broken=int(own[e, 1]),
            confirmed_triangles=int(confirmed[e]), wrong=not alive[e], reason=why.get(e, "") if not alive[e] else "")
    return PairCheckResult(verdicts=verdicts, wrong=[graph.edges[e] for e in removed], triangles=len(tris),
                           triangles_decided=int(np.count_nonzero(tri_state >= 0)),
                           triangles_broken=int(np.count_nonzero(tri_state == 1)))
