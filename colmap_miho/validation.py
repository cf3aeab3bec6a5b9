"""Checks shared by the frozen config dataclasses' ``__post_init__`` (pure: no I/O): every
numeric recipe key carries its allowed range beside it, in its field's metadata (:func:`within`),
and :func:`check_bounds` checks them all.

Every value that sizes work (radii, blur, iterations, counts, batch sizes) has a lower and an
upper bound that follow from what it means, checked before any work: the compiled kernels
size their buffers from these values, and an unbounded one either never ends or corrupts
memory (``lsm.antialias=1e20``). Relations between keys (``t_h <= t_l``,
``template_radius + search_radius``) stay in the dataclass's ``__post_init__``.
"""

from __future__ import annotations

import dataclasses
import math
import numbers
import sys
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
    """The allowed range of one key (open ends with ``lo_open`` / ``hi_open``) and why."""

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


#: Reasons shared by many fields' ranges.
PX = "pixels, larger than any image"
SHARE = "a share"
NCC = "an NCC value or difference"
#: The key of a field's :class:`Bound` in its ``dataclasses.field`` metadata.
BOUND_KEY = "bound"


def within(lo: float, hi: float, why: str, *, lo_open: bool = False, hi_open: bool = False) -> dict:
    """Field ``metadata`` for a value in ``[lo, hi]`` for the reason ``why``, shown in the error."""
    return {BOUND_KEY: Bound(lo, hi, why, lo_open=lo_open, hi_open=hi_open)}


def bounds_of(cls) -> dict[str, Bound]:
    """Field name -> :class:`Bound` of every bounded field of the dataclass ``cls`` (or instance)."""
    return {f.name: f.metadata[BOUND_KEY] for f in dataclasses.fields(cls) if BOUND_KEY in f.metadata}


#: The allowed range of the numeric command-line options that are not recipe keys (checked by
#: the CLI before any command runs; ``--memory-budget``, ``--threads`` ... go through the
#: recipe's bounds). Keyed by the argparse destination.
OPTION_BOUNDS: dict[str, Bound] = {
    "seed": Bound(0, MAX_SEED, "a 32-bit seed"),
    "workers": Bound(1, 1024, "processes"),
    "repeats": Bound(1, 100, "mapping runs per side"),
    "num_images": Bound(2, 10_000, "images rendered"),
    "max_features": Bound(1, 1_000_000, "SIFT features per image"),
    "processes": Bound(1, 1024, "kernel families compiled at once"),
}


def check_options(args) -> None:
    """Refuse a numeric CLI option outside :data:`OPTION_BOUNDS` (InvalidInput)."""
    for dest, bound in OPTION_BOUNDS.items():
        check_value(f"--{dest.replace('_', '-')}", getattr(args, dest, None), bound)


def check_bounds(cfg) -> None:
    """Refuse a value of ``cfg`` outside its field's range (non-finite first): InvalidInput naming
    the key, the range and why."""
    require_finite(cfg)
    for name, bound in bounds_of(cfg).items():
        check_value(name, getattr(cfg, name), bound)


def check_value(name: str, value, bound: Bound) -> None:
    """Refuse ``value`` outside ``bound`` (None passes)."""
    if value is None or isinstance(value, bool):
        return
    if not isinstance(value, numbers.Real):  # a string from a script: '>=' would raise TypeError
        raise InvalidInput(f"{name} must be a number, got {value!r}")
    if not bound.holds(value):
        raise InvalidInput(f"{name} must be in {bound.text()} ({bound.why}), got {value}")


def require_finite(cfg) -> None:
    """Refuse inf, nan and subnormal floats in ``cfg`` (a nan threshold silently disables a check);
    ValueError naming the field."""
    for f in dataclasses.fields(cfg):
        value = getattr(cfg, f.name)
        if isinstance(value, float) and not math.isfinite(value):
            raise InvalidInput(f"{f.name} must be a finite number, got {value}")
        if isinstance(value, float) and value != 0 and abs(value) < sys.float_info.min:
            raise InvalidInput(f"{f.name} must be 0 or at least {sys.float_info.min:g} in size (a subnormal "
                               f"number loses its digits), got {value!r}")


def require_at_most(name: str, value, limit, why: str) -> None:
    """Refuse ``value > limit`` for a field whose size drives memory use (ValueError)."""
    if value is not None and value > limit:
        raise InvalidInput(f"{name} must be <= {limit} ({why}), got {value}")
