"""Bad input a careless user gives: one line naming the option or file, exit 2."""

from __future__ import annotations

import os

import pytest

from colmap_miho.cli import main
from colmap_miho.errors import InvalidInput
from colmap_miho.recipe import load_recipe


def error_lines(err: str) -> list[str]:
    return [line for line in err.splitlines() if line.strip()]


# ------------------------------------------------------------------ recipes
def test_a_recipe_with_a_byte_order_mark_is_accepted(tmp_path):
    path = tmp_path / "windows.toml"
    path.write_bytes(b"\xef\xbb\xbf[filter]\nt_l = 12\n")
    assert load_recipe(str(path)).filter.t_l == 12


@pytest.mark.parametrize(("kind", "said"), [("fifo", "FIFO"), ("folder", "folder"), ("device", "character device")])
def test_a_recipe_path_that_is_not_a_file_says_what_it_is(kind, said, tmp_path):
    path = tmp_path / "r.toml"
    if kind == "fifo":
        os.mkfifo(path)
    elif kind == "folder":
        path.mkdir()
    else:
        path = "/dev/zero"
    with pytest.raises(InvalidInput, match=f"recipe {path} is a {said}"):
        load_recipe(str(path))


@pytest.mark.parametrize("content", ["binary", "nested", "huge"])
def test_a_recipe_that_is_not_one_is_one_line(content, tmp_path, capfd):
    path = tmp_path / "bad.toml"
    if content == "binary":
        path.write_bytes(bytes(range(256)) * 8)
    elif content == "nested":
        path.write_text("a = " + "[" * 50_000 + "]" * 50_000 + "\n")
    else:
        path.write_bytes(b"# " + b"x" * (2 << 20))
    capfd.readouterr()
    assert main(["refine", "--database", str(tmp_path / "x.db"), "--images", str(tmp_path), "--recipe", str(path),
                 "-q"]) == 2
    lines = error_lines(capfd.readouterr().err)
    assert len(lines) == 1 and "bad" in lines[0] and "unexpected" not in lines[0], lines
