"""Validation ladder, thick fog: issue 14's cube against independent truth.

The unit cube of nearly conservative fog (γ = 0.001) with a ball inside, under a sun at 30° and
a sky, seen from straight above (``difffog.study._semi_infinite.thick_cube``): as ζ grows its
image tends to what a semi-infinite conservative isotropic medium returns (Chandrasekhar's
H-functions plus the sky, 0.773), but at ζ = 100 it is 6% under it.  Renders it with the sweep
at each N, scheme, first collision and ζ (M = 2, float32, tol 1e-4, one ray per pixel) and
reports the image mean, its error against the cube's own image by an independent float64
Monte Carlo (``THICK_CUBE_REFERENCE``, ``benchmarks/thick_cube_mc.py``) and against the
semi-infinite value, the GMRES steps and the wall time (compile included).  The step depth
σ_t·h·M of each row says how many mean free paths one lattice step spans.

Writes ``thick_cube.csv`` and ``thick_cube.md`` (with the machine) to ``--out`` (default
``benchmarks/results``).

    python benchmarks/thick_cube.py                          # N 16 32, auto step linear, ζ 100 1000 10000
    python benchmarks/thick_cube.py --n 16 24 32 48 64 --schemes auto --first-collisions beam deposit
    python benchmarks/thick_cube.py --n 32 --schemes step --zetas 1000
    python benchmarks/thick_cube.py --quick --out /tmp/cube  # N 8, auto, ζ 100
"""

from __future__ import annotations

import argparse
import csv
import math
import time
import warnings
from pathlib import Path

import _common as C
import difffog as df
from difffog.study._semi_infinite import THICK_CUBE_REFERENCE, semi_infinite_value, thick_cube


def run(N: int, scheme: str, zeta: float, first_collision: str = "beam") -> dict:
    scene = thick_cube(zeta)
    m = df.forward_model(scene, "sweep", accuracy=None, resolution=N, M=2,
                         tol=1e-4, max_iterations=2000, supersample=1, scheme=scheme,
                         first_collision=first_collision)
    t = time.perf_counter()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", df.ThickStepWarning)  # every row is thick on purpose
        out = df.render(m, throw=False)
    wall = time.perf_counter() - t
    v = float(out.images["top"].mean())
    depth = m.lattice.max_segment_optical_depth(scene.fog.scattering, scene.fog.absorption)
    ref = THICK_CUBE_REFERENCE.get(zeta, (math.nan, math.nan))[0]
    return {"N": N, "scheme": scheme, "ran": out.settings["solver_options"]["scheme"],
            "first_collision": first_collision,
            "zeta": zeta, "step_depth": round(depth, 1), "mean": round(v, 4),
            "cube_error_pct": round(100 * (v / ref - 1), 1),
            "error_pct": round(100 * (v / semi_infinite_value() - 1), 1),
            "result": out.result.name, "iterations": int(out.light.iterations),
            "wall_s": round(wall, 1)}


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    C.add_sizes(ap, (16, 32), (8,), flag="--n")
    ap.add_argument("--schemes", nargs="+", default=["auto", "step", "linear"],
                    choices=["auto", "step", "linear", "substep"])
    ap.add_argument("--zetas", nargs="+", type=float, default=None)
    ap.add_argument("--first-collisions", nargs="+", default=["beam"], choices=["beam", "deposit"])
    ap.add_argument("--out", default=str(Path(__file__).parent / "results"))
    a = C.parse(ap, argv)
    zetas = a.zetas or ([100.0] if a.quick else [100.0, 1000.0, 10000.0])
    schemes = ["auto"] if a.quick else a.schemes
    info = C.machine()
    C.print_machine(info)
    rows = []
    for N in a.n:
        for scheme in schemes:
            for fc in a.first_collisions:
                for z in zetas:
                    rows.append(run(N, scheme, z, fc))
                    print(rows[-1], flush=True)
    out = Path(a.out)
    out.mkdir(parents=True, exist_ok=True)
    with open(out / "thick_cube.csv", "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=list(rows[0]))
        w.writeheader()
        w.writerows(rows)
    head = ["N", "scheme (ran)", "first collision", "ζ", "step depth", "image mean",
            "error % (cube)", "error % (half-space)", "result", "GMRES steps", "wall s"]
    table = [[r["N"], f"{r['scheme']} ({r['ran']})", r["first_collision"], f"{r['zeta']:g}",
              r["step_depth"], r["mean"], f"{r['cube_error_pct']:+.1f}",
              f"{r['error_pct']:+.1f}", r["result"], r["iterations"], r["wall_s"]]
             for r in rows]
    refs = ", ".join(f"ζ = {z:g}: {v:.4f} ± {e:.4f}" for z, (v, e) in
                     sorted(THICK_CUBE_REFERENCE.items()))
    lines = ["# Issue 14's thick cube against independent truth",
             "", f"The cube's own image mean (float64 Monte Carlo, `benchmarks/thick_cube_mc.py`): "
             f"{refs}. Semi-infinite value {semi_infinite_value():.4f}. "
             "(`benchmarks/thick_cube.py`; M = 2, float32, tol 1e-4.)", ""]
    lines += C.md_table(head, table) + ["", "Machine:", ""] + C.machine_lines(info)
    C.write_text(out / "thick_cube.md", lines)
    print(f"wrote {out / 'thick_cube.md'}")


if __name__ == "__main__":
    main()
