"""bench_end_to_end: its command line, its rows' arithmetic and its table, on made-up figures
(no mapping, no refine)."""

from __future__ import annotations

from pathlib import Path

import pytest
from bench_end_to_end import HEAD, end_to_end_row, main, mapping_figures, parse_args, table

from colmap_miho.reporting.report import auc_key

SHARED = ["strecha_castle_p19", "middlebury_temple_sparse_ring", "strecha_fountain_p11", "strecha_entry_p10"]


def _mapped(seconds: float, auc: float, registered: int, images: int = 8) -> dict:
    return {"seconds": seconds, "auc": auc, "registered": registered, "images": images}


def test_defaults_are_the_brief():
    args = parse_args([])
    assert args.scenes == ["demo", *SHARED]
    assert args.settings == ["default", "permissive"]
    assert (args.workers, args.threads, args.oracle, args.oracle_threshold) == (2, 2, True, 4.0)
    assert args.cache == Path("/tmp/bench_accuracy") and args.recipe is None and args.overrides == []
    assert args.json is None


def test_options_are_read():
    args = parse_args(["--scenes", "demo", "--settings", "permissive", "--set", "a.b=1", "--set", "c.d=x",
                       "--recipe", "mop_miho_ncc", "--no-oracle", "--threads", "1", "--workers", "3",
                       "--cache", "/c", "--json", "o.json"])
    assert args.scenes == ["demo"] and args.settings == ["permissive"]
    assert args.overrides == ["a.b=1", "c.d=x"] and args.recipe == "mop_miho_ncc"
    assert (args.oracle, args.threads, args.workers) == (False, 1, 3)
    assert args.cache == Path("/c") and args.json == Path("o.json")


@pytest.mark.parametrize("argv", [["--settings", "strict"], ["--threads", "0"], ["--workers", "0"],
                                  ["--oracle-threshold", "0"]])
def test_bad_values_exit_with_argparse_message(argv, capsys):
    with pytest.raises(SystemExit) as exc:
        parse_args(argv)
    assert exc.value.code == 2 and "error:" in capsys.readouterr().err


def test_a_bad_recipe_key_fails_before_any_work(tmp_path, capsys):
    cache, work = tmp_path / "cache", tmp_path / "work"
    code = main(["--scenes", "demo", "--cache", str(cache), "--work", str(work), "--set", "nope.key=1"])
    assert code == 2 and "nope" in capsys.readouterr().err
    assert not cache.exists() and not work.exists()


def test_mapping_figures_take_the_single_run():
    run = {"seed": 0, "seconds": 3.25, "num_reg_images": 7, "num_images": 8, auc_key(0.5): 0.75, auc_key(1.0): 0.9}
    assert mapping_figures([run]) == {"seconds": 3.25, "auc": 0.75, "registered": 7, "images": 8}


def test_row_totals_and_ratio():
    row = end_to_end_row("castle", "default", _mapped(10.0, 0.5, 18, 19), refine_s=4.0, match_check_s=1.5,
                         mapped_refined=_mapped(8.0, 0.625, 19, 19), oracle_auc=0.75)
    assert row["refine_mapping_s"] == pytest.approx(12.0)
    assert row["ratio"] == pytest.approx(1.2)
    assert (row["registered_input"], row["registered_refined"], row["images"]) == (18, 19, 19)
    assert (row["auc_input"], row["auc_refined"], row["auc_oracle"]) == (0.5, 0.625, 0.75)
    assert row["mapping_alone_s"] == 10.0 and row["mapping_refined_s"] == 8.0 and row["match_check_s"] == 1.5
    # a mapping that took no time has no ratio (not a division by zero)
    assert end_to_end_row("s", "default", _mapped(0.0, 0.0, 0), 1.0, None, _mapped(1.0, 0.0, 0), None)["ratio"] is None


def test_table_has_one_line_per_row_and_the_columns_in_order():
    rows = [end_to_end_row("castle", "default", _mapped(10.0, 0.5, 18, 19), 4.0, 1.5, _mapped(8.0, 0.625, 19, 19),
                           0.75),
            end_to_end_row("demo", "permissive", _mapped(2.0, 0.9, 8), 6.0, None, _mapped(2.0, 0.95, 8), None)]
    lines = table(rows).splitlines()
    assert len(lines) == 2 + len(rows)
    assert [c.strip() for c in lines[0].strip("|").split("|")] == HEAD
    assert HEAD[0] == "scene" and HEAD[1] == "matching" and "match check (s)" in HEAD
    assert lines[1].count("|") == len(HEAD) + 1
    castle = [c.strip() for c in lines[2].strip("|").split("|")]
    assert castle == ["castle", "default", "10.0", "4.0", "1.5", "12.0", "1.20", "50.0", "62.5", "75.0", "18/19 of 19"]
    demo = [c.strip() for c in lines[3].strip("|").split("|")]
    assert demo == ["demo", "permissive", "2.0", "6.0", "-", "8.0", "4.00", "90.0", "95.0", "-", "8/8 of 8"]
