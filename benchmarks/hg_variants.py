"""Clouds of every forward-scattering strength against Mitsuba 3: the shared cloud-tomo scene
with its isotropic fog made Henyey–Greenstein (g = 0, 0.85, 0.95, 0.99), its six views.

    python benchmarks/hg_variants.py --references     # Mitsuba 3 (pip install mitsuba) renders:
                                                      #   results/hg_variants/mitsuba_g<g>.npz
    python benchmarks/hg_variants.py [--n 32 64] [--g 0.85 0.95 0.99 0]
                                                      # difffog against them: hg_variants.md

The shared references hold one Henyey–Greenstein scene (cloud-plane, g = 0.85); a strongly
forward-scattering fog is where the sweep's coarse directions matter most (the sun's first
collision on M = 3's cells, docs/validation.md "The sun's forward peak").  The references are
``cloud_b.py``'s conversion of the scene (validated there against the shared cloud-tomo
references) with ``{"type": "hg", "g": g}`` for the phase: ``volpath``, 4096 samples per pixel
in 4 independent chunks (seeds 17, 1017, 2017, 3017), the mean and the chunks' standard error
per pixel (float32).  Errors as ``validate_references.py``'s: the bias of the mean and the
relative RMSE with the reference's own noise removed in quadrature ("0.0": below its noise).
"""

from __future__ import annotations

import argparse
import json
import time

import numpy as np

import _common

OUT = _common.RESULTS / "hg_variants"
CAMERAS = ("top", "view0", "view1", "view2", "view3", "view4")


def scene_path():
    return _common.HERE.parent / "src" / "difffog" / "data" / "scenes" / "cloud-tomo.toml"


def references(gs, spp: int, chunks: int = 4) -> None:
    import cloud_b

    mi = cloud_b.mitsuba()
    sd, cams = cloud_b.scene_dict(mi, scene_path())
    OUT.mkdir(parents=True, exist_ok=True)
    for g in gs:
        sd["fogbox"]["interior"]["phase"] = {"type": "hg", "g": float(g)}
        res, t0 = {}, time.perf_counter()
        for name in CAMERAS:
            imgs = np.array([np.array(mi.render(
                mi.load_dict({**sd, "camera": cloud_b.sensor(mi, cams[name], spp // chunks)}),
                seed=1000 * k + 17), np.float64)[..., 0] for k in range(chunks)])
            res[name] = imgs.mean(0).astype(np.float32)
            res[name + "_se"] = (imgs.std(0, ddof=1) / np.sqrt(chunks)).astype(np.float32)
        np.savez(OUT / f"mitsuba_g{g:g}.npz", **res)
        (OUT / f"mitsuba_g{g:g}.json").write_text(json.dumps(
            {"scene": "cloud-tomo", "phase": {"type": "hg", "g": float(g)}, "spp": spp,
             "chunks": chunks, "variant": mi.variant(), "mitsuba": mi.__version__,
             "seconds": round(time.perf_counter() - t0, 1)}, indent=1) + "\n")
        print(f"g = {g:g}: {time.perf_counter() - t0:.0f} s", flush=True)


def compare(gs, ns, M: int) -> None:
    import jax.numpy as jnp

    import difffog as df

    rows = []
    for g in gs:
        ref = np.load(OUT / f"mitsuba_g{g:g}.npz")
        scene = df.load_scene(str(scene_path()),
                              ["fog.phase=henyey-greenstein", f"fog.g={g:g}"])
        for n in ns:
            model = df.forward_model(scene, "sweep", accuracy="default", resolution=n, M=M)
            t0 = time.perf_counter()
            imgs = model.images(model.params(jnp.float32))
            sec = time.perf_counter() - t0
            cells = []
            for c in CAMERAS:
                r = np.asarray(ref[c], np.float64)
                noise = float(np.sqrt(np.mean(np.asarray(ref[c + "_se"], np.float64) ** 2)))
                m = _common.compare(np.asarray(imgs[c]), r, noise)
                cells.append(f"{100 * m['bias']:+.1f} / {100 * m['rel_rmse_corr']:.1f}")
            rows.append([f"{g:g}", n, M] + cells + [f"{sec:.1f}"])
            print(" | ".join(map(str, rows[-1])), flush=True)
    info = _common.machine()
    lines = ["# Henyey–Greenstein variants of cloud-tomo against Mitsuba 3", "",
             "Bias of the mean / relative RMSE with the reference's noise removed, in % "
             "(`python benchmarks/hg_variants.py`; references: `results/hg_variants/`).", ""]
    lines += _common.machine_lines(info) + [""]
    lines += _common.md_table(["g", "N", "M"] + list(CAMERAS) + ["s (first render)"], rows)
    _common.write_text(_common.RESULTS / "hg_variants.md", "\n".join(lines) + "\n")


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--references", action="store_true",
                    help="render the Mitsuba 3 references (pip install mitsuba)")
    ap.add_argument("--g", type=float, nargs="+", default=[0.85, 0.95, 0.99, 0.0])
    ap.add_argument("--n", type=int, nargs="+", default=[32, 64])
    ap.add_argument("--m", type=int, default=3)
    ap.add_argument("--spp", type=int, default=4096)
    a = ap.parse_args(argv)
    if a.references:
        references(a.g, a.spp)
    else:
        compare(a.g, a.n, a.m)


if __name__ == "__main__":
    main()
