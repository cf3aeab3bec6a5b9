"""The package as a user installs it: an sdist built from the source tree, the wheel built from
that sdist, the wheel installed into a new virtual environment, its console script run from a
folder outside the source tree, and every module of the installed wheel imported there.

The tests' own environment installs colmap-miho editable, which finds any module of the source
tree whether the wheel ships it or not; so the virtual environment here gets colmap_miho from the
wheel only. Its dependencies (torch, pycolmap, ...: minutes and gigabytes to install afresh) come
from the environment running the tests: a ``.pth`` file in the new environment names that
environment's site-packages folders. A folder named in a ``.pth`` file joins ``sys.path``, but
its own ``.pth`` files are not run, so the editable install (a ``.pth`` file that installs an
import hook) stays out; the tests check that every ``colmap_miho`` module comes from the new
environment. ``COLMAP_MIHO_WHEEL_VENV=fresh`` installs torch and the wheel's dependencies into
the new environment from the package index instead (what a user's ``pip install`` does).
"""

from __future__ import annotations

import json
import os
import shutil
import site
import subprocess
import sys
import tarfile
import zipfile
from pathlib import Path

import pytest

from colmap_miho.version import __version__

pytestmark = pytest.mark.slow

REPO = Path(__file__).resolve().parents[1]
PACKAGE = REPO / "colmap_miho"
TORCH = "torch==2.13.0"  # the README's pin: the CPU build


def _run(cmd, cwd: Path, timeout: float = 900) -> subprocess.CompletedProcess:
    """Run ``cmd`` outside the source tree, without the tests' PYTHONPATH; fail with its output."""
    env = {k: v for k, v in os.environ.items() if k != "PYTHONPATH"}
    proc = subprocess.run([str(c) for c in cmd], cwd=cwd, env=env, capture_output=True, text=True, timeout=timeout)
    assert proc.returncode == 0, f"{' '.join(map(str, cmd))} exited {proc.returncode}\n{proc.stdout}\n{proc.stderr}"
    return proc


def _package_files() -> set[str]:
    """Paths (``colmap_miho/...``) of the package's source files: modules, recipes, py.typed."""
    return {p.relative_to(REPO).as_posix() for p in PACKAGE.rglob("*")
            if p.is_file() and "__pycache__" not in p.parts and p.suffix in (".py", ".toml", ".typed")}


def _module_names() -> set[str]:
    """Dotted names of every module and package of the source tree."""
    names = set()
    for path in _package_files():
        if path.endswith(".py"):
            parts = path[:-3].split("/")
            names.add(".".join(parts[:-1] if parts[-1] == "__init__" else parts))
    return names


@pytest.fixture(scope="module")
def dist(tmp_path_factory) -> dict[str, Path]:
    """``{"sdist", "wheel"}``: the sdist of a copy of the source tree (the build writes into the
    tree it builds), and the wheel ``pip wheel`` builds from that sdist."""
    root = tmp_path_factory.mktemp("dist")
    src = root / "src"
    src.mkdir()
    for item in REPO.iterdir():  # the project files beside the package (pyproject.toml, README.md, ...)
        if item.is_file() and not item.name.startswith(".") and item.suffix in ("", ".toml", ".md", ".txt", ".in",
                                                                               ".cfg", ".py"):
            shutil.copy2(item, src / item.name)
    shutil.copytree(PACKAGE, src / PACKAGE.name, ignore=shutil.ignore_patterns("__pycache__"))
    out = root / "out"
    build_sdist = "import sys, setuptools.build_meta as b; print(b.build_sdist(sys.argv[1]))"
    name = _run([sys.executable, "-c", build_sdist, out], cwd=src).stdout.strip().splitlines()[-1]
    sdist = out / name
    _run([sys.executable, "-m", "pip", "wheel", "--no-deps", "--no-build-isolation", "-q", "-w", out, sdist], cwd=root)
    (wheel,) = out.glob("colmap_miho-*.whl")
    return {"sdist": sdist, "wheel": wheel}


def test_sdist_and_wheel_hold_every_file_of_the_package(dist):
    files = _package_files()
    assert "colmap_miho/verification/match_check.py" in files and "colmap_miho/recipes/mop_miho_lsm.toml" in files
    with tarfile.open(dist["sdist"]) as tar:
        top = dist["sdist"].name[: -len(".tar.gz")]
        in_sdist = {n[len(top) + 1:] for n in tar.getnames() if n.startswith(top + "/")}
    assert files | {"pyproject.toml", "README.md"} <= in_sdist, sorted(files - in_sdist)
    with zipfile.ZipFile(dist["wheel"]) as whl:
        names = set(whl.namelist())
        (entry_points,) = [n for n in names if n.endswith(".dist-info/entry_points.txt")]
        scripts = whl.read(entry_points).decode()
    assert files <= names, sorted(files - names)
    assert {n.split("/")[0] for n in names if not n.split("/")[0].endswith(".dist-info")} == {"colmap_miho"}
    assert "colmap-miho = colmap_miho.cli:console_main" in scripts


@pytest.fixture(scope="module")
def venv(dist, tmp_path_factory) -> Path:
    """A new virtual environment with the wheel (and the ``demo`` extra's packages) installed."""
    root = tmp_path_factory.mktemp("venv")
    env = root / "env"
    python = env / "bin" / "python"
    wheel = f"{dist['wheel']}[demo]"
    if os.environ.get("COLMAP_MIHO_WHEEL_VENV") == "fresh":
        _run([sys.executable, "-m", "venv", env], cwd=root)
        _run([python, "-m", "pip", "install", "-q", TORCH], cwd=root, timeout=1800)
        _run([python, "-m", "pip", "install", "-q", wheel], cwd=root, timeout=1800)
        return env
    _run([sys.executable, "-m", "venv", "--without-pip", env], cwd=root)
    purelib = _run([python, "-c", "import sysconfig; print(sysconfig.get_paths()['purelib'])"], cwd=root)
    ours = [*site.getsitepackages(), *([site.getusersitepackages()] if site.ENABLE_USER_SITE else [])]
    (Path(purelib.stdout.strip()) / "_dependencies.pth").write_text(
        "".join(f"{p}\n" for p in ours if os.path.isdir(p)), encoding="utf-8")
    # --no-index: every requirement of the wheel and its demo extra must already be met
    _run([sys.executable, "-m", "pip", "--python", python, "install", "-q", "--no-index", wheel], cwd=root)
    return env


IMPORT_ALL = """
import importlib, json, pkgutil, sys
import colmap_miho
from colmap_miho.recipe import DEFAULT_RECIPE, available_recipes, load_recipe
walked = [m.name for m in pkgutil.walk_packages(colmap_miho.__path__, "colmap_miho.")
          if m.name != "colmap_miho.__main__"]
for name in walked:
    importlib.import_module(name)
print(json.dumps({"walked": walked, "recipes": {r: load_recipe(r).name for r in available_recipes()},
                  "default": load_recipe().name, "default_name": DEFAULT_RECIPE,
                  "finders": [repr(f) for f in sys.meta_path],
                  "files": {m: getattr(sys.modules[m], "__file__", None) for m in sys.modules
                            if m.split(".")[0] == "colmap_miho"}}))
"""


def test_every_module_of_the_installed_wheel_imports(venv, tmp_path):
    out = json.loads(_run([venv / "bin" / "python", "-c", IMPORT_ALL], cwd=tmp_path).stdout.splitlines()[-1])
    assert not [f for f in out["finders"] if "editable" in f.lower()], out["finders"]
    assert {"colmap_miho", *out["walked"]} == _module_names() - {"colmap_miho.__main__"}
    assert set(out["files"]) >= set(out["walked"])
    for name, file in out["files"].items():
        assert file is not None and Path(file).is_relative_to(venv), (name, file)
    shipped = {p.stem for p in (PACKAGE / "recipes").glob("*.toml")}
    assert out["recipes"] == {name: name for name in shipped}
    assert out["default"] == out["default_name"] == "mop_miho_lsm"


def test_console_script_runs_the_quick_demo_outside_the_source_tree(venv, tmp_path):
    """``colmap-miho demo --quick`` from the wheel: extraction, refine (the default recipe), both
    mappings and the comparison; the refined keypoints are closer to the exact GT."""
    script = venv / "bin" / "colmap-miho"
    assert _run([script, "--version"], cwd=tmp_path).stdout.strip() == f"colmap-miho {__version__}"
    _run([script, "demo", "--quick", "--output", "demo", "-q"], cwd=tmp_path, timeout=1800)
    result = json.loads((tmp_path / "demo" / "compare.json").read_text())
    assert (tmp_path / "demo" / "report.html").is_file()
    assert result["refine"]["recipe"] == "mop_miho_lsm" and result["refine"]["refined"] is True
    assert result["refined"]["reconstruction"]["num_reg_images"] == 6
    before = result["baseline"]["keypoint_accuracy"]["residual_median_px"]
    after = result["refined"]["keypoint_accuracy"]["residual_median_px"]
    assert after < 0.8 * before, (before, after)
