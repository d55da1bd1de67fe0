"""The splat paper's figure set, reproduced with difffog's splat solver (Zhang & Crawfis):

* ``splat_clouds.png``: cloud-plane's cloud (the airplane removed) lit from behind it and from
  behind the viewer: no multiple scattering (Fig. 1), multiple forward scattering (Fig. 2),
  forward and back scattering (Fig. 4), with the paper's kernels;
* ``splat_soft_shadows.png``: hard vs soft shadows (a sun of angular radius 0 vs 4°) of the
  airplane on the cloud and ground (Figs. 13, 16-18) and of the ring in the translucent cube
  (Fig. 11), with a profile across the row where they differ most.

    python docs/splat_figures.py            # N = 48, writes docs/splat_*.png
    python docs/splat_figures.py --quick --out /tmp/figs   # N = 16 (also --smoke), quick check
    python docs/splat_figures.py --figures shadows

The models are the public ``difffog.forward_model(scene, "splat", ...)``.  Locating the shadow
of an occluder on the ground uses difffog's internal ray caster on purpose
(``difffog.geometry._rays``: ``scene_triangles``, ``cast_rays``) and the cameras' rays
(``difffog.forward._camera.camera_rays``).
"""

from __future__ import annotations

import argparse
import dataclasses
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

import difffog as df  # noqa: E402
from difffog import Camera, load_scene, set_param  # noqa: E402
from difffog.forward._camera import camera_rays  # noqa: E402
from difffog.geometry._rays import cast_rays, scene_triangles  # noqa: E402

HERE = Path(__file__).resolve().parent


def show(ax, img, title, vmax=None):
    vmax = vmax or float(np.percentile(img, 99.5)) or 1.0
    ax.imshow(np.clip(img / vmax, 0, 1) ** (1 / 2.2), cmap="gray", interpolation="nearest")
    ax.set_title(title, fontsize=9)
    ax.set_xticks([])
    ax.set_yticks([])


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", "--smoke", dest="smoke", action="store_true",
                    help="N = 16, 48-pixel images (a quick check)")
    ap.add_argument("--out", type=Path, default=HERE)
    ap.add_argument("--figures", nargs="+", choices=("clouds", "shadows"),
                    default=["clouds", "shadows"])
    args = ap.parse_args(argv)
    N = 16 if args.smoke else 48
    px = 48 if args.smoke else 160
    args.out.mkdir(parents=True, exist_ok=True)

    if "clouds" in args.figures:
        clouds(args.out, N, px)
    if "shadows" in args.figures:
        shadows(args.out, N, px)


def clouds(out: Path, N: int, px: int):
    # the cloud lit from behind it (back-to-front sheets) and from behind the viewer
    # (front-to-back), the paper's Figs. 1, 2, 4; with the paper's kernels (similarity off: the
    # scattered light keeps the HG phase of g = 0.85, which sends 3.6% of it backwards)
    cam = Camera(name="side", kind="perspective", position=(0.5, -0.9, 0.45),
                 look_at=(0.5, 0.5, 0.45), up=(0.0, 0.0, 1.0), fov_deg=45.0,
                 resolution=(px, int(px * 0.75)))
    configs = [("no multiple scattering (Fig. 1)", dict(forward_scatter=False, back_scatter=False)),
               ("multiple forward scattering (Fig. 2)", dict(back_scatter=False)),
               ("forward + back scattering (Fig. 4)", dict())]
    fig, axes = plt.subplots(2, 3, figsize=(12, 6.6), constrained_layout=True)
    for row, (light, azimuth) in zip(axes, (("sun behind the cloud", 90),
                                            ("sun behind the viewer", -90))):
        sc = load_scene("cloud-plane", ["sun.zenith_deg=60", f"sun.azimuth_deg={azimuth}"])
        sc = sc.replace(shapes=(), cameras=(cam,))
        imgs, clear = [], None
        for _, kw in configs:
            model = df.forward_model(sc, "splat", accuracy=None, resolution=N,
                                     similarity=False, **kw)
            p = model.params()
            imgs.append(np.asarray(model(p)["side"]))
            if clear is None:  # the same view without the cloud: which pixels see it
                p0 = set_param(set_param(p, sc, "fog.scattering", 0.0), sc, "fog.absorption", 0.0)
                clear = np.asarray(model(p0)["side"])
        cloud = np.abs(imgs[0] - clear) > 0.02 * float(clear.max())
        vmax = max(float(np.percentile(i, 99.5)) for i in imgs)
        for ax, (title, _), img in zip(row, configs, imgs):
            ratio = float(img[cloud].mean() / imgs[0][cloud].mean())
            show(ax, img, f"{light}: {title}\ncloud pixels {ratio:.3f}× as bright as with none",
                 vmax)
    fig.savefig(out / "splat_clouds.png", dpi=80)
    plt.close(fig)
    print(f"wrote {out / 'splat_clouds.png'}")


def shadow_centre(scene, camera, occluder: str) -> tuple[int, int]:
    """(row, column) of the centre of the pixels that see the ground in ``occluder``'s shadow."""
    tris = scene_triangles(scene)
    names = [sh.name for sh in scene.shapes]
    o, d = camera_rays(camera, 1)
    H, W = o.shape[:2]
    t, f, _, _ = cast_rays(tris, o.reshape(-1, 3), d.reshape(-1, 3))
    ground = (f >= 0) & (tris.shape[np.maximum(f, 0)] == names.index("ground"))
    x = o.reshape(-1, 3)[ground] + t[ground, None] * d.reshape(-1, 3)[ground]
    sun = np.broadcast_to(scene.sun.direction, x.shape)
    _, fs, _, _ = cast_rays(tris, x + 1e-6 * sun, sun)
    mask = np.zeros(H * W, bool)
    mask[np.flatnonzero(ground)] = (fs >= 0) & (tris.shape[np.maximum(fs, 0)]
                                                == names.index(occluder))
    ys, xs = np.nonzero(mask.reshape(H, W))
    return int(round(ys.mean())), int(round(xs.mean()))


def shadows(out: Path, N: int, px: int):
    # --- hard vs soft shadows ---------------------------------------------------------------
    rows = []
    for name, occluder in (("cloud-plane", "airplane"), ("translucent-cube", "ring")):
        base = load_scene(name)
        cam = dataclasses.replace(base.camera("oblique"), resolution=(px, int(px * 0.75)))
        pair = []
        for radius in (0.0, 4.0):
            s = base.replace(sun=dataclasses.replace(base.sun, angular_radius_deg=radius),
                             cameras=(cam,))
            model = df.forward_model(s, "splat", accuracy=None, resolution=N, similarity=True,
                                     soft_shadows=radius > 0)
            pair.append(np.asarray(model()["oblique"]))
        rows.append((name, occluder, s, cam, pair))
    fig, axes = plt.subplots(2, 3, figsize=(13, 6.5), constrained_layout=True,
                             gridspec_kw={"width_ratios": [1, 1, 0.9]})
    for (name, occluder, s, cam, pair), ax_row in zip(rows, axes):
        vmax = float(np.percentile(pair[0], 99.5))
        show(ax_row[0], pair[0], f"{name}: hard shadows (point sun)", vmax)
        show(ax_row[1], pair[1], f"{name}: soft shadows (sun radius 4°)", vmax)
        # a profile through the occluder's shadow on the ground (found by ray casting), along
        # the row or the column through its centre, whichever shows the two differ more
        y, x = shadow_centre(s, cam, occluder)
        diff = np.abs(pair[0] - pair[1])
        if diff[y].sum() >= diff[:, x].sum():
            i, what, cut = int(y), "row", lambda a, i: a[i]
            for a in ax_row[:2]:
                a.axhline(i, color="tab:red", lw=0.6, ls="--")
        else:
            i, what, cut = int(x), "column", lambda a, i: a[:, i]
            for a in ax_row[:2]:
                a.axvline(i, color="tab:red", lw=0.6, ls="--")
        ax_row[2].plot(cut(pair[0], i), color="k", lw=1, label="hard")
        ax_row[2].plot(cut(pair[1], i), color="tab:orange", lw=1, label="soft")
        ax_row[2].set_title(f"radiance along the dashed {what} {i}", fontsize=9)
        ax_row[2].set_xlabel("pixel", fontsize=8)
        ax_row[2].tick_params(labelsize=7)
        ax_row[2].legend(fontsize=8)
    fig.savefig(out / "splat_soft_shadows.png", dpi=80)
    plt.close(fig)
    print(f"wrote {out / 'splat_soft_shadows.png'}")


if __name__ == "__main__":
    main()
