"""The package's public names: all resolve, static tools see the same names, the CLI stays light."""

from __future__ import annotations

import ast
import importlib
import importlib.metadata
import subprocess
import sys
from pathlib import Path

import pytest

import colmap_miho


@pytest.mark.parametrize("name", colmap_miho.__all__)
def test_every_public_name_resolves(name):
    value = getattr(colmap_miho, name)
    if name != "__version__":
        assert getattr(value, "__name__", name) == name  # the object itself, not a module


def test_all_matches_the_lazy_table():
    assert sorted(colmap_miho.__all__) == sorted([*colmap_miho._LAZY, "__version__"])
    assert len(set(colmap_miho.__all__)) == len(colmap_miho.__all__)
    for name in ("refine_database", "RefineSummary", "PipelineConfig", "run_mapping",
                 "extract_and_match", "build_report", "compare_databases"):
        assert name in colmap_miho.__all__


def test_type_checking_imports_match_the_lazy_table():
    """The ``if TYPE_CHECKING:`` block (what mypy / IDEs see) names the same objects from the
    same modules as the run-time table."""
    tree = ast.parse(Path(colmap_miho.__file__).read_text(encoding="utf-8"))
    block = next(n for n in tree.body if isinstance(n, ast.If) and getattr(n.test, "id", "") == "TYPE_CHECKING")
    seen = {}
    for node in block.body:
        assert isinstance(node, ast.ImportFrom) and node.level == 1
        for alias in node.names:
            seen[alias.name] = f"colmap_miho.{node.module}"
    assert set(seen) == set(colmap_miho._LAZY)
    for name, module in seen.items():
        assert getattr(importlib.import_module(module), name) is getattr(colmap_miho, name)


def test_unknown_name_raises_attribute_error():
    with pytest.raises(AttributeError, match="no attribute 'nope'"):
        colmap_miho.nope  # noqa: B018


def test_version_comes_from_the_package_metadata():
    assert colmap_miho.__version__ == importlib.metadata.version("colmap-miho")


def test_import_and_cli_do_not_import_torch():
    code = (
        "import sys\n"
        "import colmap_miho, colmap_miho.cli\n"
        "colmap_miho.__version__\n"
        "colmap_miho.cli.build_parser().format_help()\n"
        "heavy = sorted(m for m in ('torch', 'pycolmap', 'kornia', 'h5py', 'cv2') if m in sys.modules)\n"
        "assert not heavy, heavy\n"
    )
    subprocess.run([sys.executable, "-c", code], check=True)
