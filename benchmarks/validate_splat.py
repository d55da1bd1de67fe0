"""The splat solver against the Mitsuba 3 references (validation ladder step 3).

For every built-in scene with a Mitsuba reference that the splat can handle (it needs a sun and
an open domain: not furnace, not slab) and every camera, renders the scene with the splat model
(``difffog.forward_model(scene, "splat", ...)`` and ``difffog.render``) in the paper's three
configurations — attenuation only, + multiple forward scattering, + forward and back scattering
(Zhang & Crawfis Figs. 1, 2, 4) — and with the similarity-scaled sheets (``similarity=True``),
and reports the metrics of ``validate_references.py`` (``_common.compare``: relative RMSE with
the reference noise removed in quadrature, smoothed 3×3, bias) against the references shipped
with difffog (``difffog.study.references``, or ``--references DIR``).  Writes
``splat_references.csv``, ``splat_references.md`` (with the machine: JAX backend and devices,
copy bandwidth, measured in the same run) and per camera ``splat_<scene>_<camera>.png``
(splat | Mitsuba | error) for the most accurate configuration, to ``--out`` (default
``benchmarks/results``).

    python benchmarks/validate_splat.py                  # N = 64, all scenes
    python benchmarks/validate_splat.py --N 32 --scenes cloud-plane
    python benchmarks/validate_splat.py --quick --out /tmp/splat   # N = 16, fog-balls
"""

from __future__ import annotations

import argparse
import csv
import time
from pathlib import Path

import numpy as np

import _common as C
import difffog as df

SCENES = ("cloud-plane", "translucent-cube", "fog-balls", "ring-box")
CONFIGS = {  # the paper's kernels (similarity off), then the default similarity-scaled sheets
    "attenuation": dict(forward_scatter=False, back_scatter=False, similarity=False),
    "+forward": dict(back_scatter=False, similarity=False),
    "+forward+back": dict(similarity=False),
    "+forward+back, similarity": dict(similarity=True),
}
SWEEP = {  # N = 64, M = 3 rows of benchmarks/results/references.md (rmse_corr %)
    ("cloud-plane", "top"): 10.8, ("cloud-plane", "oblique"): 31.3,
    ("translucent-cube", "top"): 5.6, ("translucent-cube", "oblique"): 9.5,
    ("fog-balls", "top"): 3.5, ("fog-balls", "oblique"): 17.6,
    ("ring-box", "top"): 5.6, ("ring-box", "oblique"): 7.6,
}


def shrink_png(path: Path) -> None:
    """Re-save a matplotlib PNG with a 256-colour palette (a third of the size, no visible
    change: the figures are flat colour maps and text)."""
    from PIL import Image

    with Image.open(path) as im:
        q = im.convert("RGB").quantize(colors=256, method=Image.Quantize.FASTOCTREE,
                                       dither=Image.Dither.NONE)
    q.save(path, optimize=True)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--N", type=int, default=None, help="default 64; with --quick 16")
    ap.add_argument("--sheets", type=int, default=None)
    ap.add_argument("--scenes", nargs="+", default=None,
                    help=f"default {' '.join(SCENES)}; with --quick fog-balls")
    ap.add_argument("--references", type=Path, default=None,
                    help="folder of the Mitsuba references (default: the shipped ones)")
    ap.add_argument("--out", type=Path, default=C.RESULTS)
    C.add_quick(ap)
    args = C.parse(ap, argv)
    args.N = args.N or (16 if args.quick else 64)
    args.scenes = args.scenes or (["fog-balls"] if args.quick else list(SCENES))
    info = C.machine()
    C.print_machine(info)
    rows, kept = [], {}
    for scene_name in args.scenes:
        scene = df.load_scene(scene_name)
        for label, kw in CONFIGS.items():
            t = time.perf_counter()
            model = df.forward_model(scene, "splat", accuracy=None, resolution=args.N,
                                     sheets=args.sheets, **kw)
            out = df.render(model)
            tm = out.timings
            passes = model.settings()["passes"]
            for cam, img in out.images.items():
                ref, noise = C.reference(scene_name, cam, args.references)
                m = C.compare(img, ref, noise)
                # the splat's light pass renders the images: render = light + images
                row = {"scene": scene_name, "camera": cam, "config": label, "N": args.N,
                       "sheets": passes[cam]["sheets"], **m,
                       "prepare_s": tm["prepare_s"],
                       "compile_s": tm["light_compile_s"] + tm["images_compile_s"],
                       "render_s": tm["light_s"] + tm["images_s"]}
                rows.append(row)
                kept[(scene_name, cam, label)] = (np.asarray(img, np.float64), ref)
                print(f"{scene_name:16s} {cam:8s} {label:28s} bias {100 * m['bias']:+6.1f}% "
                      f"rmse_corr {100 * m['rel_rmse_corr']:5.1f}% s3 {100 * m['rel_rmse_s3']:5.1f}%"
                      f" render {row['render_s']:.2f}s (all {time.perf_counter() - t:.0f}s)",
                      flush=True)
    args.out.mkdir(parents=True, exist_ok=True)
    with open(args.out / "splat_references.csv", "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=list(rows[0]))
        w.writeheader()
        for r_ in rows:
            w.writerow({k: (f"{v:.6g}" if isinstance(v, float) else v) for k, v in r_.items()})
    best = {}
    for r_ in rows:
        k = (r_["scene"], r_["camera"])
        if k not in best or r_["rel_rmse_corr"] < best[k]["rel_rmse_corr"]:
            best[k] = r_
    for (s, c), r_ in best.items():
        img, ref = kept[(s, c, r_["config"])]
        C.save_comparison_png(args.out / f"splat_{s}_{c}.png", s, c, img, ref,
                              f"splat, {r_['config']}", r_)
        shrink_png(args.out / f"splat_{s}_{c}.png")
    labels = list(CONFIGS)
    lines = [
        "# The splat solver against the Mitsuba 3 references",
        "",
        f"N = {args.N} (voxels splatted), sheets = {args.sheets or 'one per voxel'}, "
        "supersample 1, float32, soft shadows on (the scenes' suns are points). Relative RMSE "
        "in % of the reference mean with the reference noise removed in quadrature (bias of the "
        "mean in brackets); the sweep's figure at N = 64, M = 3 from `references.md`. Render "
        "time: warm seconds per render of a scene's cameras on the machine below (compile "
        "apart). `python benchmarks/validate_splat.py`",
        "",
        *C.machine_lines(info),
        "",
        "| scene | camera | " + " | ".join(labels) + " | sweep | splat render s |",
        "|---|---|" + "---:|" * (len(labels) + 2),
    ]
    for s in args.scenes:
        for c in sorted({r_["camera"] for r_ in rows if r_["scene"] == s}, reverse=True):
            cells = []
            for lab in labels:
                r_ = next(x for x in rows if x["scene"] == s and x["camera"] == c
                          and x["config"] == lab)
                cells.append(f"{100 * r_['rel_rmse_corr']:.1f} ({100 * r_['bias']:+.0f})")
                rs = r_["render_s"]
            lines.append(f"| {s} | {c} | " + " | ".join(cells)
                         + f" | {SWEEP.get((s, c), float('nan')):.1f} | {rs:.2f} |")
    lines += ["", "Error maps (best configuration per camera): `splat_<scene>_<camera>.png`."]
    C.write_text(args.out / "splat_references.md", lines)
    print("\n".join(lines))


if __name__ == "__main__":
    main()
