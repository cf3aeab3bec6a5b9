"""Names and values read from files are data: they never forge terminal output, and bad
values are refused up front with one line naming the option, the file or the record."""

from __future__ import annotations

import sqlite3
from pathlib import Path

from colmap_miho.cli import main

FORGED = "\nERROR: forged line\x1b[31m"


def _sql(db: Path, query: str, *args) -> list:
    con = sqlite3.connect(db)
    try:
        rows = con.execute(query, args).fetchall()
        con.commit()
    finally:
        con.close()
    return rows


def _assert_not_forged(text: str) -> None:
    assert "\x1b" not in text, text
    assert not any(line.startswith("ERROR: forged") for line in text.splitlines()), text


# ------------------------------------------------------------------ A. names are escaped
def test_a_name_with_control_characters_cannot_forge_a_line(db_copy, scene, tmp_path, capfd):
    """An image whose database name holds a newline, a forged ``ERROR:`` and an ANSI escape
    is missing from the folder: the warning and the summary name it escaped."""
    image_id, name = _sql(db_copy, "SELECT image_id, name FROM images ORDER BY image_id LIMIT 1")[0]
    hostile = "é漢字" + FORGED + ".png"
    _sql(db_copy, "UPDATE images SET name = ? WHERE image_id = ?", hostile, image_id)
    capfd.readouterr()
    code = main(["refine", "--database", str(db_copy), "--images", str(scene.image_dir), "--workers", "1",
                 "--output", str(tmp_path / "out.db")])
    out, err = capfd.readouterr()
    assert code == 0, err
    for text in (out, err):
        _assert_not_forged(text)
    escaped = "é漢字\\nERROR: forged line\\x1b[31m.png"
    assert any(line.startswith("WARNING: image ") and escaped in line for line in err.splitlines()), err
    assert escaped in out, out


def test_printable_keeps_names_readable_and_escapes_controls():
    from colmap_miho.terminal import printable

    assert printable("façade_漢字.jpg") == "façade_漢字.jpg"
    assert printable("a\r\n\t\x00\x7f\x85\x9b\u202eb") == "a\\r\\n\\t\\x00\\x7f\\x85\\x9b\\u202eb"
    assert printable("x\ny", keep_newlines=True) == "x\ny"
