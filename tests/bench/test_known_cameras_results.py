"""bench_known_cameras writes results files without the machine's folders."""

from __future__ import annotations

from pathlib import Path

import bench_known_cameras as bench


def test_databases_are_named_relative_to_the_work_or_cache_folder(tmp_path):
    work, cache = tmp_path / "work", tmp_path / "cache"
    roots = {"WORK": work, "CACHE": cache}
    assert bench.portable_path(work / "castle" / "permissive" / "oracle_4px.db", roots) == \
        "WORK/castle/permissive/oracle_4px.db"
    assert bench.portable_path(cache / "castle" / "default" / "database.db", roots) == \
        "CACHE/castle/default/database.db"
    assert bench.portable_path(Path("/elsewhere/x.db"), roots) == "x.db"


def test_command_lines_keep_no_absolute_path():
    argv = ["--cache", "/tmp/c", "--work", "/var/w", "--build-missing", "--variant",
            "v:recipe=r,code=/home/me/checkout,seed=1", "--json", "out.json"]
    out = bench.portable_argv(argv)
    assert out == ["--cache", "CACHE", "--work", "WORK", "--build-missing", "--variant",
                   "v:recipe=r,code=CHECKOUT,seed=1", "--json", "out.json"]
    assert not any("/" in tok and tok.split("/")[0] == "" for tok in out)
