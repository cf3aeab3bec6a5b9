"""What a COLMAP database holds, for tests that compare two runs' outputs byte for byte."""

from __future__ import annotations

import sqlite3
from pathlib import Path

#: Tables the refine pipeline writes, and the column that orders their rows.
WRITTEN_TABLES = {"keypoints": "image_id", "matches": "pair_id", "two_view_geometries": "pair_id"}


def database_rows(path: Path) -> dict[str, list[tuple]]:
    """Every row (blobs included) of the tables ``refine`` writes, ordered by their key."""
    con = sqlite3.connect(f"file:{path}?mode=ro", uri=True)
    try:
        return {t: con.execute(f"SELECT * FROM {t} ORDER BY {key}").fetchall()  # noqa: S608 - fixed names
                for t, key in WRITTEN_TABLES.items()}
    finally:
        con.close()


def assert_same_database(a: Path, b: Path) -> None:
    """The written tables of ``a`` and ``b`` are identical (row by row, blob by blob)."""
    ra, rb = database_rows(a), database_rows(b)
    for table in WRITTEN_TABLES:
        assert len(ra[table]) == len(rb[table]), f"{table}: {len(ra[table])} vs {len(rb[table])} rows"
        for x, y in zip(ra[table], rb[table], strict=True):
            assert x == y, f"{table}: rows differ at key {x[0]}"


def sql(db: Path, query: str, *args) -> list:
    """Run one SQL statement on the database file ``db`` (committed); its rows."""
    con = sqlite3.connect(db)
    try:
        rows = con.execute(query, args).fetchall()
        con.commit()
    finally:
        con.close()
    return rows
