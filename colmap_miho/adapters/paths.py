"""Resolves the paths a command reads and writes and refuses any overlap (``refine --json x.db
--database x.db`` would destroy the database), by device and inode, before any work."""

from __future__ import annotations

import contextlib
import os
from collections.abc import Mapping
from pathlib import Path

from ..errors import UserError
from .model_files import MODEL_EXTENSIONS, MODEL_STEMS
from .staged_write import CHARACTER_DEVICE, check_output_path

#: SQLite's side files of a database: writing one of these corrupts the database.
SQLITE_SIDE_SUFFIXES = ("-wal", "-shm", "-journal")

PathArg = str | os.PathLike | None


def resolve(path: str | os.PathLike) -> Path:
    """The absolute, symlink-free path that writing ``path`` would reach (a missing one: its folder resolved)."""
    p = Path(path).expanduser()
    try:
        return p.resolve(strict=False)
    except (OSError, RuntimeError):  # symlink loop
        return Path(os.path.abspath(p))


def identity(path: str | os.PathLike) -> tuple[int, int] | None:
    """``(st_dev, st_ino)`` of the file ``path`` reaches, or None if it does not exist."""
    try:
        st = os.stat(path)
    except OSError:
        return None
    return st.st_dev, st.st_ino


def same_file(a: str | os.PathLike, b: str | os.PathLike) -> bool:
    """Whether ``a`` and ``b`` reach the same file (device and inode, else resolved paths)."""
    ia, ib = identity(a), identity(b)
    if ia is not None and ib is not None:
        return ia == ib
    return resolve(a) == resolve(b)


#: Where a model folder argument may keep its model (see ``reporting.gt_model.resolve_model_dir``).
MODEL_SUBFOLDERS = ("", "gt_model", "sparse/0", "0")


def model_files(folder: PathArg, label: str) -> dict[str, Path]:
    """The COLMAP model files a command writes into ``folder``, labelled for :func:`check_distinct`."""
    if folder is None:
        return {}
    names = [f"{stem}{ext}" for stem in MODEL_STEMS for ext in MODEL_EXTENSIONS]
    return {f"{label} ({name})": Path(folder) / name for name in names}


def model_input_files(folder: PathArg, label: str) -> dict[str, Path]:
    """The model files (and ``pairs_with_gt.txt``) a command may read for the model argument ``folder``."""
    if folder is None:
        return {}
    out: dict[str, Path] = {}
    for sub in MODEL_SUBFOLDERS:
        where = Path(folder) / sub if sub else Path(folder)
        out.update(model_files(where, f"{label}{'/' + sub if sub else ''}"))
    out[f"{label} (pairs_with_gt.txt)"] = Path(folder) / "pairs_with_gt.txt"
    return out


#: More files than this in an input folder are not listed one by one (see :func:`folder_files`).
MAX_LISTED_FILES = 200_000


def folder_files(folder: PathArg, label: str) -> dict[str, Path]:
    """Every file below the input ``folder`` (hidden folders skipped, at most :data:`MAX_LISTED_FILES`)."""
    if folder is None or not Path(folder).is_dir():
        return {}
    out: dict[str, Path] = {}
    root = Path(folder)
    for dirpath, dirnames, filenames in os.walk(root):
        dirnames[:] = [d for d in dirnames if not d.startswith(".")]
        for name in filenames:
            path = Path(dirpath) / name
            out[f"{label} ({path.relative_to(root)})"] = path
            if len(out) >= MAX_LISTED_FILES:
                return out
    return out


def text_model_in(folder: PathArg) -> list[str]:
    """Names of the COLMAP text-model files in ``folder`` (a mapping there would delete them)."""
    if folder is None:
        return []
    return [f"{stem}.txt" for stem in MODEL_STEMS if (Path(folder) / f"{stem}.txt").is_file()]


def refuse_text_model(folder: PathArg, label: str) -> None:
    """Refuse to map into a folder holding a COLMAP text model such as a ground truth (UserError)."""
    found = text_model_in(folder)
    if found:
        raise UserError(f"{label} {folder} holds a COLMAP text model ({', '.join(found)}) that mapping "
                        "would replace: choose another folder or move that model away")


def refuse_folder_inside(output: PathArg, out_label: str, folder: PathArg, in_label: str) -> None:
    """Refuse an output folder that is, or lies inside, the input ``folder`` (UserError naming both)."""
    if output is None or folder is None or not Path(folder).is_dir():
        return
    where, inside = resolve(output), resolve(folder)
    if where == inside or inside in where.parents:
        raise UserError(f"{out_label} {output} is {'' if where == inside else 'inside '}{in_label} {folder}: "
                        f"what it writes would land among the input files; choose a folder outside {in_label}")


def comparison_paths(output: str | os.PathLike, *, images: PathArg, database: PathArg = None,
                     gt: PathArg = None, pairs: PathArg = None, repeats: int = 1, seed: int = 0,
                     compare: bool = True) -> tuple[dict[str, Path], dict[str, Path]]:
    """The inputs and outputs of ``compare`` or ``run`` for :func:`check_distinct` (``run``'s
    ``OUTPUT/database.db`` is an input when it exists). UserError for an overlap, a link among the
    job's outputs, or a text model in a model folder."""
    out = Path(output)
    refuse_folder_inside(out, "--output", images, "--images")
    files = ["refined/database.db", "refined/refine.json"]
    if compare:
        files += ["compare.md", "compare.json", "report.html", "baseline/report.json", "refined/report.json",
                  "baseline/points.ply", "refined/points.ply",
                  *(f"plots/{name}.png" for name in ("pose_error_curves", "keypoint_displacement",
                                                     "matches_per_pair", "points_baseline", "points_refined"))]
    else:
        files.append("report.json")
    outputs = {f"--output ({name})": out / name for name in files}
    for side in ("baseline", "refined") if compare else ("refined",):
        folders = [f"{side}/model"]
        folders += [f"{side}/runs/seed{seed + k}/model" for k in range(1, max(1, repeats) if compare else 1)]
        for folder in folders:
            outputs.update(model_files(out / folder, f"--output ({folder})"))
    inputs: dict[str, Path] = {}
    for label, value in (("--database", database), ("--images", images), ("--gt", gt), ("--pairs", pairs)):
        if value is not None:
            inputs[label] = Path(value)
    inputs.update(folder_files(images, "--images"))
    inputs.update(model_input_files(gt, "--gt"))
    if database is None:  # run: extraction writes OUTPUT/database.db, or reuses it
        reused = out / "database.db"
        if reused.exists():
            inputs["--output (database.db, reused)"] = reused
        else:
            outputs["--output (database.db)"] = reused
    check_distinct(inputs, outputs)  # first: an overlap names the input (a GT inside OUTPUT, say)
    refuse_links_below(out, outputs)
    for model in sorted({p.parent for p in outputs.values() if p.name == "cameras.bin"}):
        refuse_text_model(model, f"--output ({model.relative_to(out)})")
    return inputs, outputs


def refuse_links_below(root: str | os.PathLike, outputs: Mapping[str, PathArg]) -> None:
    """Refuse a symbolic link among the folders and files a command makes below ``root`` (``root``
    itself may be a link); UserError naming the link."""
    base = Path(root)
    for label, path in _clean(outputs).items():
        try:
            parts = path.relative_to(base).parts
        except ValueError:
            continue
        where = base
        for part in parts:
            where = where / part
            if os.path.islink(where):
                short = label.split(" (", 1)[0]
                rel = where.relative_to(base)
                raise UserError(f"{short} ({rel}) {where} is a symbolic link (to {os.readlink(where)}); "
                                "colmap-miho writes there only into what it makes itself, never through a link: "
                                f"remove the link or choose another {short}")


def leaves_folder(name: str) -> bool:
    """Whether the image name ``name`` is absolute or climbs out of the image folder with ``..``."""
    if not name or os.path.isabs(name) or name.startswith(("/", "\\")):
        return True
    parts = os.path.normpath(name.replace("\\", "/")).split("/")
    return parts[0] == ".."


def names_of_one_file(image_dir: str | os.PathLike, names: Mapping[int, str]) -> list[list[tuple[int, str]]]:
    """Groups of database images ``(image_id, name)`` whose names lead to one file of ``image_dir``."""
    groups: dict[object, list[tuple[int, str]]] = {}
    folder = Path(image_dir)
    for image_id in sorted(names):
        name = names[image_id]
        if leaves_folder(name):
            continue
        key: object = os.path.normpath(name.replace("\\", "/"))
        with contextlib.suppress(OSError, ValueError):
            st = os.stat(folder / name)
            key = (st.st_dev, st.st_ino)
        groups.setdefault(key, []).append((int(image_id), name))
    return [g for g in groups.values() if len(g) > 1]


def _clean(paths: Mapping[str, PathArg]) -> dict[str, Path]:
    return {label: Path(p) for label, p in paths.items() if p is not None and str(p) != ""}


def check_distinct(inputs: Mapping[str, PathArg], outputs: Mapping[str, PathArg]) -> None:
    """Refuse a command whose outputs overlap its inputs or each other (UserError, exit 2). An input
    database also protects its SQLite side files; a folder protects only itself, so list the files
    read or written inside one."""
    ins, outs = _clean(inputs), _clean(outputs)
    # one stat and one resolve per path: input folders may list thousands of files
    by_identity: dict[tuple[int, int], str] = {}
    by_path: dict[Path, str] = {}
    for label, inp in ins.items():
        ident = identity(inp)
        if ident is not None:
            by_identity.setdefault(ident, label)
        by_path.setdefault(resolve(inp), label)
    devices = set()
    for out_label, out in outs.items():
        if check_output_path(out, out_label) == CHARACTER_DEVICE:  # written through: /dev/null twice is fine
            devices.add(out_label)
            continue
        ident, where = identity(out), resolve(out)
        hit = by_identity.get(ident) if ident is not None else by_path.get(where)
        if hit is not None:
            raise UserError(f"{out_label} {out} is the same file as {hit} {ins[hit]}; it would "
                            f"be overwritten: choose another {out_label} path")
        for suffix in SQLITE_SIDE_SUFFIXES:
            if where.name.endswith(suffix):
                base = where.with_name(where.name[: -len(suffix)])
                if base in by_path:
                    label = by_path[base]
                    raise UserError(f"{out_label} {out} is SQLite's {suffix} file of {label} "
                                    f"{ins[label]}: choose another {out_label} path")
    labels = [label for label in outs if label not in devices]
    seen: dict[Path, str] = {}
    for label in labels:
        key = resolve(outs[label])
        if key in seen:
            raise UserError(f"{seen[key]} and {label} are the same file ({outs[label]}): "
                            f"choose another {label} path")
        seen[key] = label
    linked: dict[tuple[int, int], str] = {}
    for label in labels:  # hard links between existing outputs
        ident = identity(outs[label])
        if ident is None:
            continue
        if ident in linked:
            a = linked[ident]
            raise UserError(f"{a} and {label} are the same file ({outs[a]}): choose another {label} path")
        linked[ident] = label
