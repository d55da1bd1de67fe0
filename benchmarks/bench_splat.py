"""Speed of the splat solver: time per image of cloud-plane's top view at 128² and 256² pixels,
for the 64³ cloud and at 128³, with the sheet count as the accuracy knob.

Compilation is timed apart (``jit.lower().compile()``); the warm time is the median of 3 runs
(``block_until_ready``).  At 128² the image is compared with the Mitsuba reference (relative
RMSE with its noise removed, as ``validate_references.py``).  Writes
``benchmarks/results/bench_splat.md``.

    python benchmarks/bench_splat.py
"""

from __future__ import annotations

import dataclasses
import os
import statistics
import sys
import time
from pathlib import Path

import jax
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from validate_references import RESULTS, compare, load_reference  # noqa: E402

from difffog import SplatRenderer, load_scene  # noqa: E402


def run(N, pixels, sheets, similarity=True):
    sc = load_scene("cloud-plane")
    cam = dataclasses.replace(sc.camera("top"), resolution=(pixels, pixels))
    sc = sc.replace(cameras=(cam,))
    t = time.perf_counter()
    r = SplatRenderer(sc, resolution=N, sheets=sheets, similarity=similarity)
    setup = time.perf_counter() - t
    p = r.params()
    t = time.perf_counter()
    comp = r._forward.lower(r.plans, p).compile()
    compile_s = time.perf_counter() - t
    times = []
    for _ in range(3):
        t = time.perf_counter()
        img = jax.block_until_ready(comp(r.plans, p))["top"]
        times.append(time.perf_counter() - t)
    info = r.plan_info["top"]
    err = ""
    if pixels == 128:
        ref, noise = load_reference("cloud-plane", "top")
        err = f"{100 * compare(np.asarray(img), ref, noise)['rel_rmse_corr']:.1f}"
    return dict(N=N, pixels=pixels, sheets=info["sheets"], buffer="x".join(map(str, info[
        "shadow_buffer"])), setup=setup, compile=compile_s, warm=statistics.median(times), err=err)


def main():
    rows = []
    # the sheet count (accuracy knob) at 64³ / 128², then the bigger images and lattice
    for N, pixels, mult in ((64, 128, 0.5), (64, 128, 1.0), (64, 128, 2.0), (64, 256, 1.0),
                            (128, 128, 1.0), (128, 256, 1.0)):
        K = None if mult == 1.0 else max(4, int(round(mult * N * 1.05)))
        row = run(N, pixels, K)
        rows.append(row)
        print(row, flush=True)
    load = os.getloadavg()
    lines = [
        "# Splat solver speed (cloud-plane, top camera)",
        "",
        f"float32, similarity sheets, forward + back scattering (window 6), soft shadows; "
        f"2-core CPU shared with other jobs (load average {load[0]:.1f} / {load[1]:.1f} / "
        f"{load[2]:.1f} at the end). `warm`: median of 3 renders of one image after compilation; "
        "`setup`: host-side voxelization, rasterization and footprint sheets; error: relative "
        "RMSE vs the Mitsuba reference, noise removed (128² only). "
        "`python benchmarks/bench_splat.py`",
        "",
        "| voxels | pixels | sheets | shadow buffer | setup s | compile s | warm s/image | error % |",
        "|---:|---:|---:|---|---:|---:|---:|---:|",
    ]
    for r in rows:
        lines.append(f"| {r['N']}³ | {r['pixels']}² | {r['sheets']} | {r['buffer']} | "
                     f"{r['setup']:.1f} | {r['compile']:.1f} | {r['warm']:.3f} | {r['err']} |")
    (RESULTS / "bench_splat.md").write_text("\n".join(lines) + "\n")
    print("\n".join(lines))


if __name__ == "__main__":
    main()
