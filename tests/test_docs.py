"""The manual's promises about itself: the CI runs the README's test command, no issue numbers,
and every results table sits in a section that names the command producing it."""

from __future__ import annotations

import re
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
README = REPO / "README.md"
RESULTS = REPO / "docs" / "results.md"
MAX_README_LINES = 300


def _bash_blocks(text: str) -> list[str]:
    return re.findall(r"```bash\n(.*?)```", text, re.S)


def test_ci_runs_exactly_the_readme_test_command():
    ci = [line for line in (REPO / ".ci" / "run").read_text().splitlines()
          if line.strip() and not line.startswith(("#", "set ", "cd "))]
    assert len(ci) == 1, ci
    readme_lines = [line for block in _bash_blocks(README.read_text()) for line in block.splitlines()]
    assert ci[0] in readme_lines


def test_readme_is_a_short_manual_without_issue_numbers():
    text = README.read_text()
    assert len(text.splitlines()) <= MAX_README_LINES
    for doc in (README, *sorted((REPO / "docs").glob("*.md"))):
        assert not re.search(r"\bissues? ?#?\d+", doc.read_text(), re.I), doc


def test_every_results_table_names_its_command():
    """Each table of the results document has, above it in its section, the command that
    produces it (a benchmark script or a colmap-miho command)."""
    command = re.compile(r"`(python benchmarks/\w+\.py|colmap-miho \w+)")
    sections = re.split(r"\n(?=#{2,3} )", RESULTS.read_text())
    tables = 0
    for section in sections:
        for table in re.finditer(r"(?:^ *\|.*\|\n)+", section, re.M):
            tables += 1
            assert command.search(section[:table.start()]), (section.splitlines()[0], table.group(0)[:80])
    assert tables >= 14


def test_the_readme_recipe_table_is_the_shipped_recipes_and_says_which_run_the_match_check():
    """Every shipped recipe has a row (rows may name two), no row names another, and the line
    above the table (only the default recipe runs the match check) holds for the recipe files."""
    from colmap_miho.recipe import DEFAULT_RECIPE, available_recipes, load_recipe

    text = README.read_text()
    table = text[text.index("| recipe | what | pick it when |"):]
    table = table[: table.index("\n\n")]
    named = {n for row in table.splitlines()[2:] for n in re.findall(r"`([a-z_]+)`", row.split("|")[1])}
    assert named == set(available_recipes())
    assert "Only the default\nrecipe runs it" in text or "Only the default recipe runs it" in text
    checked = {r for r in available_recipes() if load_recipe(r).match_check.enabled}
    assert checked == {DEFAULT_RECIPE}


def test_refine_help_says_what_the_default_does():
    from colmap_miho.commands import refine

    for stage in ("MOP+MiHo", "match check", "least-squares matching", "--set match_check.mode=off"):
        assert stage in refine.DESCRIPTION, stage
