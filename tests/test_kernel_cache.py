"""The compiled kernels' cache: where it is (the environment's rule), which kernel families a
recipe needs, ``colmap-miho compile`` filling it once, and a read-only installation compiling
once per user cache, not per run."""

from __future__ import annotations

import logging
import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from colmap_miho import compiled, kernel_cache
from colmap_miho.cli import main
from colmap_miho.kernel_cache import FAMILIES, cached, ensure_compiled, families_for, ready_file
from colmap_miho.recipe import load_recipe

PACKAGE = Path(kernel_cache.__file__).resolve().parent

#: the smallest family (the fewest seconds to compile), for the tests that compile one.
SMALL = "lsm"


@pytest.fixture
def clean_env(monkeypatch):
    for name in (compiled.CACHE_ENV, compiled.NUMBA_CACHE_ENV, "XDG_CACHE_HOME"):
        monkeypatch.delenv(name, raising=False)
    return monkeypatch


@pytest.mark.skipif(sys.platform in ("win32", "darwin"), reason="the Linux rule (XDG)")
def test_cache_dir_is_the_users_cache_unless_the_environment_names_one(clean_env, tmp_path):
    clean_env.setenv("HOME", str(tmp_path / "home"))
    assert compiled.cache_dir() == tmp_path / "home" / ".cache" / "colmap-miho" / "numba"
    clean_env.setenv("XDG_CACHE_HOME", "relative/ignored")  # XDG: only an absolute path counts
    assert compiled.cache_dir() == tmp_path / "home" / ".cache" / "colmap-miho" / "numba"
    clean_env.setenv("XDG_CACHE_HOME", str(tmp_path / "xdg"))
    assert compiled.cache_dir() == tmp_path / "xdg" / "colmap-miho" / "numba"
    clean_env.setenv(compiled.NUMBA_CACHE_ENV, str(tmp_path / "numba"))  # numba's own setting
    assert compiled.cache_dir() == tmp_path / "numba"
    clean_env.setenv(compiled.CACHE_ENV, str(tmp_path / "ours"))  # ours first
    assert compiled.cache_dir() == tmp_path / "ours"
    clean_env.setenv(compiled.CACHE_ENV, "")  # empty: unset
    assert compiled.cache_dir() == tmp_path / "numba"


def test_kernels_are_cached_in_the_cache_dir_and_numbas_setting_is_restored(clean_env, tmp_path):
    """numba's cache folder is ours only while our kernels are jitted; a folder that cannot be
    written means no cache (a warning), not numba's "cannot cache function" error."""
    from numba.core import config

    before = config.CACHE_DIR
    clean_env.setenv(compiled.CACHE_ENV, str(tmp_path / "cache"))
    with compiled._kernel_cache():
        assert config.CACHE_DIR == str(tmp_path / "cache")
        assert compiled._CACHING == [True]
    assert config.CACHE_DIR == before
    (tmp_path / "file").write_text("")
    clean_env.setenv(compiled.CACHE_ENV, str(tmp_path / "file" / "cache"))  # under a file: never writable
    with compiled._kernel_cache():
        assert compiled._CACHING == [False]
    assert compiled._CACHING == [True]


def test_the_families_follow_the_recipe():
    assert families_for(load_recipe(None)) == ("filter", "rectify", "ncc", "lsm")  # the default uses all
    assert families_for(load_recipe("mop")) == ("filter",)
    assert families_for(load_recipe("mop_miho_ncc")) == ("filter", "rectify", "ncc")
    assert families_for(load_recipe(None, ["rectify.mode=filter"])) == ("filter", "ncc", "lsm")
    assert families_for(load_recipe(None, ["lsm.enabled=false", "tracks.multiphoto_lsm=true"])) == (
        "filter", "rectify", "ncc", "lsm")
    with pytest.raises(ValueError, match="unknown kernel families"):
        ensure_compiled(["filter", "nope"])


def test_the_ready_files_depend_on_the_sources_and_the_folder(tmp_path):
    for family in FAMILIES:
        assert ready_file(family, tmp_path).parent == tmp_path / kernel_cache.READY_FOLDER
    assert len({ready_file(f, tmp_path).name for f in FAMILIES}) == len(FAMILIES)


def test_every_kernel_module_belongs_to_a_family():
    """A module with jitted kernels (a ``Kernels`` handle) outside every family would compile
    unannounced in the run, and its changes would not make the family compile again."""
    sources = {path for family in FAMILIES for path in kernel_cache.source_files(family)}
    kernel_modules = {path for path in PACKAGE.rglob("*.py") if "= Kernels(" in path.read_text()}
    assert len(kernel_modules) == 7
    assert kernel_modules <= sources


def test_compile_command_with_the_families_cached_compiles_nothing(clean_env, tmp_path, capsys):
    clean_env.setenv(compiled.CACHE_ENV, str(tmp_path))
    path = ready_file("filter")
    path.parent.mkdir(parents=True)
    path.write_text("")
    assert main(["compile", "--recipe", "mop"]) == 0
    out = capsys.readouterr().out.splitlines()
    assert out == [f"kernel cache: {tmp_path}", "  filter   already in the cache"]


def test_compile_command_refuses_a_cache_it_cannot_write(clean_env, tmp_path, capsys):
    (tmp_path / "file").write_text("")
    clean_env.setenv(compiled.CACHE_ENV, str(tmp_path / "file" / "cache"))
    assert main(["compile"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert err == [f"ERROR: cannot write the kernel cache in {tmp_path / 'file' / 'cache'}: set "
                   f"{compiled.CACHE_ENV} to a writable folder"]
    assert main(["compile", "--processes", "0"]) == 2


def test_compiling_in_the_background_finds_the_cached_families(clean_env, tmp_path, caplog):
    """The whole jobs start compiling before their extraction and mapping; with every family
    cached that is a check and nothing more."""
    clean_env.setenv(compiled.CACHE_ENV, str(tmp_path))
    for family in FAMILIES:
        ready_file(family).parent.mkdir(parents=True, exist_ok=True)
        ready_file(family).write_text("")
    with caplog.at_level(logging.INFO, logger="colmap_miho"):
        thread = kernel_cache.compile_in_background(FAMILIES)
        thread.join(timeout=60)
    assert not thread.is_alive()
    assert "compiling" not in caplog.text


@pytest.mark.slow
def test_ensure_compiled_fills_the_cache_once_and_says_so(clean_env, tmp_path, caplog):
    clean_env.setenv(compiled.CACHE_ENV, str(tmp_path))
    with caplog.at_level(logging.INFO, logger="colmap_miho"):
        first = ensure_compiled([SMALL])
    assert set(first.compiled) == {SMALL} and not first.failed
    assert "compiling kernels (first run, once per cache): lsm" in caplog.text
    assert cached(SMALL)
    assert list(tmp_path.glob("*/kernel._lsm_matches-*.nbi"))  # numba's index, in our folder
    caplog.clear()
    with caplog.at_level(logging.INFO, logger="colmap_miho"):
        second = ensure_compiled([SMALL])
    assert second.cached == (SMALL,) and not second.compiled
    assert "compiling" not in caplog.text


_LOAD = """
import logging, sys
logging.basicConfig(level=logging.INFO, format="%(message)s")
from colmap_miho.kernel_cache import ensure_compiled
from colmap_miho.refinement.lsm import kernel
report = ensure_compiled(["lsm"])
assert kernel.warm()
print("stats", sum(sum(d.stats.cache_misses.values()) for d in [kernel.KERNELS()]))
"""


def _as_user_command() -> tuple[list[str], str]:
    """How to run this interpreter as a user who cannot write the installation: this user when
    it is not root, else ``nobody`` through ``setpriv``; ([], why not) where neither works."""
    if os.geteuid() != 0:
        return [], ""
    setpriv = shutil.which("setpriv")
    if setpriv is None:
        return [], "running as root and setpriv is not installed (run the tests as a non-root user)"
    prefix = [setpriv, "--reuid=nobody", "--regid=nogroup", "--clear-groups", "--"]
    probe = subprocess.run([*prefix, sys.executable, "-c", "import numba, torch, pycolmap"], capture_output=True)
    if probe.returncode:
        return [], (f"running as root and 'nobody' cannot run {sys.executable} with its packages (e.g. the "
                    "interpreter is under /root); run the tests as a non-root user")
    return prefix, ""


@pytest.mark.slow
def test_a_read_only_installation_compiles_once_per_user_cache(tmp_path):
    """A copy of the package its user cannot write (as a wheel in a root-owned site-packages):
    the first run compiles into the user's cache (and says so), the second compiles nothing."""
    prefix, why = _as_user_command()
    if why:
        pytest.skip(why)
    install, home = tmp_path / "site-packages", tmp_path / "home"
    shutil.copytree(PACKAGE, install / "colmap_miho", ignore=shutil.ignore_patterns("__pycache__"))
    home.mkdir()
    if prefix:  # the user's home is theirs, the installation not; the folders above reachable
        shutil.chown(home, "nobody", "nogroup")
        for folder in (tmp_path, *tmp_path.parents[:2]):
            folder.chmod(folder.stat().st_mode | 0o555)
    paths = [install, *install.rglob("*")]
    for path in paths:
        path.chmod(path.stat().st_mode & ~0o222)
    env = {k: v for k, v in os.environ.items() if not k.startswith(("COLMAP_MIHO", "NUMBA", "XDG"))}
    env.update(HOME=str(home), PYTHONPATH=str(install), PYTHONDONTWRITEBYTECODE="1")
    try:
        runs = [subprocess.run([*prefix, sys.executable, "-c", _LOAD], env=env, capture_output=True, text=True,
                               timeout=600, cwd=home) for _ in range(2)]
    finally:
        for path in paths:  # pytest removes tmp_path later
            path.chmod(path.stat().st_mode | 0o200)
    for run in runs:
        assert run.returncode == 0, run.stderr
    assert "compiling kernels (first run, once per cache): lsm" in runs[0].stderr
    assert "compiling" not in runs[1].stderr
    assert runs[1].stdout.split() == ["stats", "0"]  # every kernel loaded from the cache
    cache = home / ".cache" / "colmap-miho" / "numba"
    assert list(cache.glob("*/kernel._lsm_matches-*.nbi"))
    assert not [p for p in install.rglob("*") if p.suffix in (".nbi", ".nbc", ".pyc")]  # nothing written there
