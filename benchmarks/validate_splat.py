"""The splat solver against the Mitsuba 3 references (validation ladder step 3).

For every shared scene the splat can handle (it needs a sun and an open domain: not furnace,
not slab) and every camera, renders the scene with ``SplatRenderer`` in the paper's three
configurations — attenuation only, + multiple forward scattering, + forward and back scattering
(Zhang & Crawfis Figs. 1, 2, 4) — and with the similarity-scaled sheets (``similarity=True``),
and reports the metrics of ``validate_references.py`` (relative RMSE with the reference noise
removed in quadrature, smoothed 3×3, bias).  Writes ``benchmarks/results/splat_references.csv``,
``splat_references.md`` and per camera ``splat_<scene>_<camera>.png`` (splat | Mitsuba | error)
for the most accurate configuration.

    python benchmarks/validate_splat.py                  # N = 64, all scenes
    python benchmarks/validate_splat.py --N 32 --scenes cloud-plane
"""

from __future__ import annotations

import argparse
import csv
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from validate_references import RESULTS, compare, load_reference, save_png  # noqa: E402

from difffog import SplatRenderer, load_scene  # noqa: E402

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
    ap.add_argument("--N", type=int, default=64)
    ap.add_argument("--sheets", type=int, default=None)
    ap.add_argument("--scenes", nargs="+", default=list(SCENES))
    ap.add_argument("--out", type=Path, default=RESULTS)
    args = ap.parse_args(argv)
    rows, kept = [], {}
    for scene_name in args.scenes:
        scene = load_scene(scene_name)
        for label, kw in CONFIGS.items():
            t = time.perf_counter()
            r = SplatRenderer(scene, resolution=args.N, sheets=args.sheets, **kw)
            out = r.render()
            for cam, img in out.images.items():
                ref, noise = load_reference(scene_name, cam)
                m = compare(img, ref, noise)
                row = {"scene": scene_name, "camera": cam, "config": label, "N": args.N,
                       "sheets": out.light[cam]["sheets"], **m,
                       "prepare_s": out.timings["prepare_s"],
                       "compile_s": out.timings["render_compile_s"],
                       "render_s": out.timings["render_s"]}
                rows.append(row)
                kept[(scene_name, cam, label)] = (np.asarray(img, np.float64), ref)
                print(f"{scene_name:16s} {cam:8s} {label:28s} bias {100 * m['bias']:+6.1f}% "
                      f"rmse_corr {100 * m['rel_rmse_corr']:5.1f}% s3 {100 * m['rel_rmse_s3']:5.1f}%"
                      f" render {out.timings['render_s']:.2f}s (all {time.perf_counter() - t:.0f}s)",
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
        save_png(args.out / f"splat_{s}_{c}.png", s, c, img, ref, f"splat, {r_['config']}", r_)
        shrink_png(args.out / f"splat_{s}_{c}.png")
    labels = list(CONFIGS)
    lines = [
        "# The splat solver against the Mitsuba 3 references",
        "",
        f"N = {args.N} (voxels splatted), sheets = {args.sheets or 'one per voxel'}, "
        "supersample 1, float32, soft shadows on (the scenes' suns are points). Relative RMSE "
        "in % of the reference mean with the reference noise removed in quadrature (bias of the "
        "mean in brackets); the sweep's figure at N = 64, M = 3 from `references.md`. Render "
        "time: warm seconds per image on the shared 2-core CPU (compile apart). "
        "`python benchmarks/validate_splat.py`",
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
    (args.out / "splat_references.md").write_text("\n".join(lines) + "\n")
    print("\n".join(lines))


if __name__ == "__main__":
    main()
