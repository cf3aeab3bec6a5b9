"""The track plan: tracks built once, for the walk and for the worker split alike.

Every match that reaches the output database is an edge between two ``(image_id,
keypoint_index)`` nodes; the connected components of all edges are the tracks, exactly the
tracks COLMAP will build from the output. An edge is *refinable* when it carries a patch
homography pair (a match the filter kept and labelled); the others (pairs that were never
filtered, whose filter failed, or that touch a missing image) join tracks but are never used
to refine.

Rules (documented once, here):

- **Anchor**: per track, the node with the most refinable edges; ties go to the lowest
  ``(image_id, keypoint_index)``. Tracks without a refinable edge have no anchor.
- **Reach**: a track is walked from its anchor over refinable edges only; its keypoints that
  the anchor cannot reach that way never move. So every moved keypoint is refined relative
  to the anchor of the track it belongs to in the output, whatever joined the track.
- **Conflicts**: a track holding two keypoints of one image more than
  ``TrackConfig.duplicate_px`` apart is *frozen*: none of its keypoints moves (the
  keypoints of one image cannot all be the same 3D point, so the walk has no single
  reference to refine them to). Keypoints of one image closer than that are duplicates
  (SIFT keeps one keypoint per dominant orientation at the same position) and are walked
  like the others.

Pure numpy/scipy: no images, no torch.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field, replace

import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components


@dataclass(frozen=True)
class TrackPlan:
    """Tracks over ``T`` keypoint nodes and ``E`` match edges.

    Attributes:
        keypoints: image_id -> (Ni, 2) float64 input positions (integer = pixel centre).
        node_image, node_kp: (T,) int64 image id and keypoint index of each node; nodes are
            ordered by (image_id, keypoint_index).
        pairs: the image pairs (id1, id2); ``edge_pair`` indexes it.
        pair_homs: per pair the (K, 2, 3, 3) float64 patch homography pairs (A, B),
            ``A x1 ~ B x2``.
        local_homs: None, or per pair the (M_p, 2, 3, 3) local affine pairs of its edges
            (``local_affine``), indexed by ``edge_row``. Plans from :func:`build_track_plan`
            compute them lazily, pair by pair (:meth:`TrackPlan.local_pairs`).
        edge_a, edge_b: (E,) int64 nodes of each edge, ``edge_a`` in the pair's first image.
        edge_pair: (E,) int64 pair of each edge.
        edge_row: (E,) int64 row of each edge among its pair's edges.
        edge_label: (E,) int64 homography pair of each edge in ``pair_homs``; -1: joins
            tracks, never refines.
        track: (T,) int64 track of each node, -1 for nodes without an edge.
        anchors: (A,) int64 anchor node of each walked track.
        frozen: (T,) bool nodes of frozen (conflicting) tracks.
        to_refine: keypoints the walk will refine (reachable from an anchor, anchors not
            counted).
        local_affine: (k neighbours, max residual px) of the local affine pairs, or None.
        source_pairs: None for a plan over all output matches; for a group
            (:meth:`TrackPlan.groups`) the (P',) int64 index of each of its pairs in the
            plan it came from.
        source_rows: None, or for a group the (E',) int64 row of each edge among its pair's
            edges in the plan it came from.
        stats: ``tracks`` (tracks with >= 2 keypoints), ``conflicting_tracks`` (two
            keypoints of one image), ``frozen_tracks``, ``frozen_keypoints``,
            ``keypoints_in_tracks``, ``anchors``, ``unrefinable_matches`` (edges without
            a homography), ``unreached_keypoints`` (in walked tracks, not reachable from
            the anchor over refinable edges).
    """

    keypoints: dict
    node_image: np.ndarray
    node_kp: np.ndarray
    pairs: tuple
    pair_homs: tuple
    local_homs: tuple | None
    edge_a: np.ndarray
    edge_b: np.ndarray
    edge_pair: np.ndarray
    edge_row: np.ndarray
    edge_label: np.ndarray
    track: np.ndarray
    anchors: np.ndarray
    frozen: np.ndarray
    to_refine: int
    stats: dict = field(default_factory=dict)
    local_affine: tuple | None = None
    source_pairs: np.ndarray | None = None
    source_rows: np.ndarray | None = None
    _local_cache: dict = field(default_factory=dict, init=False, repr=False, compare=False)
    _steps: list = field(default_factory=list, init=False, repr=False, compare=False)

    @property
    def num_nodes(self) -> int:
        return int(self.node_image.size)

    @property
    def image_ids(self) -> list:
        """The images of this plan's keypoints, sorted."""
        return sorted(self.keypoints)

    def local_pairs(self, p: int) -> np.ndarray | None:
        """(M_p, 2, 3, 3) local affine pairs of the edges of pair ``p`` (by ``edge_row``), or
        None without ``local_affine``. A plan over all output matches fits them on first use
        (each from the neighbourhood of its match among all of the pair's edges) and keeps
        them until :meth:`release_local`; a group carries those of its own edges
        (:meth:`attach_local`). Only the edges the walk can refine along
        (:meth:`walk_steps`) are fitted: the others keep the filter's pair.

        Raises:
            ValueError: a group whose local pairs were not attached.
        """
        if self.local_homs is not None:
            return self.local_homs[p]
        if self.local_affine is None:
            return None
        if self.source_pairs is not None:
            raise ValueError("this group has no local affine pairs: attach them with "
                             "attach_local of the plan it came from")
        if p not in self._local_cache:
            from .rectify import local_affine_pairs

            lo, hi = np.searchsorted(self.edge_pair, [p, p + 1])
            id1, id2 = self.pairs[p]
            x1 = self.keypoints[id1][self.node_kp[self.edge_a[lo:hi]]]
            x2 = self.keypoints[id2][self.node_kp[self.edge_b[lo:hi]]]
            k, max_residual_px = self.local_affine
            self._local_cache[p] = local_affine_pairs(
                x1, x2, self.edge_label[lo:hi], self.pair_homs[p], k=k,
                max_residual_px=max_residual_px, fit=self.walk_steps()[lo:hi])
        return self._local_cache[p]

    def release_local(self, pairs) -> None:
        """Forget the local affine pairs of ``pairs`` (pair indices); they are fitted again,
        identically, if asked for later."""
        for p in np.asarray(pairs, np.int64).reshape(-1):
            self._local_cache.pop(int(p), None)

    def attach_local(self, group: TrackPlan) -> TrackPlan:
        """``group`` (from :meth:`groups` of this plan) with the local affine pairs of its
        edges, fitted in this plan (over each pair's full edge set, so they are those a walk of
        this whole plan uses); itself when this plan has no ``local_affine``."""
        if self.local_affine is None or group.local_homs is not None:
            return group
        if group.source_pairs is None or group.source_rows is None:
            raise ValueError("attach_local takes a group made by groups() of this plan")
        starts = np.searchsorted(group.edge_pair, np.arange(len(group.pairs) + 1))
        rows = group.source_rows
        local = []
        for q, sp in enumerate(group.source_pairs):
            fitted = self.local_pairs(int(sp))
            assert fitted is not None  # local_affine is set
            local.append(fitted[rows[starts[q]:starts[q + 1]]])
        return replace(group, local_homs=tuple(local))

    def walked_units(self) -> tuple[np.ndarray, np.ndarray]:
        """The walk's independent units: per edge the (E,) int64 walked component it belongs
        to (-1: not refinable, or not reachable from its track's anchor over refinable
        edges), and per unit its anchor node (U,) int64. Units are numbered in anchor
        order."""
        ok = self.refinable()
        unit = np.full(self.edge_a.size, -1, np.int64)
        if not ok.any() or not self.anchors.size:
            return unit, np.zeros(0, np.int64)
        total = self.num_nodes
        ea, eb = self.edge_a[ok], self.edge_b[ok]
        _, comp = connected_components(
            coo_matrix((np.ones(ea.size), (ea, eb)), shape=(total, total)), directed=False)
        of_comp = np.full(comp.max() + 1, -1, np.int64)
        of_comp[comp[self.anchors]] = np.arange(self.anchors.size)
        unit[ok] = of_comp[comp[ea]]
        return unit, self.anchors

    def subset(self, edges: np.ndarray, anchors: np.ndarray) -> TrackPlan:
        """A compact plan of whole walked units: the refinable ``edges`` (indices, all the
        edges of the units of ``anchors``) and ``anchors`` (nodes). Only its own nodes,
        edges, pairs and the keypoint arrays of its images are kept, re-indexed in the same
        order (node order is (image_id, keypoint_index) as here, pairs as here), so its walk
        moves its keypoints exactly as a walk of this whole plan does."""
        edges = np.sort(np.asarray(edges, np.int64))
        ea, eb = self.edge_a[edges], self.edge_b[edges]
        nodes = np.unique(np.concatenate([ea, eb, anchors]))
        used_pairs, edge_pair = np.unique(self.edge_pair[edges], return_inverse=True)
        edge_pair = edge_pair.astype(np.int64).reshape(-1)
        node_image = self.node_image[nodes]
        src_pairs = used_pairs if self.source_pairs is None else self.source_pairs[used_pairs]
        rows = self.edge_row[edges]
        src_rows = rows if self.source_rows is None else self.source_rows[edges]
        local = None
        if self.local_homs is not None:
            starts = np.searchsorted(edge_pair, np.arange(used_pairs.size + 1))
            local = tuple(self.local_homs[int(p)][rows[starts[q]:starts[q + 1]]]
                          for q, p in enumerate(used_pairs))
        _, track = np.unique(self.track[nodes], return_inverse=True)
        new_a, new_b = np.searchsorted(nodes, ea), np.searchsorted(nodes, eb)
        new_anchors = np.searchsorted(nodes, np.asarray(anchors, np.int64))
        return TrackPlan(
            keypoints={int(i): self.keypoints[int(i)] for i in np.unique(node_image)},
            node_image=node_image, node_kp=self.node_kp[nodes],
            pairs=tuple(self.pairs[int(p)] for p in used_pairs),
            pair_homs=tuple(self.pair_homs[int(p)] for p in used_pairs), local_homs=local,
            edge_a=new_a, edge_b=new_b, edge_pair=edge_pair,
            edge_row=np.arange(edge_pair.size) - np.searchsorted(edge_pair, edge_pair),
            edge_label=self.edge_label[edges], track=track.astype(np.int64).reshape(-1),
            anchors=new_anchors, frozen=np.zeros(nodes.size, bool),
            to_refine=int(nodes.size - new_anchors.size), stats={},
            local_affine=self.local_affine, source_pairs=src_pairs, source_rows=src_rows)

    def groups(self, max_images: int, max_edges: int | None = None) -> list[TrackPlan]:
        """Whole walked units (the part of a track its anchor reaches over refinable
        edges) packed into compact groups (:meth:`subset`) of at most ``max_images``
        distinct images and at most ``max_edges`` refinable edges each. A unit over
        ``max_images`` images (its walk needs them all anyway) raises its group's image bound
        to its own image count; one over ``max_edges`` is a group alone.

        Schedule: units sorted by their sorted image ids (lexicographically; ties by
        anchor), then swept in that order, a new group started when the next unit would
        exceed a bound; so consecutive groups share images and an image stops being needed
        once the sweep has passed the units that start with it. Deterministic: the same
        plan and bounds give the same groups in the same order. Walking the
        groups one by one moves exactly the keypoints a walk of the whole plan moves, to the
        same positions (units never share a keypoint). Local affine pairs are not included:
        :meth:`attach_local` adds them, group by group.
        """
        if max_images < 1:
            raise ValueError(f"max_images must be >= 1, got {max_images}")
        if max_edges is not None and max_edges < 1:
            raise ValueError(f"max_edges must be >= 1 or None, got {max_edges}")
        unit, anchors = self.walked_units()
        if not anchors.size:
            return []
        e_ids = np.flatnonzero(unit >= 0)
        eu = unit[e_ids]
        img_a, img_b = self.node_image[self.edge_a[e_ids]], self.node_image[self.edge_b[e_ids]]
        # the (unit, image) pairs, sorted, as one int64 code each (np.unique on rows is slow)
        ids, img = np.unique(np.concatenate([img_a, img_b]), return_inverse=True)
        code = np.unique(np.concatenate([eu, eu]) * ids.size + img.reshape(-1))
        key_unit, key_image = code // ids.size, ids[code % ids.size]
        bounds = np.searchsorted(key_unit, np.arange(anchors.size + 1))
        images = [tuple(key_image[bounds[u]:bounds[u + 1]].tolist()) for u in range(anchors.size)]
        order = sorted(range(anchors.size), key=lambda u: (images[u], u))
        n_edges = np.bincount(eu, minlength=anchors.size).tolist()
        limit = max_edges or eu.size
        group_of = np.empty(anchors.size, np.int64)
        g, current, edges, cap = -1, set[int](), 0, max_images
        for u in order:
            both = current | set(images[u])
            edges += n_edges[u]
            if g < 0 or len(both) > max(cap, len(images[u])) or edges > limit:
                g, both, edges, cap = g + 1, set(images[u]), n_edges[u], max_images
            group_of[u] = g
            current, cap = both, max(cap, len(images[u]))
        return self._split(e_ids, group_of[eu], anchors, group_of, g + 1)

    def _split(self, e_ids, edge_group, anchors, anchor_group, n) -> list[TrackPlan]:
        """Compact plans of the edges ``e_ids`` by their group ``edge_group`` (0..n-1)."""
        e_sorted = e_ids[np.argsort(edge_group, kind="stable")]
        e_bounds = np.searchsorted(np.sort(edge_group), np.arange(n + 1))
        a_order = np.argsort(anchor_group, kind="stable")
        a_sorted = anchors[a_order]
        a_bounds = np.searchsorted(anchor_group[a_order], np.arange(n + 1))
        return [self.subset(e_sorted[e_bounds[b]:e_bounds[b + 1]],
                            a_sorted[a_bounds[b]:a_bounds[b + 1]])
                for b in range(n) if e_bounds[b + 1] > e_bounds[b]]

    def walk_steps(self) -> np.ndarray:
        """(E,) bool: the edges the walk can refine along, the refinable edges from a node
        of one level of the walk to a node of the next (level = refinable-edge hops from
        the anchor; a node is refined at its level against a node of the level before, so
        edges within a level or to unreached nodes are never used)."""
        if not self._steps:
            ok = self.refinable()
            ea, eb = self.edge_a[ok], self.edge_b[ok]
            level = np.full(self.num_nodes, -1, np.int64)
            level[self.anchors] = 0
            n = 0
            while True:  # the walk's levels (tracks._level_groups)
                fa, fb = level[ea] >= 0, level[eb] >= 0
                new = np.concatenate([eb[fa & ~fb], ea[fb & ~fa]])
                if not new.size:
                    break
                n += 1
                level[new] = n
            steps = np.zeros(self.edge_a.size, bool)
            la, lb = level[ea], level[eb]
            steps[ok] = (la >= 0) & (lb >= 0) & (np.abs(la - lb) == 1)
            self._steps.append(steps)
        return self._steps[0]

    def refinable(self) -> np.ndarray:
        """(E,) bool: edges the walk may refine along (labelled, track not frozen)."""
        return (self.edge_label >= 0) & ~self.frozen[self.edge_a]

    def partition(self, n: int) -> list[TrackPlan]:
        """At most ``n`` compact plans (:meth:`subset`) of whole walked units, balanced by
        refinable edges (greedy: the biggest unit to the lightest part). Parts never share a
        keypoint, so their results merge without conflict. Empty parts are left out."""
        if n < 1:
            raise ValueError(f"n must be >= 1, got {n}")
        unit, anchors = self.walked_units()
        e_ids = np.flatnonzero(unit >= 0)
        sizes = np.bincount(unit[e_ids], minlength=anchors.size)
        order = np.argsort(-sizes, kind="stable")
        load = np.zeros(n)
        part_of = np.zeros(anchors.size, np.int64)
        for u in order:
            b = int(np.argmin(load))
            part_of[u] = b
            load[b] += sizes[u]
        return self._split(e_ids, part_of[unit[e_ids]], anchors, part_of, n)


def _reachable(total: int, ea: np.ndarray, eb: np.ndarray, anchors: np.ndarray,
               nodes: np.ndarray | None = None) -> int:
    """Nodes joined to an anchor by the edges (ea, eb), anchors not counted."""
    if not ea.size:
        return 0
    _, comp = connected_components(
        coo_matrix((np.ones(ea.size), (ea, eb)), shape=(total, total)), directed=False)
    if nodes is None:
        nodes = np.unique(np.concatenate([ea, eb]))
    hit = np.zeros(comp.max() + 1, bool)
    hit[comp[anchors]] = True
    return int(hit[comp[nodes]].sum() - anchors.size)


def _check_matches(pair, m, keypoints) -> np.ndarray:
    m = np.asarray(m)
    if m.ndim != 2 or m.shape[1] != 2:
        if m.size == 0:
            return np.zeros((0, 2), np.int64)
        raise ValueError(f"pair {pair}: matches must have shape (M, 2), got {m.shape}")
    m = m.astype(np.int64)
    id1, id2 = pair
    if id1 == id2:
        raise ValueError(f"pair {pair}: an image cannot be matched with itself")
    for c, i in ((0, id1), (1, id2)):
        if i not in keypoints:
            raise ValueError(f"pair {pair}: no keypoints for image {i}")
        if m.size and (m[:, c].min() < 0 or m[:, c].max() >= keypoints[i].shape[0]):
            raise ValueError(f"pair {pair}: keypoint index out of range for image {i}")
    return m


def pair_rows(pair, matches: np.ndarray, result) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The output rows of one filtered pair: rows of ``result`` are 1:1 with ``matches``.

    Args:
        pair: (id1, id2), for messages.
        matches: (M, 2) int keypoint indices.
        result: a ``FilterResult``-like object: ``labels`` (M,) int (-1 = no homography),
            ``patch_homographies`` (K, 2, 3, 3), optional ``inliers`` (M,) bool (rows that
            reach the output; all rows when absent).
    Returns:
        (kept matches (M', 2) int64, their labels (M',) int64, homographies (K, 2, 3, 3)
        float64).
    Raises:
        ValueError: rows not 1:1, bad shapes or labels out of range (names the pair).
    """
    labels = np.asarray(result.labels).astype(np.int64).reshape(-1)
    if labels.shape[0] != matches.shape[0]:
        raise ValueError(f"pair {pair}: {labels.shape[0]} filter labels for "
                         f"{matches.shape[0]} matches (rows must be 1:1)")
    inliers = getattr(result, "inliers", None)
    keep = (np.ones(labels.shape[0], bool) if inliers is None
            else np.asarray(inliers).astype(bool).reshape(-1))
    if keep.shape[0] != labels.shape[0]:
        raise ValueError(f"pair {pair}: {keep.shape[0]} inlier flags for "
                         f"{labels.shape[0]} matches (rows must be 1:1)")
    homs = np.asarray(result.patch_homographies, dtype=np.float64)
    if homs.ndim != 4 or homs.shape[1:] != (2, 3, 3):
        raise ValueError(f"pair {pair}: patch_homographies must be (K, 2, 3, 3), got {homs.shape}")
    if ((labels >= homs.shape[0]) | (labels < -1)).any():
        raise ValueError(f"pair {pair}: labels out of range for {homs.shape[0]} homographies")
    return matches[keep], labels[keep], homs


def _nodes(keypoints: Mapping) -> tuple[dict, dict, np.ndarray, np.ndarray]:
    kps, offset, total = {}, {}, 0
    for i in sorted(keypoints):
        arr = np.asarray(keypoints[i], dtype=np.float64)
        if arr.ndim != 2 or arr.shape[1] != 2:
            raise ValueError(f"keypoints[{i}] must have shape (N, 2), got {arr.shape}")
        kps[i], offset[i] = arr, total
        total += arr.shape[0]
    node_image = np.concatenate([np.full(len(a), i, np.int64) for i, a in kps.items()]
                                or [np.zeros(0, np.int64)])
    node_kp = np.concatenate([np.arange(len(a), dtype=np.int64) for a in kps.values()]
                             or [np.zeros(0, np.int64)])
    return kps, offset, node_image, node_kp


def _edges(kps, offset, pair_matches, pair_filter_results, unrefined_matches):
    """Edge arrays over all output matches, in (pair, row) order."""
    pairs = sorted(set(pair_matches) | set(unrefined_matches or {}))
    homs, ea, eb, ep, el = [], [], [], [], []
    for p, pair in enumerate(pairs):
        ms, ls = [], []
        h = np.zeros((0, 2, 3, 3))
        if pair in pair_matches:
            if pair not in pair_filter_results:
                raise ValueError(f"pair {pair}: no filter result")
            m = _check_matches(pair, pair_matches[pair], kps)
            m, lab, h = pair_rows(pair, m, pair_filter_results[pair])
            ms.append(m)
            ls.append(lab)
        if unrefined_matches and pair in unrefined_matches:
            m = _check_matches(pair, unrefined_matches[pair], kps)
            ms.append(m)
            ls.append(np.full(m.shape[0], -1, np.int64))
        m, lab = np.concatenate(ms), np.concatenate(ls)
        homs.append(h)
        ea.append(offset[pair[0]] + m[:, 0])
        eb.append(offset[pair[1]] + m[:, 1])
        ep.append(np.full(m.shape[0], p, np.int64))
        el.append(lab)
    def cat(xs: list) -> np.ndarray:
        return np.concatenate(xs) if xs else np.zeros(0, np.int64)

    return tuple(pairs), tuple(homs), cat(ea), cat(eb), cat(ep), cat(el)


def _conflicts(track, nodes, node_image, pos, duplicate_px) -> tuple[np.ndarray, np.ndarray]:
    """(n_tracks,) bool: tracks with two keypoints of one image more than ``duplicate_px``
    apart; and (n_tracks,) bool: tracks with two keypoints of one image at all."""
    n_tracks = int(track.max()) + 1
    key = np.lexsort((node_image[nodes], track[nodes]))
    t, im, p = track[nodes][key], node_image[nodes][key], pos[key]
    start = np.ones(t.size, bool)
    start[1:] = (t[1:] != t[:-1]) | (im[1:] != im[:-1])
    idx = np.flatnonzero(start)
    count = np.diff(np.append(idx, t.size))
    spread = np.maximum.reduceat(p, idx, axis=0) - np.minimum.reduceat(p, idx, axis=0)
    far = np.linalg.norm(spread, axis=1) > duplicate_px
    any_two = np.zeros(n_tracks, bool)
    any_two[t[idx[count > 1]]] = True
    conflict = np.zeros(n_tracks, bool)
    conflict[t[idx[(count > 1) & far]]] = True
    return conflict, any_two


def build_track_plan(
    keypoints: Mapping,
    pair_matches: Mapping,
    pair_filter_results: Mapping,
    *,
    unrefined_matches: Mapping | None = None,
    duplicate_px: float = 1.0,
    local_affine: tuple[int, float] | None = None,
) -> TrackPlan:
    """Build the tracks of all output matches (see the module docstring for the rules).

    Args:
        keypoints: image_id -> (Ni, 2) pixel positions (integer = pixel centre).
        pair_matches: (id1, id2) -> (M, 2) int keypoint indices of a filtered pair.
        pair_filter_results: (id1, id2) -> ``FilterResult``-like, rows 1:1 with
            ``pair_matches`` (see :func:`pair_rows`): ``inliers`` rows reach the output,
            those with a label >= 0 are refinable.
        unrefined_matches: (id1, id2) -> (M, 2) matches that reach the output but carry no
            homography (pairs never filtered, failed, or with a missing image).
        duplicate_px: keypoints of one image in one track closer than this are duplicates,
            farther ones freeze the track.
        local_affine: (k neighbours, max residual px): also give every refinable match its
            own patch homography pair from a local affine fit to its pair's nearest matches
            (:func:`.rectify.local_affine_pairs`), fitted when the walk first needs the pair
            (:meth:`TrackPlan.local_pairs`); None: the filter's pairs only.
    Returns:
        :class:`TrackPlan`.
    Raises:
        ValueError: malformed inputs (names the pair or image).
    """
    kps, offset, node_image, node_kp = _nodes(keypoints)
    pairs, homs, ea, eb, ep, el = _edges(kps, offset, pair_matches, pair_filter_results,
                                         unrefined_matches)
    total = node_image.size
    track = np.full(total, -1, np.int64)
    stats = dict.fromkeys(["tracks", "conflicting_tracks", "frozen_tracks", "frozen_keypoints",
                           "keypoints_in_tracks", "anchors", "unreached_keypoints"], 0)
    stats["unrefinable_matches"] = int((el < 0).sum())
    frozen = np.zeros(total, bool)
    anchors = np.zeros(0, np.int64)
    to_refine = 0
    if ea.size:
        _, comp = connected_components(
            coo_matrix((np.ones(ea.size), (ea, eb)), shape=(total, total)), directed=False)
        nodes = np.unique(np.concatenate([ea, eb]))
        _, track[nodes] = np.unique(comp[nodes], return_inverse=True)
        pos = np.concatenate(list(kps.values()))[nodes]
        conflict, any_two = _conflicts(track, nodes, node_image, pos, duplicate_px)
        frozen[nodes] = conflict[track[nodes]]
        stats.update(tracks=int(conflict.size), conflicting_tracks=int(any_two.sum()),
                     frozen_tracks=int(conflict.sum()), frozen_keypoints=int(frozen.sum()),
                     keypoints_in_tracks=int(nodes.size))
        ok = (el >= 0) & ~frozen[ea]
        degree = np.bincount(ea[ok], minlength=total) + np.bincount(eb[ok], minlength=total)
        cand = np.flatnonzero(degree > 0)
        # anchors: most refinable edges, ties to the lowest node (= (image_id, kp index))
        order = np.lexsort((cand, -degree[cand], track[cand]))
        first = np.ones(order.size, bool)
        first[1:] = track[cand][order][1:] != track[cand][order][:-1]
        anchors = cand[order[first]]
        to_refine = _reachable(total, ea[ok], eb[ok], anchors, cand)
        stats["anchors"] = int(anchors.size)
        stats["unreached_keypoints"] = int(
            np.isin(track[nodes], track[anchors]).sum() - anchors.size - to_refine)
    return TrackPlan(keypoints=kps, node_image=node_image, node_kp=node_kp, pairs=pairs,
                     pair_homs=homs, local_homs=None, edge_a=ea, edge_b=eb, edge_pair=ep,
                     edge_row=np.arange(ep.size) - np.searchsorted(ep, ep), edge_label=el,
                     track=track, anchors=anchors, frozen=frozen, to_refine=to_refine,
                     stats=stats,
                     local_affine=None if local_affine is None else tuple(local_affine))
