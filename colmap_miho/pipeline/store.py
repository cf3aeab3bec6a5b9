"""Run store: the finished work of one ``refine`` run on disk (``.<output name>.miho-run/`` beside
the output), so that a killed run resumes. Its files are written atomically, tied to their run and
checked when read back (:mod:`.store_checks`); links are refused."""

from __future__ import annotations

import contextlib
import dataclasses
import fcntl
import hashlib
import json
import logging
import os
import re
import secrets
from collections.abc import Iterator, Mapping
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..adapters.filesystem import write_atomic
from ..errors import UserError
from ..types import Pair
from ..version import __version__
from .records import FilteredPairs, PairOutcome
from .store_checks import (
    ChunkIndex,
    GroupResult,
    StoreDamaged,
    check_filter_chunk,
    check_group,
    read_manifest,
    read_npz,
    stored_array,
)

log = logging.getLogger(__name__)

MANIFEST = "manifest.json"
LOCK = "lock"
#: Format of the store's files; a store of another format is not resumed.
STORE_VERSION = 1
#: Recipe tables whose values change a run's result (``mapping`` is not used by ``refine``).
RESULT_TABLES = ("filter", "ncc", "lsm", "rectify", "tracks", "pipeline", "match_check")
#: keys left out of a table: ``pipeline``'s that only bound memory, ``ncc``'s nested tables (their own).
NOT_RESULT_KEYS = {"pipeline": ("memory_budget_mb",), "ncc": ("lsm", "rectify")}

_FILTER_FILE = re.compile(r"^filter-(\d{6})\.npz$")
_GROUP_FILE = re.compile(r"^group-(\d{6})\.npz$")
#: Every name the store makes: its files, and their temporary names while being written
#: (:func:`~colmap_miho.adapters.filesystem.temp_beside`).
_OWN_FILE = re.compile(r"^(lock|manifest\.json|(filter|group)-\d{6}\.npz|stage-[a-z_]+\.npz)$")
_OWN_TEMP = re.compile(r"^\.(manifest\.json|(filter|group)-\d{6}\.npz|stage-[a-z_]+\.npz)\.[A-Za-z0-9_]+\.tmp$")


def store_folder(output: Path) -> Path:
    """``<output dir>/.<output name>.miho-run`` (the run store of ``output``)."""
    output = Path(output)
    return output.with_name(f".{output.name}.miho-run")


def check_no_links(folder: Path) -> None:
    """Refuse a run store reached through a symbolic link (the folder or one of its files): the
    store would read, write or delete through it. UserError names the link."""
    folder = Path(folder)
    if folder.is_symlink():
        raise UserError(f"the run folder {folder} is a symbolic link (to {os.readlink(folder)}); a run keeps its "
                        "work only in a folder of its own and never follows a link there: remove the link "
                        "or choose another --output")
    if folder.exists() and not folder.is_dir():
        raise UserError(f"{folder} is a file, not the run folder a run keeps its work in (it is never replaced): "
                        "remove it or choose another --output")
    if not folder.is_dir():
        return
    for p in folder.iterdir():
        if not (_OWN_FILE.match(p.name) or _OWN_TEMP.match(p.name)):
            continue
        if p.is_symlink():
            raise UserError(f"{p} is a symbolic link (to {os.readlink(p)}) in the run folder, where only "
                            "colmap-miho's own files belong; nothing was read or deleted through it: remove it and "
                            "run again")
        if not p.is_file():
            raise UserError(f"{p} is not a regular file, in the run folder, where only colmap-miho's own files "
                            "belong; nothing was deleted: remove it and run again")


def content_hash(path: Path, chunk: int = 1 << 22) -> str:
    """BLAKE2b (128-bit) of ``path``'s bytes: size and time alone miss a ``cp -p`` of another database."""
    digest = hashlib.blake2b(digest_size=16)
    with open(path, "rb") as fh:
        while block := fh.read(chunk):
            digest.update(block)
    return digest.hexdigest()


def run_fingerprint(database: Path, image_dir: Path, recipe, seed: int, device: str) -> dict:
    """What a run's stored work depends on, as JSON data compared on resume."""
    st = Path(database).stat()
    tables = {}
    for name in RESULT_TABLES:
        values = dataclasses.asdict(getattr(recipe, name))
        for key in NOT_RESULT_KEYS.get(name, ()):
            values.pop(key, None)
        tables[name] = values
    data = {"store_version": STORE_VERSION, "colmap_miho": __version__,
            "database": {"path": str(Path(database).resolve()), "size": st.st_size,
                         "blake2b": content_hash(Path(database))},
            "images": str(Path(image_dir).resolve()), "recipe": tables, "seed": int(seed), "device": device}
    return json.loads(json.dumps(data, default=str))  # enums -> str, tuples -> lists


def fingerprint_difference(old: dict, new: dict) -> str | None:
    """What differs between two fingerprints in words ("the seed", ...), or None."""
    words = {"store_version": "store format", "colmap_miho": "colmap-miho version",
             "database": "input database (its content changed since)",
             "images": "image folder", "seed": "seed", "device": "device"}
    for key in sorted(set(old) | set(new)):
        if old.get(key) == new.get(key):
            continue
        if key == "recipe":
            a, b = old.get(key) or {}, new.get(key) or {}
            for table in sorted(set(a) | set(b)):
                ta, tb = a.get(table) or {}, b.get(table) or {}
                for name in sorted(set(ta) | set(tb)):
                    if ta.get(name) != tb.get(name):
                        return f"recipe value {table}.{name} ({ta.get(name)!r} then, {tb.get(name)!r} now)"
            return "recipe"
        return words.get(key, key)
    return None


@dataclass(frozen=True)
class FilterCounts:
    """Totals over the stored filter chunks."""

    chunks: int = 0
    pairs: int = 0
    pairs_ok: int = 0
    matches_in: int = 0
    matches_kept: int = 0


def _atomic_savez(path: Path, arrays: dict[str, np.ndarray]) -> None:
    write_atomic(path, lambda fh: np.savez(fh, **arrays))  # type: ignore[arg-type]  # numpy stubs: allow_pickle kw


def _atomic_write_text(path: Path, text: str) -> None:
    write_atomic(path, lambda fh: fh.write(text.encode("utf-8")))


class RunStore:
    """The open run store of one run; make it with :meth:`open`."""

    def __init__(self, folder: Path, manifest: dict, lock_fd: int) -> None:
        self.folder = Path(folder)
        self.manifest = manifest
        self._lock_fd: int | None = lock_fd
        self._chunks: dict[int, ChunkIndex] = {}
        self._pairs: set[Pair] | None = None  # the run's plan, once expect() gives it
        self._num_keypoints: dict[int, int] | None = None
        seen: dict[Pair, Path] = {}
        for index, path in self._files(_FILTER_FILE):
            chunk = check_filter_chunk(self._read(path), path)
            for a, b in chunk.pairs.tolist():
                if (a, b) in seen:
                    raise StoreDamaged(path, f"it holds pair ({a}, {b}), which {seen[(a, b)].name} holds too")
                seen[(a, b)] = path
            self._chunks[index] = chunk

    # -- opening, closing --------------------------------------------------------------------
    @classmethod
    def open(cls, folder: Path, fingerprint: dict, *, resume: bool = False, restart: bool = False) -> RunStore:
        """Open (create) the store at ``folder`` for ``fingerprint``. UserError when another run holds
        it, when finished work is there without ``resume``/``restart``, or when it changed."""
        folder = Path(folder)
        if resume and restart:
            raise UserError("use either --resume or --restart, not both")
        check_no_links(folder)
        try:
            folder.mkdir(exist_ok=True)
            # O_NOFOLLOW: a link put there after the check is not opened either
            lock_fd = os.open(folder / LOCK, os.O_RDWR | os.O_CREAT | os.O_NOFOLLOW, 0o644)
        except OSError as exc:
            check_no_links(folder)  # a link made meanwhile: that line
            raise UserError(f"cannot create the run folder {folder}: {exc.strerror or exc}") from None
        try:
            fcntl.flock(lock_fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError:
            os.close(lock_fd)
            raise UserError(f"another colmap-miho run is using {folder} (it writes the same output); "
                            "wait for it to finish or choose another output") from None
        try:
            return cls._open_locked(folder, fingerprint, lock_fd, resume=resume, restart=restart)
        except BaseException:
            os.close(lock_fd)
            raise

    @classmethod
    def _open_locked(cls, folder: Path, fingerprint: dict, lock_fd: int, *, resume: bool,
                     restart: bool) -> RunStore:
        check_no_links(folder)  # again, under the lock: no other run of ours changes it now
        manifest_path = folder / MANIFEST
        has_work = any(_FILTER_FILE.match(p.name) or _GROUP_FILE.match(p.name) for p in folder.iterdir())
        if has_work and not restart:
            old = read_manifest(manifest_path)  # damaged: --restart is the only way on
            if not resume:
                raise UserError(f"an interrupted run left its finished work in {folder}: pass --resume to "
                                "continue it, or --restart to discard it and start again")
            what = fingerprint_difference(old["fingerprint"], fingerprint)
            if what is not None:
                raise UserError(f"--resume: the interrupted run in {folder} was made with another {what}; "
                                "resume with the same inputs and options, or pass --restart to discard it")
            log.info("resuming the interrupted run from %s", folder)
            return cls(folder, old, lock_fd)
        if resume:
            log.info("--resume: no finished work in %s; starting from the beginning", folder)
        cls._clear(folder)
        manifest = {"fingerprint": fingerprint, "run_id": secrets.token_hex(16)}
        _atomic_write_text(manifest_path, json.dumps(manifest, indent=1) + "\n")
        return cls(folder, manifest, lock_fd)

    @staticmethod
    def _clear(folder: Path) -> None:
        """Delete the store's own files in ``folder``, keep the lock; anything else is left."""
        for p in _own_entries(folder):
            if p.name != LOCK:
                p.unlink(missing_ok=True)

    def has_work(self) -> bool:
        """Whether any chunk or group is stored."""
        return bool(self._chunks) or any(True for _ in self._files(_GROUP_FILE))

    def close(self) -> None:
        """Release the lock; the files stay."""
        if self._lock_fd is not None:
            os.close(self._lock_fd)
            self._lock_fd = None

    def remove(self) -> None:
        """Delete the store's own files, then the folder if empty (others' files kept, with a warning)."""
        with contextlib.suppress(OSError):
            for p in _own_entries(self.folder):  # the lock last, still held: no other run takes the folder
                if p.name != LOCK:
                    p.unlink(missing_ok=True)
            (self.folder / LOCK).unlink(missing_ok=True)
            others = sorted(p.name for p in self.folder.iterdir())
            if others:
                log.warning("the run folder %s holds files that are not colmap-miho's (%s): left as they are",
                            self.folder, ", ".join(others[:5]) + (", ..." if len(others) > 5 else ""))
            else:
                self.folder.rmdir()
        self.close()

    def _read(self, path: Path) -> dict[str, np.ndarray]:
        """Read one of this store's files, checked to be this run's own; StoreDamaged otherwise."""
        arrays = read_npz(path)
        run_id, name = arrays.pop("run_id", None), arrays.pop("file_name", None)
        want = self.manifest["run_id"]  # a non-empty string (read_manifest)
        if run_id is None or run_id.dtype.kind != "U" or str(run_id) != want:
            raise StoreDamaged(path, "it was written by another run than the one this folder's manifest records")
        if name is None or name.dtype.kind != "U" or str(name) != path.name:
            raise StoreDamaged(path, f"it was written as {name if name is None else str(name)}, not under this name")
        return arrays

    def _save(self, path: Path, arrays: dict[str, np.ndarray]) -> None:
        _atomic_savez(path, {**arrays, "run_id": np.array(self.manifest["run_id"]), "file_name": np.array(path.name)})

    def _files(self, pattern: re.Pattern) -> list[tuple[int, Path]]:
        out = []
        for p in self.folder.iterdir():
            m = pattern.match(p.name)
            if m:
                out.append((int(m.group(1)), p))
        return sorted(out)

    # -- what the work must fit --------------------------------------------------------------
    def expect(self, pairs, num_keypoints) -> None:
        """Give the run's plan (``pairs``, ``num_keypoints``) the stored work must fit, checked now
        and on every later read; StoreDamaged for a foreign pair or an out-of-range keypoint index."""
        self._pairs = {(int(a), int(b)) for a, b in pairs}
        self._num_keypoints = {int(i): int(n) for i, n in num_keypoints.items()}
        for index, chunk in self._chunks.items():
            self._check_fits(chunk, self.folder / f"filter-{index:06d}.npz")

    def _check_fits(self, chunk: ChunkIndex, path: Path) -> None:
        if self._pairs is None or self._num_keypoints is None:
            return
        for (a, b), (top_a, top_b) in zip(chunk.pairs.tolist(), chunk.top.tolist(), strict=True):
            if (a, b) not in self._pairs:
                raise StoreDamaged(path, f"it holds pair ({a}, {b}), which is not a pair this run filters")
            for image_id, top in ((a, top_a), (b, top_b)):
                n = self._num_keypoints.get(image_id, 0)
                if top >= n:
                    raise StoreDamaged(path, f"its matches of pair ({a}, {b}) use keypoint {top} of image "
                                             f"{image_id}, which has {n} keypoints")

    # -- filter chunks -----------------------------------------------------------------------
    def filtered_pairs(self) -> set[Pair]:
        """Pairs (image_id1, image_id2) of the stored filter chunks."""
        return {(int(a), int(b)) for c in self._chunks.values() for a, b in c.pairs}

    def filter_counts(self) -> FilterCounts:
        """Chunks, pairs, successful pairs and their matches in / kept, over the stored chunks."""
        cs = list(self._chunks.values())
        return FilterCounts(chunks=len(cs), pairs=sum(len(c.pairs) for c in cs),
                            pairs_ok=sum(int(c.success.sum()) for c in cs),
                            matches_in=sum(c.matches for c in cs), matches_kept=sum(c.kept for c in cs))

    def next_filter_index(self) -> int:
        """The first chunk index not used yet."""
        return max(self._chunks, default=-1) + 1

    def save_filter_chunk(self, index: int, pairs: list[Pair], matches: list[np.ndarray],
                          outcomes: list[PairOutcome]) -> None:
        """Store one finished chunk: ``pairs``, their matches ``(M, 2)`` and outcomes; failed pairs
        are not kept (they are written back unchanged)."""
        if index in self._chunks:
            raise RuntimeError(f"filter chunk {index} is stored already")
        stored = self.filtered_pairs()
        if any(p in stored for p in pairs) or len(set(pairs)) != len(pairs):
            raise RuntimeError(f"filter chunk {index} holds a pair that is stored already")
        ok = np.array([o.success for o in outcomes], bool)
        rows = [len(m) if s else 0 for m, s in zip(matches, ok, strict=True)]
        homs = [len(o.patch_homographies) if s else 0 for o, s in zip(outcomes, ok, strict=True)]
        sel = [k for k in range(len(pairs)) if ok[k]]
        arrays = {
            "pairs": np.asarray(pairs, np.int64).reshape(-1, 2),
            "success": ok,
            "offsets": np.concatenate([[0], np.cumsum(rows)]).astype(np.int64),
            "kept": np.array([int(np.count_nonzero(o.inliers)) if s else 0 for o, s in zip(outcomes, ok, strict=True)],
                             np.int64),
            "matches": _cat([matches[k] for k in sel], (0, 2), np.uint32),
            "inliers": _cat([outcomes[k].inliers for k in sel], (0,), bool),
            "labels": _cat([outcomes[k].labels for k in sel], (0,), np.int64),
            "hom_offsets": np.concatenate([[0], np.cumsum(homs)]).astype(np.int64),
            "patch_homographies": _cat([outcomes[k].patch_homographies for k in sel], (0, 2, 3, 3), np.float64),
        }
        path = self.folder / f"filter-{index:06d}.npz"
        self._save(path, arrays)
        self._chunks[index] = check_filter_chunk(arrays, path)

    def iter_filter_chunks(self) -> Iterator[FilteredPairs]:
        """The successful pairs of each stored chunk, one chunk at a time (chunk order)."""
        for index, path in self._files(_FILTER_FILE):
            if index not in self._chunks:
                continue
            z = self._read(path)
            chunk = check_filter_chunk(z, path)
            known = self._chunks[index]
            if not (np.array_equal(chunk.pairs, known.pairs) and np.array_equal(chunk.success, known.success)
                    and np.array_equal(chunk.top, known.top)):
                raise StoreDamaged(path, "it changed since the run opened it")
            self._check_fits(chunk, path)
            pairs, ok, off, hoff = chunk.pairs, chunk.success, z["offsets"], z["hom_offsets"]
            matches, inliers, labels, homs = (z["matches"], z["inliers"], z["labels"].astype(np.int64),
                                              z["patch_homographies"].astype(np.float64))
            out: FilteredPairs = {}
            for k in np.flatnonzero(ok):
                a, b = int(off[k]), int(off[k + 1])
                out[(int(pairs[k, 0]), int(pairs[k, 1]))] = (matches[a:b], PairOutcome(
                    inliers=inliers[a:b], labels=labels[a:b],
                    patch_homographies=homs[int(hoff[k]):int(hoff[k + 1])], success=True))
            yield out

    def load_filtered(self) -> FilteredPairs:
        """The successful pairs of all stored chunks."""
        out: FilteredPairs = {}
        for chunk in self.iter_filter_chunks():
            out.update(chunk)
        return out

    # -- refine groups -----------------------------------------------------------------------
    def refine_groups(self, plan_key: dict, image_sizes: Mapping[int, tuple[int, int]] | None = None
                      ) -> dict[int, GroupResult]:
        """The stored refine groups if made under ``plan_key`` (else dropped and ``plan_key``
        recorded), checked against ``image_sizes`` when given."""
        plan_key = json.loads(json.dumps(plan_key, default=str))
        files = self._files(_GROUP_FILE)
        if self.manifest.get("refine_plan") != plan_key:
            if files:
                log.info("the stored refine groups were planned for %s, this run for %s: refining them again",
                         self.manifest.get("refine_plan"), plan_key)
            for _, path in files:
                path.unlink(missing_ok=True)
            self.manifest = dict(self.manifest, refine_plan=plan_key)
            _atomic_write_text(self.folder / MANIFEST, json.dumps(self.manifest, indent=1) + "\n")
            return {}
        return {index: check_group(self._read(path), path, self._num_keypoints, image_sizes)
                for index, path in files}

    def group_path(self, index: int) -> Path:
        """The file of refine group ``index``."""
        return self.folder / f"group-{index:06d}.npz"

    def save_group(self, index: int, moved: dict[int, tuple[np.ndarray, np.ndarray]], stats: dict) -> None:
        """Store one refine group: image id -> (indices ``(K,)``, positions ``(K, 2)`` pixels) and its stats."""
        ids = sorted(moved)
        sizes = [len(moved[i][0]) for i in ids]
        self._save(self.group_path(index), {
            "image_ids": np.asarray(ids, np.int64),
            "offsets": np.concatenate([[0], np.cumsum(sizes)]).astype(np.int64),
            "idx": _cat([np.asarray(moved[i][0], np.int64) for i in ids], (0,), np.int64),
            "xy": _cat([np.asarray(moved[i][1], np.float64).reshape(-1, 2) for i in ids], (0, 2), np.float64),
            "stats": np.array(json.dumps(stats, default=float)),
        })

    # -- results of once-per-run stages ----------------------------------------------------
    def save_stage(self, name: str, arrays: dict[str, np.ndarray], meta: dict) -> None:
        """Store stage ``name``'s arrays and JSON-ready ``meta``."""
        if not re.fullmatch(r"[a-z_]+", name):
            raise ValueError(f"stage name must be lower-case letters and _, got {name!r}")
        self._save(self.folder / f"stage-{name}.npz", {**arrays, "meta": np.array(json.dumps(meta, default=float))})

    def load_stage(self, name: str) -> tuple[dict[str, np.ndarray], dict] | None:
        """Stage ``name``'s stored (arrays, meta), or None; StoreDamaged for a broken file."""
        path = self.folder / f"stage-{name}.npz"
        if not path.is_file():
            return None
        arrays = self._read(path)
        try:
            meta = json.loads(str(stored_array(arrays, "meta", path)))
        except (ValueError, RecursionError) as exc:  # not JSON, or nested past reading
            raise StoreDamaged(path, exc) from None
        if not isinstance(meta, dict):
            raise StoreDamaged(path, "its meta is not a JSON object")
        return {k: v for k, v in arrays.items() if k != "meta"}, meta


def _own_entries(folder: Path) -> list[Path]:
    return [p for p in Path(folder).iterdir()
            if (_OWN_FILE.match(p.name) or _OWN_TEMP.match(p.name)) and not p.is_symlink() and p.is_file()]


def _cat(parts: list[np.ndarray], empty_shape: tuple, dtype) -> np.ndarray:
    return np.concatenate([np.asarray(p, dtype) for p in parts]) if parts else np.zeros(empty_shape, dtype)
