"""Regenerate the README gallery: `python docs/make_gallery.py` (about a minute on 2 cores).

Renders the sweep solver's shared scenes at resolution 64, M = 3 and writes
docs/gallery.png: difffog (top row) beside the Mitsuba 3 references (bottom row) when
../shared/references is present, with one tone map per scene.
"""

from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from difffog import Renderer, SweepSolver, load_scene  # noqa: E402

HERE = Path(__file__).resolve().parent
REFS = HERE.parents[1] / "shared" / "references"
SHOTS = [("fog-balls", "oblique"), ("fog-balls", "top"), ("ring-box", "oblique"),
         ("ring-box", "top")]


def main():
    rows = 2 if REFS.exists() else 1
    fig, axes = plt.subplots(rows, len(SHOTS), figsize=(3.2 * len(SHOTS), 2.9 * rows),
                             squeeze=False)
    cache = {}
    for j, (scene, cam) in enumerate(SHOTS):
        if scene not in cache:
            r = Renderer(load_scene(scene), resolution=64, solver=SweepSolver(M=3, tol=1e-4))
            cache[scene] = r.render().images
        img = cache[scene][cam]
        ref_path = REFS / scene / f"{cam}.npy"
        ref = np.load(ref_path) if ref_path.exists() else None
        vmax = float(np.percentile(ref if ref is not None else img, 99.5))
        for i, (im, who) in enumerate([(img, "difffog"), (ref, "Mitsuba 3 (4096 spp)")][:rows]):
            ax = axes[i, j]
            ax.imshow(np.clip(im / vmax, 0, 1) ** (1 / 2.2), cmap="gray", vmin=0, vmax=1)
            ax.set_title(f"{scene} / {cam}\n{who}", fontsize=9)
            ax.set_xticks([])
            ax.set_yticks([])
    fig.tight_layout()
    out = HERE / "gallery.png"
    fig.savefig(out, dpi=72)
    print(f"wrote {out}")


if __name__ == "__main__":
    main()
