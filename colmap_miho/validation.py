"""Checks shared by the frozen config dataclasses' ``__post_init__`` (pure: no I/O), and the
one table of the allowed range of every numeric recipe key (:data:`BOUNDS`).

Every value that sizes work (radii, blur, iterations, counts, batch sizes) has a lower and an
upper bound that follow from what it means, checked before any work: the compiled kernels
size their buffers from these values, and an unbounded one either never ends or corrupts
memory (``ncc.lsm_antialias=1e20``). Relations between keys (``t_h <= t_l``,
``template_radius + search_radius``) stay in the dataclass's ``__post_init__``.
"""

from __future__ import annotations

import dataclasses
import math
import numbers
from dataclasses import dataclass

from .errors import InvalidInput

#: Upper bound of ``template_radius + search_radius`` (pixels): each match holds a
#: (2 (r_t + r_s) + 1)^2 window per perturbation (paper: 10 + 10); 1000 tried to allocate 320 GB.
MAX_WINDOW_RADIUS_PX = 64
#: Largest Gaussian blur (pixels) an LSM read applies: a blur wider than the widest window it
#: smooths is meaningless, and the compiled LSM kernel sizes its tap buffers by it.
MAX_BLUR_PX = float(MAX_WINDOW_RADIUS_PX)
#: Upper bound of ``NCCConfig.batch_size`` (matches per batched call).
MAX_NCC_BATCH = 65536
#: Upper bound of ``FilterConfig.batch_size``: each batch scores that many homographies on every match.
MAX_HYPOTHESES_BATCH = 8192
#: Upper bound of the thresholds ``t_l`` / ``t_h`` in pixels: larger than any image side
#: (``filter.t_l=1e308`` overflowed the squared thresholds).
MAX_THRESHOLD_PX = 1e5
#: Lower bound of ``t_l`` / ``t_h`` in pixels: far below keypoint noise; a smaller threshold
#: (``1e-300`` squares to 0) keeps no match, which silently turns the filter off.
MIN_THRESHOLD_PX = 1e-3
#: Upper bound of ``max_iters`` (c_max): RANSAC hypotheses per round, each scored on every match.
MAX_ITERS = 1_000_000
#: Upper bound of ``local_neighbours``: the k-NN table of local sampling holds k per match.
MAX_LOCAL_NEIGHBOURS = 1024
#: More matches than any image pair holds (SIFT keeps tens of thousands of features per image):
#: the upper bound of the counts of matches.
MAX_MATCHES = 1_000_000
#: Seeds are 32-bit (numpy's SeedSequence entries, COLMAP's ``random_seed``).
MAX_SEED = 2**31 - 1
#: ``pipeline.memory_budget_mb``: at least what one chunk needs, at most 1 TiB.
MIN_MEMORY_BUDGET_MB = 256
MAX_MEMORY_BUDGET_MB = 1 << 20


@dataclass(frozen=True)
class Bound:
    """The allowed range of one key: ``lo <= value <= hi`` (``lo < value`` when
    ``lo_open``, ``value < hi`` when ``hi_open``), and why the range is what it is (shown in the message)."""

    lo: float
    hi: float
    why: str
    lo_open: bool = False
    hi_open: bool = False

    def text(self) -> str:
        return f"{'(' if self.lo_open else '['}{_num(self.lo)}, {_num(self.hi)}{')' if self.hi_open else ']'}"

    def holds(self, value) -> bool:
        return ((value > self.lo if self.lo_open else value >= self.lo)
                and (value < self.hi if self.hi_open else value <= self.hi))


def _num(x: float) -> str:
    return str(int(x)) if float(x).is_integer() and abs(x) < 1e15 else f"{x:g}"


_PX = "pixels, larger than any image"
_SHARE = "a share"
_NCC = "an NCC value or difference"

#: The allowed range of every numeric key of every recipe section (None values mean "off" or
#: "the default" and are not checked). The parametrised test in
#: ``tests/adapters/test_bounds.py`` tries a value past each end of each.
BOUNDS: dict[str, dict[str, Bound]] = {
    "filter": {
        "t_l": Bound(MIN_THRESHOLD_PX, MAX_THRESHOLD_PX, _PX),
        "t_h": Bound(MIN_THRESHOLD_PX, MAX_THRESHOLD_PX, _PX),
        "min_inliers": Bound(4, MAX_MATCHES, "a homography needs 4 matches; no pair holds more"),
        "max_failures": Bound(1, 100, "each failure is a whole RANSAC round"),
        "min_iters": Bound(1, MAX_ITERS, "RANSAC hypotheses per round"),
        "max_iters": Bound(1, MAX_ITERS, "RANSAC hypotheses per round, each scored on every match"),
        "confidence": Bound(0, 1, "a probability", lo_open=True, hi_open=True),
        "min_singular_value": Bound(0, 1, "a singular value of a normalised system"),
        "buffer_size": Bound(0, 100, "models kept and scored again every round"),
        "local_neighbours": Bound(3, MAX_LOCAL_NEIGHBOURS, "neighbours held per match"),
        "local_fraction": Bound(0, 1, _SHARE),
        "batch_size": Bound(1, MAX_HYPOTHESES_BATCH, "hypotheses scored at once are held in memory"),
        "refit_iters": Bound(0, 100, "least-squares refits of each kept model"),
        "rotation_pairs": Bound(0, 10_000_000, "match pairs scored at once are held in memory"),
        "batch_growth": Bound(0, 8, "batches never exceed 8 x batch_size"),
    },
    "ncc": {
        "template_radius": Bound(1, MAX_WINDOW_RADIUS_PX, "pixels; the window of every match is held in memory"),
        "search_radius": Bound(1, MAX_WINDOW_RADIUS_PX, "pixels; the window of every match is held in memory"),
        "min_gain": Bound(0, 2, _NCC),
        "min_ncc": Bound(-1, 1, _NCC),
        "min_template_std": Bound(0, 1, "intensities are in [0, 1]"),
        "subpixel_iterations": Bound(0, 10, "re-centred fits per match"),
        "batch_size": Bound(1, MAX_NCC_BATCH, "matches held in memory at once"),
        "local_affine_neighbours": Bound(6, MAX_LOCAL_NEIGHBOURS, "neighbours of every local fit"),
        "local_affine_max_residual_px": Bound(0, MAX_THRESHOLD_PX, _PX, lo_open=True),
        "lsm_radius": Bound(0, MAX_WINDOW_RADIUS_PX, "pixels; 0: template_radius"),
        "lsm_radius_per_scale": Bound(0, MAX_WINDOW_RADIUS_PX, "pixels per keypoint scale; 0: off"),
        "lsm_max_iterations": Bound(1, 50, "Gauss-Newton steps per match"),
        "lsm_tol_px": Bound(0, 0.1, "pixels", lo_open=True),
        "lsm_max_shift_px": Bound(0, MAX_WINDOW_RADIUS_PX, "pixels, within the LSM window", lo_open=True),
        "lsm_max_sigma_px": Bound(0, MAX_WINDOW_RADIUS_PX, "pixels, within the LSM window", lo_open=True),
        "lsm_antialias": Bound(0, MAX_BLUR_PX, "pixels of blur; wider than the LSM window is meaningless"),
        "inner_radius": Bound(0, MAX_WINDOW_RADIUS_PX, "pixels; 0: off"),
    },
    "tracks": {
        "max_images_in_memory": Bound(2, 1024, "decoded images held at once"),
        "duplicate_px": Bound(0, MAX_WINDOW_RADIUS_PX, "pixels between keypoints of one image"),
        "multiphoto_iterations": Bound(0, 10, "consensus passes per track"),
        "far_move_px": Bound(0, MAX_WINDOW_RADIUS_PX, "pixels, within the search window; unset: "
                                                      "ncc.local_affine_max_residual_px", lo_open=True),
        "far_move_ratio": Bound(0, 1, "a share of the old distance to the prediction", lo_open=True),
    },
    "pipeline": {
        "min_matches": Bound(4, MAX_MATCHES, "a homography needs 4 matches; no pair holds more"),
        "memory_budget_mb": Bound(MIN_MEMORY_BUDGET_MB, MAX_MEMORY_BUDGET_MB, "MiB; at least one chunk, at most 1 TiB"),
    },
    "mapping": {
        "seed": Bound(0, MAX_SEED, "a 32-bit seed"),
        "num_threads": Bound(-1, 4096, "threads; -1: all cores"),
        "min_num_matches": Bound(0, MAX_MATCHES, "no pair holds more matches"),
    },
    "pair_check": {
        "transfer_tol_px": Bound(0, MAX_THRESHOLD_PX, _PX, lo_open=True),
        "min_transfers": Bound(1, MAX_MATCHES, "no pair holds more matches"),
        "min_closed_share": Bound(0, 1, _SHARE),
        "min_relative_share": Bound(0, 1, _SHARE),
        "trust_iterations": Bound(0, 100, "rounds over every triangle before each removal; the trust "
                                          "settles within a few"),
        "trust_power": Bound(0, 100, "an exponent of a share", lo_open=True),
        "confirm_triangles": Bound(0, MAX_MATCHES, "triangles of a pair"),
        "confirm_share": Bound(0, 1, _SHARE, lo_open=True),
        "confirm_trust": Bound(0, 1, _SHARE),
        "min_blame": Bound(1, MAX_MATCHES, "votes on a pair"),
        "min_blame_share": Bound(0, 1, _SHARE, lo_open=True),
        "min_angle_deg": Bound(0, 90, "degrees, below a right angle", hi_open=True),
        "max_transfers": Bound(1, 100_000, "matches carried into every third image"),
        "f_threshold_px": Bound(0, MAX_THRESHOLD_PX, _PX, lo_open=True),
        "min_f_matches": Bound(8, MAX_MATCHES, "the eight-point algorithm; no pair holds more"),
        "seed": Bound(0, MAX_SEED, "a 32-bit seed"),
    },
    "match_check": {
        "false_reject": Bound(0, 0.5, "a probability in the tail of the residuals", lo_open=True, hi_open=True),
        "min_threshold_px": Bound(0, MAX_THRESHOLD_PX, _PX, lo_open=True),
        "max_threshold_px": Bound(0, MAX_THRESHOLD_PX, _PX, lo_open=True),
        "max_rotation_deg": Bound(0, 180, "degrees between two rotations", lo_open=True, hi_open=True),
        "min_agreeing_pairs": Bound(1, 10_000, "pairs of one image"),
        "min_pair_matches": Bound(8, MAX_MATCHES, "the eight-point algorithm; no pair holds more"),
        "min_trusted_images": Bound(2, 1_000_000, "images"),
        "min_trusted_share": Bound(0, 1, _SHARE, lo_open=True),
        "max_pair_fail_share": Bound(0, 1, _SHARE, lo_open=True),
        "min_placed_inliers": Bound(6, MAX_MATCHES, "an absolute pose needs 6 correspondences"),
        "ba_iterations": Bound(1, 10, "rounds of bundle adjustment, each a full adjustment"),
        "ba_function_tolerance": Bound(0, 0.1, "a relative cost decrease (0: Ceres' 1e-5)"),
        "rounds": Bound(1, 5, "global-mapper runs"),
        "seed": Bound(0, MAX_SEED, "a 32-bit seed"),
    },
}


#: The allowed range of the numeric command-line options that are not recipe keys (checked by
#: the CLI before any command runs; ``--memory-budget``, ``--threads`` ... go through the
#: recipe's bounds). Keyed by the argparse destination.
OPTION_BOUNDS: dict[str, Bound] = {
    "seed": Bound(0, MAX_SEED, "a 32-bit seed"),
    "workers": Bound(1, 1024, "processes"),
    "repeats": Bound(1, 100, "mapping runs per side"),
    "num_images": Bound(2, 10_000, "images rendered"),
    "max_features": Bound(1, 1_000_000, "SIFT features per image"),
}


def check_options(args) -> None:
    """Refuse a numeric option of the argparse namespace ``args`` outside
    :data:`OPTION_BOUNDS` (options the command does not have, or left unset, pass).

    Raises:
        InvalidInput: ``"--<option> must be in [lo, hi] (why), got value"``.
    """
    for dest, bound in OPTION_BOUNDS.items():
        check_value(f"--{dest.replace('_', '-')}", getattr(args, dest, None), bound)


def check_bounds(cfg, section: str) -> None:
    """Refuse, before any work, a value of the dataclass instance ``cfg`` outside its
    :data:`BOUNDS` range (non-finite floats first, see :func:`require_finite`).

    Raises:
        InvalidInput: naming the key, the allowed range and why.
    """
    require_finite(cfg)
    for name, bound in BOUNDS[section].items():
        check_value(name, getattr(cfg, name), bound)


def check_value(name: str, value, bound: Bound) -> None:
    """Refuse ``value`` outside ``bound`` (None passes: off or the default).

    Raises:
        InvalidInput: ``"<name> must be in [lo, hi] (why), got value"``.
    """
    if value is None or isinstance(value, bool):
        return
    if not isinstance(value, numbers.Real):  # a string from a script: '>=' would raise TypeError
        raise InvalidInput(f"{name} must be a number, got {value!r}")
    if not bound.holds(value):
        raise InvalidInput(f"{name} must be in {bound.text()} ({bound.why}), got {value}")


def require_finite(cfg) -> None:
    """Refuse ``inf`` and ``nan`` in every float field of the dataclass instance ``cfg``
    (a ``nan`` threshold compares False with everything and silently disables a check).

    Raises:
        ValueError: names the field and the value.
    """
    for f in dataclasses.fields(cfg):
        value = getattr(cfg, f.name)
        if isinstance(value, float) and not math.isfinite(value):
            raise InvalidInput(f"{f.name} must be a finite number, got {value}")


def require_at_most(name: str, value, limit, why: str) -> None:
    """Refuse ``value > limit`` for a field whose size drives memory use.

    Raises:
        ValueError: names the field, the value, the limit and ``why``.
    """
    if value is not None and value > limit:
        raise InvalidInput(f"{name} must be <= {limit} ({why}), got {value}")
