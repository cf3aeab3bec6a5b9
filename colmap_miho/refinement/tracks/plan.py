"""The track plan's data: nodes, edges, tracks and anchors, and its splits into groups and
parts for the walk and the workers (built by :func:`.build.build_track_plan`, whose
module states the rules)."""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass, field, replace

import numpy as np

from ...match_tracks import components, distinct

#: Most entries of the padded (units, longest image tuple) table :func:`_by_image_tuple`
#: sorts with numpy; larger plans sort the tuples in Python.
MAX_TUPLE_TABLE = 1 << 24


def _by_image_tuple(key_unit: np.ndarray, key_image: np.ndarray, bounds: np.ndarray
                    ) -> tuple[np.ndarray, np.ndarray]:
    """Units sorted by their sorted image tuples (lexicographically, a tuple before its
    extensions; ties by unit), and the starts of the runs of equal tuples in that order.

    Args:
        key_unit, key_image: (N,) int64 the (unit, image rank) pairs, sorted.
        bounds: (U + 1,) int64 start of each unit's pairs.
    Returns:
        (order (U,) int64 units, block (B + 1,) int64 positions in ``order`` where a run of
        equal tuples starts, and U last).
    """
    n_units = bounds.size - 1
    count = np.diff(bounds)
    width = int(count.max())
    if n_units * width <= MAX_TUPLE_TABLE:
        table = np.full((n_units, width), -1, np.int64)  # -1: shorter tuples first
        table[key_unit, np.arange(key_unit.size) - bounds[key_unit]] = key_image
        order = np.lexsort((np.arange(n_units), *table.T[::-1]))
        rows = table[order]
        new = np.any(rows[1:] != rows[:-1], axis=1)
    else:
        tuples = [tuple(key_image[bounds[u]:bounds[u + 1]].tolist()) for u in range(n_units)]
        order = np.array(sorted(range(n_units), key=lambda u: (tuples[u], u)), np.int64)
        new = np.array([tuples[a] != tuples[b] for a, b in zip(order[1:], order[:-1], strict=True)],
                       bool)
    block = np.flatnonzero(np.concatenate([[True], new, [True]]))
    return order.astype(np.int64), block


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
            (``local_affine``), indexed by ``edge_row``. Plans from :func:`~.build.build_track_plan`
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
        local_inputs: None, or for a group (:meth:`TrackPlan.with_local_inputs`) per pair
            what its own walk needs to fit the local affine pairs of its edges: ``(x1, x2,
            labels, at, fit)``, the (n, 2) float64 positions and (n,) int64 labels of the
            source pair's edges in the clusters of this group's edges (in the source's row
            order), the (E'_p,) int64 index into them of each of this group's edges of the
            pair and (E'_p,) bool whether the walk refines along it.
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
    local_inputs: tuple | None = None
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
        None without ``local_affine``; fitted on first use (only along :meth:`walk_steps`, the
        others keep the filter's pair) and kept until :meth:`release_local`. A group carries
        its own (:meth:`attach_local`) or fits them from :attr:`local_inputs`, the same bits.

        Raises:
            ValueError: a group whose local pairs were not attached.
        """
        if self.local_homs is not None:
            return self.local_homs[p]
        if self.local_affine is None:
            return None
        if self.local_inputs is not None:
            if p not in self._local_cache:
                from ..rectify.local_affine import local_affine_pairs

                x1, x2, labels, at, fit = self.local_inputs[p]
                want = np.zeros(labels.size, bool)
                want[at[fit]] = True
                k, max_residual_px = self.local_affine
                self._local_cache[p] = local_affine_pairs(
                    x1, x2, labels, self.pair_homs[p], k=k, max_residual_px=max_residual_px,
                    fit=want, rows=at)
            return self._local_cache[p]
        if self.source_pairs is not None:
            raise ValueError("this group has no local affine pairs: attach them with "
                             "attach_local of the plan it came from")
        if p not in self._local_cache:
            from ..rectify.local_affine import local_affine_pairs

            lo, hi = np.searchsorted(self.edge_pair, [p, p + 1])
            id1, id2 = self.pairs[p]
            x1 = self.keypoints[id1][self.node_kp[self.edge_a[lo:hi]]]
            x2 = self.keypoints[id2][self.node_kp[self.edge_b[lo:hi]]]
            k, max_residual_px = self.local_affine
            self._local_cache[p] = local_affine_pairs(
                x1, x2, self.edge_label[lo:hi], self.pair_homs[p], k=k,
                max_residual_px=max_residual_px, fit=self.walk_steps()[lo:hi])
        return self._local_cache[p]

    def release_local(self, pairs: Iterable[int] | np.ndarray) -> None:
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

    def with_local_inputs(self, group: TrackPlan) -> TrackPlan:
        """``group`` (from :meth:`groups` of this plan) with what it needs to fit the local
        affine pairs of its edges itself (:attr:`local_inputs`; e.g. in the worker that walks
        it, instead of here): per pair, the edges of the clusters its own edges belong to.
        A match's fit depends only on the edges of its cluster, so these are the pairs
        :meth:`attach_local` gives, bit for bit. Itself when this plan has no
        ``local_affine``."""
        if self.local_affine is None or group.local_homs is not None:
            return group
        if group.source_pairs is None or group.source_rows is None:
            raise ValueError("with_local_inputs takes a group made by groups() of this plan")
        starts = np.searchsorted(group.edge_pair, np.arange(len(group.pairs) + 1))
        steps = self.walk_steps()
        inputs = []
        for q, sp in enumerate(group.source_pairs.tolist()):
            lo, hi = np.searchsorted(self.edge_pair, [sp, sp + 1])
            rows = group.source_rows[starts[q]:starts[q + 1]]
            labels = self.edge_label[lo:hi]
            used = np.zeros(len(self.pair_homs[sp]) + 1, dtype=bool)  # last: label -1
            used[labels[rows]] = True
            keep = np.flatnonzero(used[labels])
            id1, id2 = self.pairs[sp]
            ea, eb = self.edge_a[lo:hi][keep], self.edge_b[lo:hi][keep]
            inputs.append((self.keypoints[id1][self.node_kp[ea]],
                           self.keypoints[id2][self.node_kp[eb]], labels[keep],
                           np.searchsorted(keep, rows), steps[lo:hi][rows]))
        return replace(group, local_inputs=tuple(inputs))

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
        _, comp = components(ea, eb, total)
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
        nodes = distinct(np.concatenate([ea, eb, anchors]), self.num_nodes)
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
            keypoints={int(i): self.keypoints[int(i)] for i in distinct(node_image)},
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
        """Whole walked units packed into compact groups (:meth:`subset`) of at most
        ``max_images`` images and ``max_edges`` refinable edges (a larger unit is its own
        group). Units are swept in the order of their sorted image ids, so consecutive groups
        share images; walking the groups one by one moves the keypoints exactly as a walk of
        the whole plan. Local affine pairs: :meth:`attach_local`, group by group.
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
        # the (unit, image) pairs, sorted, as one int64 code each (np.unique on rows is slow);
        # images as their rank among the plan's (the same order as their ids)
        ids, img = np.unique(np.concatenate([img_a, img_b]), return_inverse=True)
        code = distinct(np.concatenate([eu, eu]) * ids.size + img.reshape(-1))
        key_unit, key_image = code // ids.size, code % ids.size
        bounds = np.searchsorted(key_unit, np.arange(anchors.size + 1))
        order, block = _by_image_tuple(key_unit, key_image, bounds)
        n_edges = np.bincount(eu, minlength=anchors.size)[order]
        cum = np.concatenate([[0], np.cumsum(n_edges)])
        limit = max_edges or eu.size
        group_of = np.empty(anchors.size, np.int64)  # by position in ``order``
        g, current, edges, cap = -1, set[int](), 0, max_images
        for s, e in zip(block[:-1].tolist(), block[1:].tolist(), strict=True):
            u = int(order[s])
            mine = set(key_image[bounds[u]:bounds[u + 1]].tolist())
            both = current | mine
            edges += int(n_edges[s])
            if g < 0 or len(both) > max(cap, len(mine)) or edges > limit:
                g, both, edges, cap = g + 1, mine, int(n_edges[s]), max_images
            group_of[s] = g
            current, cap = both, max(cap, len(mine))
            # the block's other units use the same images: only the edge bound can cut
            i = s + 1
            while i < e:
                # the first unit that takes the group past the bound starts the next one
                k = max(i, int(np.searchsorted(cum, limit - edges + cum[i], side="right")) - 1)
                if k >= e:
                    group_of[i:e] = g
                    edges += int(cum[e] - cum[i])
                    break
                group_of[i:k] = g
                g, edges, current, cap = g + 1, int(n_edges[k]), mine, max(max_images, len(mine))
                group_of[k] = g
                i = k + 1
        unit_group = np.empty(anchors.size, np.int64)
        unit_group[order] = group_of
        return self._split(e_ids, unit_group[eu], anchors, unit_group, g + 1)

    def _split(self, e_ids: np.ndarray, edge_group: np.ndarray, anchors: np.ndarray,
               anchor_group: np.ndarray, n: int) -> list[TrackPlan]:
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
