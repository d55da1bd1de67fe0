"""Maintainer check: the scenes difffog ships (``src/difffog/data/scenes``) say the same as the
benchmark scene files they were copied from, and every benchmark scene loads.

    python benchmarks/check_shared_scenes.py                 # ../shared/scenes beside the repository
    python benchmarks/check_shared_scenes.py PATH/TO/scenes

The benchmark folder is not part of a clone or an install, so this is not in the test suite
(where it could only be skipped); run it when the shared scenes change.  Exit status 1 names
every scene that differs.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

import difffog as df


def check(folder: Path) -> list[str]:
    problems = []
    shipped = set(df.builtin_scenes())
    for path in sorted(folder.glob("*.toml")):
        s = df.load_scene(path)
        if not s.cameras:
            problems.append(f"{path.name}: no camera")
        if path.stem not in shipped:  # a shared scene that is not shipped: it loads
            print(f"{path.stem}: loads (not shipped)")
            continue
        mine = df.load_scene(path.stem)
        same = s.replace(source=None) == mine.replace(source=None) and all(
            np.array_equal(a.vertices, b.vertices)
            for a, b in zip(s.shapes, mine.shapes) if a.kind == "mesh")
        print(f"{path.stem}: {'same as the shipped copy' if same else 'DIFFERS from the shipped copy'}")
        if not same:
            problems.append(f"{path.stem}: the shipped copy differs from {path}")
    return problems


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("folder", nargs="?",
                    default=str(Path(__file__).resolve().parents[2] / "shared" / "scenes"))
    a = ap.parse_args(argv)
    folder = Path(a.folder)
    if not folder.is_dir():
        print(f"no scene folder {folder}: give the benchmark scenes' folder", file=sys.stderr)
        return 2
    problems = check(folder)
    for p in problems:
        print(p, file=sys.stderr)
    return 1 if problems else 0


if __name__ == "__main__":
    sys.exit(main())
