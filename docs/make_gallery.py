"""Regenerate the README gallery: `python docs/make_gallery.py` (about a minute on 2 cores).

Renders the sweep solver's built-in scenes at resolution 64, M = 3 (``difffog.render``) and
writes docs/gallery.png: difffog (top row) beside the Mitsuba 3 references shipped with
difffog (``difffog.study.references``, or ``--references DIR``; bottom row), with one tone map
per scene.  ``--quick`` renders at resolution 16, M = 2 (a smoke test: write it elsewhere with
``--out``).
"""

import argparse
from pathlib import Path

from matplotlib.figure import Figure

import difffog as df
from difffog import plot
from difffog.study import references

HERE = Path(__file__).resolve().parent
SHOTS = [("fog-balls", "oblique"), ("fog-balls", "top"), ("ring-box", "oblique"),
         ("ring-box", "top")]


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="resolution 16, M = 2 (smoke test)")
    ap.add_argument("--references", type=Path, default=None,
                    help="folder of the Mitsuba references (default: the shipped ones)")
    ap.add_argument("--out", type=Path, default=HERE / "gallery.png")
    args = ap.parse_args(argv)
    N, M = (16, 2) if args.quick else (64, 3)
    refs = {shot: references.reference(*shot, args.references) for shot in SHOTS}
    rows = 2 if any(r is not None for r in refs.values()) else 1
    fig = Figure(figsize=(3.4 * len(SHOTS), 2.9 * rows), layout="compressed")
    axes = fig.subplots(rows, len(SHOTS), squeeze=False)
    cache = {}
    for j, (scene, cam) in enumerate(SHOTS):
        if scene not in cache:
            cache[scene] = df.render(df.load_scene(scene), solver="sweep", accuracy=None,
                                     resolution=N, M=M, tol=1e-4).images
        img = cache[scene][cam]
        ref = None if refs[(scene, cam)] is None else refs[(scene, cam)][0]
        # one tone map per column: the reference's exposure when there is one
        scale = plot.exposure(ref if ref is not None else img)
        column = {f"{scene} / {cam}\ndifffog": img}
        if ref is not None:
            column["Mitsuba 3 (4096 spp)"] = ref
        plot.image_grid(column, axes=axes[:, j], ncols=1, scale=scale, colorbar=False)
    for ax in axes.ravel():  # a gallery of pictures: no pixel rulers
        ax.set_xticks([])
        ax.set_yticks([])
        ax.set_xlabel("")
        ax.set_ylabel("")
    fig.supxlabel("Tone map per column: radiance / (99.5th percentile of the reference), "
                  "gamma 2.2", fontsize=9)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(args.out, dpi=72)
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
