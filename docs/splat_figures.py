"""The splat paper's figure set, reproduced with difffog's splat solver (Zhang & Crawfis):

* ``splat_clouds.png``: cloud-plane's cloud (the airplane removed) seen with the light from
  behind it: no multiple scattering (Fig. 1), multiple forward scattering (Fig. 2), forward and
  back scattering (Fig. 4);
* ``splat_soft_shadows.png``: hard vs soft shadows (a sun of angular radius 0 vs 4°) of the
  airplane on the cloud and ground (Figs. 13, 16-18) and of the ring in the translucent cube
  (Fig. 11).

    python docs/splat_figures.py            # N = 48, writes docs/splat_*.png
    python docs/splat_figures.py --smoke    # N = 16, quick check
"""

from __future__ import annotations

import argparse
import dataclasses
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from difffog import SplatRenderer, load_scene  # noqa: E402
from difffog._scene import Camera  # noqa: E402

HERE = Path(__file__).resolve().parent


def show(ax, img, title, vmax=None):
    vmax = vmax or float(np.percentile(img, 99.5)) or 1.0
    ax.imshow(np.clip(img / vmax, 0, 1) ** (1 / 2.2), cmap="gray", interpolation="nearest")
    ax.set_title(title, fontsize=9)
    ax.set_xticks([])
    ax.set_yticks([])


def main(argv=None):
    ap = argparse.ArgumentParser()
    ap.add_argument("--smoke", action="store_true")
    ap.add_argument("--out", type=Path, default=HERE)
    args = ap.parse_args(argv)
    N = 16 if args.smoke else 48
    px = 48 if args.smoke else 160

    # --- clouds with the light behind them (back-to-front order, the paper's Figs. 1, 2, 4) ---
    sc = load_scene("cloud-plane", ["sun.zenith_deg=60", "sun.azimuth_deg=90"])
    cam = Camera(name="side", kind="perspective", position=(0.5, -0.9, 0.45),
                 look_at=(0.5, 0.5, 0.45), up=(0.0, 0.0, 1.0), fov_deg=45.0,
                 resolution=(px, int(px * 0.75)))
    sc = sc.replace(shapes=(), cameras=(cam,))
    configs = [("no multiple scattering (Fig. 1)", dict(forward_scatter=False, back_scatter=False)),
               ("multiple forward scattering (Fig. 2)", dict(back_scatter=False)),
               ("forward + back scattering (Fig. 4)", dict())]
    imgs = [np.asarray(SplatRenderer(sc, resolution=N, **kw)()["side"]) for _, kw in configs]
    vmax = max(float(np.percentile(i, 99.5)) for i in imgs)
    fig, axes = plt.subplots(1, 3, figsize=(12, 3.3), constrained_layout=True)
    for ax, (title, _), img in zip(axes, configs, imgs):
        show(ax, img, title, vmax)
    fig.savefig(args.out / "splat_clouds.png", dpi=80)
    plt.close(fig)

    # --- hard vs soft shadows ---------------------------------------------------------------
    rows = []
    for name, over in (("cloud-plane", []), ("translucent-cube", [])):
        base = load_scene(name, over)
        cam = dataclasses.replace(base.camera("oblique"), resolution=(px, int(px * 0.75)))
        pair = []
        for radius in (0.0, 4.0):
            s = base.replace(sun=dataclasses.replace(base.sun, angular_radius_deg=radius),
                             cameras=(cam,))
            pair.append(np.asarray(SplatRenderer(s, resolution=N, similarity=True,
                                                 soft_shadows=radius > 0)()["oblique"]))
        rows.append((name, pair))
    fig, axes = plt.subplots(2, 2, figsize=(9, 6.5), constrained_layout=True)
    for (name, pair), ax_row in zip(rows, axes):
        vmax = float(np.percentile(pair[0], 99.5))
        show(ax_row[0], pair[0], f"{name}: hard shadows (point sun)", vmax)
        show(ax_row[1], pair[1], f"{name}: soft shadows (sun radius 4°)", vmax)
    fig.savefig(args.out / "splat_soft_shadows.png", dpi=80)
    plt.close(fig)
    print(f"wrote {args.out / 'splat_clouds.png'} and {args.out / 'splat_soft_shadows.png'}")


if __name__ == "__main__":
    main()
