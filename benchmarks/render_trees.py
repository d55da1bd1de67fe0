"""A render through the command line, cold and from the cache, for one or more source trees
alternated in one run: what a user waits for, and where.

Per scene and round, each tree (in turn, the order reversed every other round) renders the
scene twice in new processes (``python -m difffog render SCENE``, its default preset) on an
empty ``DIFFFOG_CACHE_DIR`` of its own: ``cold`` compiles, ``cached`` loads its programs from
JAX's persistent cache.  Reported, medians over the rounds: the command's wall time (the
interpreter, the imports, the set-up, compile, run and the files written), the compile seconds
of the light and of the images (``report.json``), the images' run and the whole render
(``total_s``).  The images of every tree are compared with the first tree's (max |Δ| over max
|ref|).  The report starts with the machine and its copy bandwidth, measured in the same run.

    git worktree add /tmp/old <commit>
    python benchmarks/render_trees.py --trees /tmp/old . --scenes fog-balls cloud-tomo
    python benchmarks/render_trees.py --trees /tmp/old . --scenes "fog-balls -N 128 -M 5"
"""

from __future__ import annotations

import argparse
import shlex
import shutil
import statistics as st
import tempfile
from pathlib import Path

import numpy as np

import _common as C

ROOT = Path(__file__).resolve().parents[1]


def _render(tree: Path, scene: str, cache: Path, out: Path) -> dict:
    rep, wall = C.cli_render(shlex.split(scene), out, cache, src=tree / "src")
    t = rep["timings_s"]
    return dict(wall=wall, light_compile=t["light_compile_s"],
                images_compile=t["images_compile_s"], light=t["light_s"], images=t["images_s"],
                total=rep["total_s"], lattice="×".join(map(str, rep["settings"]["lattice_shape"])))


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--trees", nargs="+", default=[str(ROOT)])
    ap.add_argument("--scenes", nargs="+", default=["fog-balls"],
                    help="scenes, each with its render options if any: 'fog-balls -N 128 -M 5'")
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("--out", default=str(C.RESULTS / "render_trees.md"))
    a = ap.parse_args(argv)
    trees = [Path(t).resolve() for t in a.trees]
    info = C.machine()
    keys = ("wall", "light_compile", "images_compile", "light", "images", "total")
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        for scene in a.scenes:
            runs = {(i, kind): [] for i in range(len(trees)) for kind in ("cold", "cached")}
            for r in range(a.rounds):
                order = list(range(len(trees)))
                for i in (order if r % 2 == 0 else order[::-1]):
                    cache = tmp / f"cache{i}"
                    shutil.rmtree(cache, ignore_errors=True)
                    for kind in ("cold", "cached"):
                        runs[i, kind].append(_render(trees[i], scene, cache, tmp / f"out{i}"))
                    print(scene, trees[i], r, runs[i, "cached"][-1], flush=True)
            ref = {p.stem: np.load(p) for p in sorted((tmp / "out0").glob("*.npy"))}
            for i, tree in enumerate(trees):
                imgs = {p.stem: np.load(p) for p in sorted((tmp / f"out{i}").glob("*.npy"))}
                diff = max(float(np.abs(imgs[k] - ref[k]).max() / np.abs(ref[k]).max())
                           for k in ref)
                for kind in ("cold", "cached"):
                    med = {k: st.median(x[k] for x in runs[i, kind]) for k in keys}
                    rows.append([scene, str(tree), kind, runs[i, kind][0]["lattice"],
                                 f"{med['wall']:.2f}",
                                 f"{med['light_compile']:.2f} + {med['images_compile']:.2f} = "
                                 f"{med['light_compile'] + med['images_compile']:.2f}",
                                 f"{med['light']:.2f}", f"{med['images']:.2f}",
                                 f"{med['total']:.2f}", f"{diff:.1e}"])
    lines = ["# A render through the command line, cold and from the cache", "",
             f"`python benchmarks/render_trees.py` (see its docstring); medians of "
             f"{a.rounds} rounds (new processes, the trees alternated)", "",
             *C.machine_lines(info), "",
             *C.md_table(["scene", "tree", "run", "lattice", "wall s",
                          "compile s (light + images)", "light run s", "images run s",
                          "render s (total_s)",
                          "images: max rel. difference from the first tree"], rows)]
    C.write_text(a.out, lines)


if __name__ == "__main__":
    main()
