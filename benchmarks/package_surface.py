"""The package's surface: lines, docstring lines and their share, recipe keys, largest modules.

    python benchmarks/package_surface.py [--json FILE]

Docstrings are module, class and function docstrings, counted by the lines they span; recipe
keys are what a recipe table or ``--set`` may set (:func:`colmap_miho.recipe.recipe_keys`).
"""

from __future__ import annotations

import argparse
import ast
import json
import sys
from pathlib import Path

PACKAGE = Path(__file__).resolve().parents[1] / "colmap_miho"


def docstring_lines(tree: ast.AST) -> int:
    total = 0
    for node in ast.walk(tree):
        if isinstance(node, (ast.Module, ast.ClassDef, ast.FunctionDef, ast.AsyncFunctionDef)):
            body = node.body
            if body and isinstance(body[0], ast.Expr) and isinstance(body[0].value, ast.Constant):
                if isinstance(body[0].value.value, str):
                    total += body[0].end_lineno - body[0].lineno + 1
    return total


def recipe_keys() -> list[str]:
    sys.path.insert(0, str(PACKAGE.parent))  # the tree this script sits in, not an installed one
    from colmap_miho.recipe import recipe_keys as keys

    return keys()


def measure() -> dict:
    files = sorted(PACKAGE.rglob("*.py"))
    lines = doc = 0
    sizes = []
    for path in files:
        text = path.read_text()
        n = len(text.splitlines())
        lines += n
        doc += docstring_lines(ast.parse(text))
        sizes.append((n, str(path.relative_to(PACKAGE.parent))))
    sizes.sort(reverse=True)
    keys = recipe_keys()
    return {
        "modules": len(files),
        "lines": lines,
        "docstring_lines": doc,
        "docstring_share": round(doc / lines, 4),
        "recipe_keys": len(keys),
        "largest_modules": sizes[:5],
        "keys": keys,
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--json", type=Path, help="also write the figures here")
    parser.add_argument("--keys", action="store_true", help="list every recipe key")
    args = parser.parse_args()
    m = measure()
    print(f"modules {m['modules']}  lines {m['lines']}  docstring lines {m['docstring_lines']} "
          f"({100 * m['docstring_share']:.1f}%)  recipe keys {m['recipe_keys']}")
    for n, name in m["largest_modules"]:
        print(f"  {n:5d}  {name}")
    if args.keys:
        print("\n".join(m["keys"]))
    if args.json:
        args.json.write_text(json.dumps(m, indent=1))


if __name__ == "__main__":
    main()
