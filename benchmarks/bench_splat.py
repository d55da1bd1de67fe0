"""Speed of the splat solver: time per image of cloud-plane's top view at 128² and 256² pixels,
for the 64³ cloud and at 128³, with the sheet count as the accuracy knob.

Compilation is timed apart (``lower().compile()``); the warm time is the median of 3 runs
(``block_until_ready``).  At 128² the image is compared with the Mitsuba reference shipped with
difffog (``difffog.study.references``, or ``--references DIR``; relative RMSE with its noise
removed, as ``validate_references.py``).  The model is the public ``difffog.forward_model(...,
"splat")``.  Writes ``bench_splat.md`` (with the machine: JAX backend and devices, copy
bandwidth, measured in the same run) to ``--out`` (default ``benchmarks/results``).

    python benchmarks/bench_splat.py
    python benchmarks/bench_splat.py --quick --out /tmp/splat     # 16³, 128², one sheet count
"""

from __future__ import annotations

import argparse
import dataclasses
import os
import time
from pathlib import Path

import numpy as np

import _common as C

CASES = ((64, 128, 0.5), (64, 128, 1.0), (64, 128, 2.0), (64, 256, 1.0), (128, 128, 1.0),
         (128, 256, 1.0))  # (N, pixels, sheets per voxel): the knob at 64³ / 128², then bigger
QUICK = ((16, 128, 1.0),)


def run(N, pixels, sheets, refdir=None, similarity=True):
    import difffog as df

    sc = df.load_scene("cloud-plane")
    cam = dataclasses.replace(sc.camera("top"), resolution=(pixels, pixels))
    sc = sc.replace(cameras=(cam,))
    t = time.perf_counter()
    model = df.forward_model(sc, "splat", accuracy=None, resolution=N, sheets=sheets,
                             similarity=similarity)
    setup = time.perf_counter() - t
    p = model.params()
    comp, compile_s = C.compile_timed(lambda m, q: m.images(q), model, p)
    t = C.time_calls(lambda: comp(model, p), 3, first=False)
    img = t.value["top"]
    info = model.settings()["passes"]["top"]
    err = ""
    if pixels == 128:
        ref, noise = C.reference("cloud-plane", "top", refdir)
        err = f"{100 * C.compare(np.asarray(img), ref, noise)['rel_rmse_corr']:.1f}"
    return dict(N=N, pixels=pixels, sheets=info["sheets"],
                buffer="x".join(map(str, info["shadow_buffer"])), setup=setup,
                compile=compile_s, warm=t.median, err=err)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--references", type=Path, default=None,
                    help="folder of the Mitsuba references (default: the shipped ones)")
    ap.add_argument("--out", type=Path, default=C.RESULTS, help="folder of the report")
    C.add_quick(ap)
    args = C.parse(ap, argv)
    info = C.machine()
    C.print_machine(info)
    rows = []
    for N, pixels, mult in QUICK if args.quick else CASES:
        K = None if mult == 1.0 else max(4, int(round(mult * N * 1.05)))
        row = run(N, pixels, K, args.references)
        rows.append(row)
        print(row, flush=True)
    load = os.getloadavg()
    lines = [
        "# Splat solver speed (cloud-plane, top camera)",
        "",
        f"float32, similarity sheets, forward + back scattering (window 6), soft shadows; "
        f"CPU shared with other jobs (load average {load[0]:.1f} / {load[1]:.1f} / "
        f"{load[2]:.1f} at the end). `warm`: median of 3 renders of one image after compilation; "
        "`setup`: host-side voxelization, rasterization and footprint sheets; error: relative "
        "RMSE vs the Mitsuba reference, noise removed (128² only). "
        "`python benchmarks/bench_splat.py`",
        "",
        *C.machine_lines(info),
        "",
    ]
    lines += C.md_table(["voxels", "pixels", "sheets", "shadow buffer", "setup s", "compile s",
                         "warm s/image", "error %"],
                        [[f"{r['N']}³", f"{r['pixels']}²", r["sheets"], r["buffer"],
                          f"{r['setup']:.1f}", f"{r['compile']:.1f}", f"{r['warm']:.3f}",
                          r["err"]] for r in rows], "rrrlrrrr")
    C.write_text(args.out / "bench_splat.md", lines)
    print("\n".join(lines))


if __name__ == "__main__":
    main()
