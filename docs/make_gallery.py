"""Regenerate the README gallery: `python docs/make_gallery.py` (about a minute on 2 cores).

Renders the sweep solver's shared scenes at resolution 64, M = 3 and writes
docs/gallery.png: difffog (top row) beside the Mitsuba 3 references (bottom row) when
../shared/references is present, with one tone map per scene.
"""

from pathlib import Path

import numpy as np
from matplotlib.figure import Figure

from difffog import Renderer, SweepSolver, load_scene, plot

HERE = Path(__file__).resolve().parent
REFS = HERE.parents[1] / "shared" / "references"
SHOTS = [("fog-balls", "oblique"), ("fog-balls", "top"), ("ring-box", "oblique"),
         ("ring-box", "top")]


def main():
    rows = 2 if REFS.exists() else 1
    fig = Figure(figsize=(3.4 * len(SHOTS), 2.9 * rows), layout="compressed")
    axes = fig.subplots(rows, len(SHOTS), squeeze=False)
    cache = {}
    for j, (scene, cam) in enumerate(SHOTS):
        if scene not in cache:
            r = Renderer(load_scene(scene), resolution=64, solver=SweepSolver(M=3, tol=1e-4))
            cache[scene] = r.render().images
        img = cache[scene][cam]
        ref_path = REFS / scene / f"{cam}.npy"
        ref = np.load(ref_path) if ref_path.exists() else None
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
    out = HERE / "gallery.png"
    fig.savefig(out, dpi=72)
    print(f"wrote {out}")


if __name__ == "__main__":
    main()
