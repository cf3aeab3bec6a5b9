"""Every benchmark script imports: a moved module breaks the script here, not in a user's hands."""

from __future__ import annotations

import importlib
from pathlib import Path

import pytest

BENCHMARKS = sorted(p.stem for p in (Path(__file__).resolve().parents[2] / "benchmarks").glob("*.py"))


def test_the_benchmark_folder_is_found():
    assert "bench_accuracy" in BENCHMARKS


@pytest.mark.parametrize("name", BENCHMARKS)
def test_benchmark_script_imports_and_has_a_main(name):
    module = importlib.import_module(name)
    assert callable(getattr(module, "main", None)), f"benchmarks/{name}.py has no main()"
