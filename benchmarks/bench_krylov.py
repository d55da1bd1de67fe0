"""Jacobi vs GMRES on the same light problem (I − K)x = b, near albedo 1.

    python benchmarks/bench_krylov.py                       # N = 32, M = 3, float32
    python benchmarks/bench_krylov.py --N 48 --albedos 0.9 0.99
    python benchmarks/bench_krylov.py --quick --out /tmp/krylov   # N = 16, M = 2, albedo 0.9

For the furnace (closed box, emission 1, wall albedo a, a purely scattering fog: exact radiance
1/(1 − a)) and for fog-balls made thick and bright (ζ + γ = 8 per unit, fog albedo a, every
surface albedo a; the roof is open, so light leaks), solve to tol = 1e-4 with each method and
record the applications of K (one application = one Jacobi iteration = six sweeps), the warm
solve time (compilation timed apart), the solver's own error estimate and the true error: max
relative difference of Λ and B from a float64 GMRES solve to 1e-9 (the furnace: from the exact
1/(1 − a)).  Writes krylov.md (with the machine: JAX backend and devices, copy bandwidth,
measured in the same run) and krylov.csv to ``--out`` (default benchmarks/results).  Public API
only (``difffog.SweepSolver`` on a ``difffog.voxelize`` lattice).
"""

from __future__ import annotations

import argparse
import csv
import os
import time
from pathlib import Path

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

import _common as C
from difffog import Params, SweepSolver, load_scene, voxelize
from difffog.geometry._lattice import VACUUM_MARGIN


def scene_for(name: str, a: float):
    if name == "furnace":
        return load_scene("furnace", [f"shape.walls.albedo={a}"])
    over = [f"fog.scattering={8 * a}", f"fog.absorption={8 * (1 - a)}"]
    over += [f"shape.{sh.name}.albedo={a}" for sh in load_scene("fog-balls").shapes]
    return load_scene("fog-balls", over)


def fields(light, geom):
    surf = np.asarray(geom.surf)
    free = ~np.asarray(geom.solid)
    return np.asarray(light.fluence, np.float64)[free], np.asarray(light.radiosity, np.float64)[surf]


def rel_err(x, ref):
    errs = [np.max(np.abs(a - b)) / max(np.max(np.abs(b)), 1e-30) for a, b in zip(x, ref) if b.size]
    return float(max(errs))


def run(name, a, N, M, cap, tol):
    scene = scene_for(name, a)
    # the furnace's exact value holds inside the box: no vacuum margin around it
    # the renderer's vacuum margin (two nodes since stop 82, M + 1 before: results up to stop 82
    # were measured with M + 1)
    lat = voxelize(scene, N, M, margin=0 if name == "furnace" else VACUUM_MARGIN)
    rows = []
    p32 = Params.from_scene(scene, jnp.float32)
    if name == "furnace":
        exact = 1.0 / (1.0 - float(np.float32(a)))
        ref = None
    else:
        jax.config.update("jax_enable_x64", True)
        s = SweepSolver(M=M, method="gmres", tol=1e-9, max_iterations=2000)
        g = s.prepare(scene, lat)
        light = eqx.filter_jit(s.solve)(g, Params.from_scene(scene, jnp.float64))
        ref = fields(light, g)
        jax.config.update("jax_enable_x64", False)
    for method in ("jacobi", "gmres"):
        s = SweepSolver(M=M, method=method, tol=tol, max_iterations=cap)
        g = s.prepare(scene, lat)
        compiled, tc = C.compile_timed(s.solve, g, p32)
        t = time.perf_counter()
        light = jax.block_until_ready(compiled(g, p32))
        ts = time.perf_counter() - t
        lam, B = fields(light, g)
        if ref is None:
            err = rel_err((lam / (4 * np.pi), B), (np.full_like(lam, exact), np.full_like(B, exact)))
        else:
            err = rel_err((lam, B), ref)
        k = int(light.iterations)
        rows.append(dict(scene=name, albedo=a, N=N, M=M, method=method, applications=k,
                         converged=bool(float(light.error_estimate) <= tol),
                         solve_s=round(ts, 3), s_per_application=round(ts / k, 4),
                         compile_s=round(tc, 1), error_estimate=float(light.error_estimate),
                         true_error=err))
        print(rows[-1], flush=True)
    return rows


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--N", type=int, default=None, help="default 32; with --quick 16")
    ap.add_argument("--M", type=int, default=None, help="default 3; with --quick 2")
    ap.add_argument("--albedos", type=float, nargs="+", default=None,
                    help="default 0.5 0.9 0.99 0.999; with --quick 0.9")
    ap.add_argument("--scenes", nargs="+", default=["furnace", "fog-balls"])
    ap.add_argument("--cap", type=int, default=3000, help="max applications of K")
    ap.add_argument("--tol", type=float, default=1e-4)
    ap.add_argument("--out", type=Path, default=C.RESULTS, help="folder of the reports")
    C.add_quick(ap)
    args = C.parse(ap, argv)
    args.N = args.N or (16 if args.quick else 32)
    args.M = args.M or (2 if args.quick else 3)
    args.albedos = args.albedos or ([0.9] if args.quick else [0.5, 0.9, 0.99, 0.999])
    info = C.machine()
    C.print_machine(info)
    load = os.getloadavg()[0]
    rows = []
    for name in args.scenes:
        for a in args.albedos:
            rows.extend(run(name, a, args.N, args.M, args.cap, args.tol))
    args.out.mkdir(parents=True, exist_ok=True)
    with open(args.out / "krylov.csv", "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=list(rows[0]))
        w.writeheader()
        w.writerows(rows)
    lines = [
        "# Jacobi vs GMRES (benchmarks/bench_krylov.py)",
        "",
        f"N = {args.N}, M = {args.M}, float32, tol = {args.tol:g}, cap {args.cap} applications; "
        f"load average at start {load:.1f} on a CPU shared with other jobs. "
        "Applications = applications of K (six sweeps each, Jacobi's iterations); true error = "
        "max relative error of Λ and B against the exact furnace value or a float64 GMRES solve "
        "to 1e-9.",
        "",
        *C.machine_lines(info),
        "",
    ]
    table = []
    for r in rows:
        jac = next(x for x in rows if x["scene"] == r["scene"] and x["albedo"] == r["albedo"]
                   and x["method"] == "jacobi")
        cap = "" if r["converged"] else " (cap)"
        table.append([r["scene"], f"{r['albedo']:g}", r["method"], f"{r['applications']}{cap}",
                      f"{r['solve_s']:.2f}", f"{r['s_per_application']:.3f}",
                      f"{r['error_estimate']:.1e}", f"{r['true_error']:.1e}",
                      f"{jac['solve_s'] / r['solve_s']:.1f}×"])
    lines += C.md_table(["scene", "albedo", "method", "applications", "solve (s)",
                         "s / application", "error estimate", "true error", "speed-up"],
                        table, "lrlrrrrrr")
    C.write_text(args.out / "krylov.md", lines)
    print("\n".join(lines))


if __name__ == "__main__":
    main()
