"""Structure-from-Motion with pycolmap: incremental (default) or global mapping.

:func:`run_mapping` maps a COLMAP database and writes the largest model (by registered images)
to one folder. It never opens the caller's database: pycolmap migrates the schema of any
database it opens, so mapping reads a private copy made first.

Known cameras: :class:`MappingConfig` (``camera_model``, ``camera_params``) or ``intrinsics``
(e.g. the GT's) are written into that copy, never into the caller's file, and
``refine_intrinsics`` (:class:`RefineIntrinsics`) says what bundle adjustment may change.

COLMAP's own log (glog) goes to a file in the output folder (``colmap_log.*``) unless
``verbose``; errors still reach stderr. A tqdm bar fed by the incremental mapper's callbacks
shows registered images when ``progress`` is set.
"""

from __future__ import annotations

import contextlib
import logging
import math
import time
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path

from ..enums import Mapper, StrEnum
from ..errors import InvalidInput, RunFailed
from ..validation import MAX_MATCHES, check_bounds, within
from .colmap_log import colmap_log_to_file, latest_log

log = logging.getLogger(__name__)



@dataclass(frozen=True, kw_only=True)
class MappingResult:
    """What :func:`run_mapping` produced.

    Attributes:
        success: at least one model with two or more registered images.
        output: folder of the written (largest) model, or None.
        mapper: "incremental" or "global".
        seed: the mapper's random seed.
        num_models: models found by the mapper.
        num_images: images in the database.
        num_reg_images, num_points3D: of the largest model (0 on failure).
        seconds: wall time of the mapper call.
        cameras: the largest model's cameras after mapping, ``[{"camera_id", "model",
            "width", "height", "params"}]`` (params in COLMAP's order and pixel convention).
        refine_intrinsics: what bundle adjustment was allowed to change.
        log_file: COLMAP's log file (None when verbose).
        reconstruction: the largest ``pycolmap.Reconstruction`` (not serialised).
    """

    success: bool
    output: Path | None
    mapper: str
    seed: int = 0
    num_models: int = 0
    num_images: int = 0
    num_reg_images: int = 0
    num_points3D: int = 0
    seconds: float = 0.0
    cameras: list = field(default_factory=list)
    refine_intrinsics: str = "default"
    log_file: Path | None = None
    reconstruction: object = field(default=None, repr=False, compare=False)

    def to_dict(self) -> dict:
        d = asdict(self)
        d.pop("reconstruction")
        d["output"] = str(self.output) if self.output else None
        d["log_file"] = str(self.log_file) if self.log_file else None
        return d


class RefineIntrinsics(StrEnum):
    """What bundle adjustment may change in the cameras (``--refine-intrinsics``).

    ``all``: focal length, principal point and extra (distortion) parameters; ``default``:
    COLMAP's own choice (focal length and extra parameters, principal point fixed); ``none``:
    keep the intrinsics in the database (for known, calibrated cameras).
    """

    ALL = "all"
    DEFAULT = "default"
    NONE = "none"


#: (refine_focal_length, refine_principal_point, refine_extra_params), None = COLMAP's default
_REFINE_FLAGS = {RefineIntrinsics.ALL: (True, True, True), RefineIntrinsics.NONE: (False, False, False)}


def parse_camera_params(model: str, params: str) -> tuple[float, ...]:
    """COLMAP's comma-separated parameter list for ``model`` as floats.

    Args:
        model: COLMAP camera model name (any case).
        params: e.g. ``"1379.7,1382.1,760.8,503.9"`` for PINHOLE (fx, fy, cx, cy), COLMAP pixel
            convention; "" gives ().

    Raises:
        ValueError: unknown model, a value that is not a finite number, or a count that does not
            fit the model (one line naming the model and the count it takes).
    """
    from ..adapters.cameras import model_num_params

    n = model_num_params(model)
    if not params.strip():
        return ()
    values = []
    for item in params.split(","):
        try:
            v = float(item)
        except ValueError:
            raise InvalidInput(f"camera_params: {item.strip()!r} is not a number (in {params!r})") from None
        if not math.isfinite(v):
            raise InvalidInput(f"camera_params: {item.strip()!r} is not a finite number")
        values.append(v)
    if len(values) != n:
        raise InvalidInput(f"camera_params: camera model {model.upper()} takes {n} parameters, got {len(values)} "
                         f"({params!r})")
    # A focal length is in pixels: width / (2 tan(fov / 2)). 1e9 px is a field of view of 1e-4 deg
    # for a 100 000 px wide image, beyond any lens (a 100 m telescope on 1 um pixels is 1e8 px);
    # larger values (or 0) are typos that would fail late, deep in the mapper.
    import pycolmap

    max_focal_px = 1e9
    cam = pycolmap.Camera.create_from_model_name(1, model.upper(), 1.0, 2, 2)
    for i in cam.focal_length_idxs():
        if not 0.0 < values[i] <= max_focal_px:
            raise InvalidInput(f"camera_params: focal length {values[i]:g} (parameter {i + 1} of {model.upper()}) "
                               f"must be > 0 and at most {max_focal_px:g} pixels")
    return tuple(values)


@dataclass(frozen=True, kw_only=True)
class MappingConfig:
    """Parameters of the mapping stage (the recipe's ``mapping`` table; ``map``, ``run`` and
    ``compare`` flags override it).

    Attributes:
        mapper: "incremental" (``pycolmap.incremental_mapping``) or "global"
            (``pycolmap.global_mapping``, GLOMAP).
        num_threads: mapper threads, -1 = all cores.
        min_num_matches: pairs with fewer verified inliers are ignored by the mapper.
        camera_model: COLMAP camera model written into the mapped copy of the database for
            every camera ("" = keep the database's cameras).
        camera_params: the model's parameters as COLMAP's comma-separated list (COLMAP pixel
            convention); "" with a ``camera_model`` = keep the database camera's focal length,
            principal point at the image centre. Needs ``camera_model``.
        refine_intrinsics: what bundle adjustment may change (:class:`RefineIntrinsics`);
            ``none`` keeps the given (or stored) intrinsics exactly.
    """

    mapper: Mapper = Mapper.INCREMENTAL
    num_threads: int = field(default=-1, metadata=within(-1, 4096, "threads; -1: all cores"))
    min_num_matches: int = field(default=15, metadata=within(0, MAX_MATCHES, "no pair holds more matches"))
    camera_model: str = ""
    camera_params: str = ""
    refine_intrinsics: RefineIntrinsics = RefineIntrinsics.DEFAULT

    def __post_init__(self) -> None:
        object.__setattr__(self, "mapper", Mapper.parse(self.mapper, "mapper"))
        object.__setattr__(self, "refine_intrinsics", RefineIntrinsics.parse(self.refine_intrinsics,
                                                                             "refine_intrinsics"))
        if self.camera_params.strip() and not self.camera_model.strip():
            raise InvalidInput("camera_params needs camera_model (the model the parameters belong to)")
        if self.camera_model.strip():
            parse_camera_params(self.camera_model, self.camera_params)
        check_bounds(self)
        if self.num_threads == 0:
            raise InvalidInput(f"num_threads must be -1 (all cores) or >= 1, got {self.num_threads}")

    def intrinsics(self):
        """The :class:`~colmap_miho.adapters.cameras.CameraIntrinsics` to write into every
        camera, or None when ``camera_model`` is empty."""
        from ..adapters.cameras import CameraIntrinsics

        if not self.camera_model.strip():
            return None
        return CameraIntrinsics(model=self.camera_model.strip().upper(),
                                params=parse_camera_params(self.camera_model, self.camera_params))


def run_mapping(
    database: str | Path,
    image_dir: str | Path,
    output: str | Path,
    config: MappingConfig | None = None,
    *,
    mapper: Mapper | str | None = None,
    seed: int = 0,
    intrinsics: dict | None = None,
    progress: bool = False,
    label: str = "mapping",
    verbose: bool = False,
) -> MappingResult:
    """Map ``database`` with pycolmap and write the largest model to ``output``.

    Args:
        database: COLMAP database (read through a private copy; never modified).
        image_dir: the image folder (colours of the 3D points).
        output: folder for the model (cameras/images/points3D .bin); created. An existing
            binary model in it is replaced; a text model (a ground truth, say) is refused.
        config: mapper, threads and ``min_num_matches`` (default :class:`MappingConfig`).
        mapper: when given, replaces ``config.mapper``.
        seed: the mapper's seed (:func:`colmap_miho.seeds.mapping_seed` of the run's root).
        intrinsics: image name -> :class:`~colmap_miho.adapters.cameras.CameraIntrinsics`
            written into those images' cameras of the copy after ``config.camera_model`` (e.g.
            the GT cameras, :func:`colmap_miho.reporting.compare.gt_intrinsics`).
        progress: tqdm bar of registered images (incremental only).
        label: the bar's description (e.g. "baseline run 2/3").
        verbose: leave COLMAP's log on the terminal instead of a file.

    Returns:
        :class:`MappingResult`; ``success=False`` when no model was found (not an exception).

    Raises:
        DatabaseError: the database is missing or not a COLMAP database.
    """
    from ..adapters.database import count_images, validate_database, write_camera_intrinsics
    from ..adapters.paths import refuse_text_model
    from ..adapters.safety import check_database_path, read_copy
    from ..adapters.staged_write import disk_full_error, is_disk_full, private_tempdir
    from ..arguments import check_paths, check_seed

    check_paths(database=database, image_dir=image_dir, output=output)
    check_seed(seed)
    if config is not None and not isinstance(config, MappingConfig):
        raise InvalidInput(f"config must be of type MappingConfig, got {type(config).__name__}")
    cfg = config or MappingConfig()
    if mapper is not None:
        cfg = replace(cfg, mapper=Mapper.parse(mapper, "mapper"))
    database = check_database_path(database)
    image_dir = Path(image_dir)
    if not image_dir.is_dir():
        raise NotADirectoryError(f"image folder not found: {image_dir}")
    output = Path(output)
    refuse_text_model(output, "mapping output")
    made = [p for p in (output, *output.parents) if not p.exists()]  # removed again if nothing lands there
    output.mkdir(parents=True, exist_ok=True)

    try:
        with private_tempdir("colmap_miho_map_", output) as tmp:  # removed by the next run after a kill -9
            db_copy = Path(tmp) / "database.db"
            read_copy(database, db_copy)  # refuses a database in use or with a hot journal
            validate_database(db_copy, name=database)  # e.g. a lying blob size: pycolmap would abort
            _warn_names_outside(db_copy, database, image_dir)
            if cfg.intrinsics() is not None:
                write_camera_intrinsics(db_copy, cfg.intrinsics())
            if intrinsics and not write_camera_intrinsics(db_copy, intrinsics):
                log.warning("no database image has given intrinsics (names differ?): cameras unchanged")
            num_images = count_images(db_copy)
            models_dir = Path(tmp) / "models"
            models_dir.mkdir()
            t0 = time.perf_counter()
            # COLMAP prints image names raw: with one that needs escaping, -v replays the log
            with colmap_log_to_file(output, verbose=verbose, replay=verbose and _names_need_escaping(db_copy),
                                    hide=()) as prefix:
                models = _run_mapper(cfg, seed, db_copy, image_dir, models_dir, num_images if progress else None, label)
            seconds = time.perf_counter() - t0
            log_file = latest_log(prefix)
    except BaseException as exc:
        for folder in made:  # a refused input leaves no empty output folder behind
            with contextlib.suppress(OSError):
                folder.rmdir()
        if isinstance(exc, (OSError, RuntimeError)) and is_disk_full(exc):  # pycolmap's SQLite: "disk is full"
            raise disk_full_error(output, f"mapping {database}", exc) from None
        raise

    if not models:
        log.warning("mapping found no model (%d images in the database)", num_images)
        return MappingResult(success=False, output=None, mapper=cfg.mapper.value, seed=seed, num_images=num_images,
                             seconds=seconds, refine_intrinsics=cfg.refine_intrinsics.value, log_file=log_file)
    best = _write_largest(models, output)
    log.info(
        "%s mapping: %d of %d images registered, %d points, %d model(s), %.1f s -> %s",
        cfg.mapper.value, best.num_reg_images(), num_images, best.num_points3D(), len(models), seconds,
        output,
    )
    return MappingResult(
        success=best.num_reg_images() >= 2, output=output, mapper=cfg.mapper.value, seed=seed,
        num_models=len(models),
        num_images=num_images, num_reg_images=int(best.num_reg_images()),
        num_points3D=int(best.num_points3D()), seconds=seconds, cameras=_camera_rows(best),
        refine_intrinsics=cfg.refine_intrinsics.value, log_file=log_file, reconstruction=best,
    )


def _names_need_escaping(copy: Path) -> bool:
    """Whether an image name of the database ``copy`` holds a character that
    :func:`~colmap_miho.terminal.printable` escapes (a newline, ESC ...)."""
    import sqlite3

    from ..terminal import printable

    con = sqlite3.connect(f"file:{copy.resolve()}?mode=ro", uri=True)
    try:
        return any(printable(str(name)) != str(name) for (name,) in con.execute("SELECT name FROM images"))
    finally:
        con.close()


def _warn_names_outside(copy: Path, database: Path, image_dir: Path) -> None:
    """Warn about image names that leave the image folder (absolute, or with ``..``): the
    mapper reads those files (for the points' colours) from outside ``image_dir``."""
    import sqlite3

    from ..adapters.paths import leaves_folder

    con = sqlite3.connect(f"file:{copy.resolve()}?mode=ro", uri=True)
    try:
        outside = [name for (name,) in con.execute("SELECT name FROM images") if leaves_folder(name)]
    finally:
        con.close()
    if outside:
        log.warning("%d image name(s) of %s lead outside the image folder %s (e.g. %r): the mapper reads them "
                    "from there", len(outside), database, image_dir, outside[0])


def _camera_rows(rec) -> list[dict]:
    return [{"camera_id": int(c.camera_id), "model": c.model.name, "width": int(c.width), "height": int(c.height),
             "params": [float(v) for v in c.params]} for _, c in sorted(rec.cameras.items())]


def global_options(*, seed: int, num_threads: int, min_num_matches: int,
                   refine: tuple[bool, bool, bool] | None = None):
    """``pycolmap.GlobalPipelineOptions`` with the seed, threads (-1: all cores), the fewest
    inliers of a pair it uses and, when given, what bundle adjustment may change in the cameras
    (focal length, principal point, extra parameters; None: COLMAP's default)."""
    import pycolmap

    gopts = pycolmap.GlobalPipelineOptions()
    gopts.random_seed = int(seed)
    gopts.num_threads = int(num_threads)
    gopts.min_num_matches = int(min_num_matches)
    if refine is not None:
        ba = gopts.mapper.bundle_adjustment
        ba.refine_focal_length, ba.refine_principal_point, ba.refine_extra_params = refine
    return gopts


def release_freed_heap() -> None:
    """Give the C heap's free pages back to the system (glibc's ``malloc_trim``): pycolmap's
    mappers free hundreds of MB that glibc would otherwise keep for the process. A no-op
    where the C library has no such call."""
    import ctypes
    import ctypes.util

    try:
        ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6").malloc_trim(0)
    except (OSError, AttributeError):
        pass


def largest_model(models: dict):
    """The model with the most registered images (then points), or None without models."""
    return max(models.values(), key=lambda r: (r.num_reg_images(), r.num_points3D()), default=None)


def _run_mapper(cfg: MappingConfig, seed: int, database: Path, image_dir: Path, models_dir: Path,
                bar_total: int | None, label: str = "mapping") -> dict:
    """pycolmap's incremental or global pipeline on ``database``; returns its models. A tqdm
    bar over ``bar_total`` images follows the incremental mapper's callbacks when given."""
    import pycolmap

    refine = _REFINE_FLAGS.get(cfg.refine_intrinsics)
    if cfg.mapper == Mapper.GLOBAL:
        gopts = global_options(seed=seed, num_threads=cfg.num_threads, min_num_matches=cfg.min_num_matches,
                               refine=refine)
        return pycolmap.global_mapping(str(database), str(image_dir), str(models_dir), gopts)
    opts = pycolmap.IncrementalPipelineOptions()
    opts.random_seed = int(seed)
    opts.num_threads = int(cfg.num_threads)
    opts.min_num_matches = int(cfg.min_num_matches)
    opts.mapper.random_seed = int(seed)
    opts.mapper.num_threads = int(cfg.num_threads)
    opts.triangulation.random_seed = int(seed)
    if refine is not None:
        opts.ba_refine_focal_length, opts.ba_refine_principal_point, opts.ba_refine_extra_params = refine
        # image registration (absolute pose) refines focal / distortion on its own flags
        opts.mapper.abs_pose_refine_focal_length, opts.mapper.abs_pose_refine_extra_params = refine[0], refine[2]
    if bar_total is None:
        return pycolmap.incremental_mapping(str(database), str(image_dir), str(models_dir), opts)
    from tqdm import tqdm

    with tqdm(total=bar_total, desc=label, unit="img") as bar:
        return pycolmap.incremental_mapping(
            str(database), str(image_dir), str(models_dir), opts,
            initial_image_pair_callback=lambda: bar.update(2),
            next_image_callback=lambda: bar.update(1))


def _write_largest(models: dict, output: Path):
    """Write the model with the most registered images (then points) to ``output``, replacing
    model files there (staged, read back, then renamed: see
    :func:`~colmap_miho.adapters.staged_write.write_model_atomic`); returns it."""
    from ..adapters.staged_write import write_model_atomic

    best = largest_model(models)
    write_model_atomic(best, output)
    return best


def require_success(result: MappingResult) -> MappingResult:
    """Raise :class:`RunFailed` when mapping registered fewer than two images."""
    if not result.success:
        raise RunFailed(
            f"mapping registered no model ({result.num_images} images in the database); "
            f"see {result.log_file or 'the log above'}"
        )
    return result


