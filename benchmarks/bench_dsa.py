"""GMRES with and without the diffusion preconditioner (``SweepSolver(precondition=...)``) over
albedo × optical thickness, in issue 14's thick cube.

    python benchmarks/bench_dsa.py                    # N = 40, M = 2, float32
    python benchmarks/bench_dsa.py --N 64 --M 3
    python benchmarks/bench_dsa.py --quick --out /tmp/dsa   # N = 16, two points

The scene: the unit cube of fog (open sides), a sphere of albedo 0.6 inside, sun at 30°, sky
0.2; σ_t = τ per unit length (τ = the cube's optical thickness), single-scattering albedo a.
Each method solves to tol = 1e-4; recorded: GMRES steps (applications of the one-bounce
operator K, six sweeps each), the warm solve time (best of 2, compilation apart), the solver's
error estimate and the difference of the two methods' fluence (max relative).  Writes dsa.md
(with the machine: backend, copy bandwidth measured in the same run) and dsa.csv to ``--out``
(default benchmarks/results).
"""

from __future__ import annotations

import argparse
import csv
import time
from pathlib import Path

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

import _common as C
import difffog as df
from difffog import Params, SweepSolver, voxelize


def cube(tau: float, a: float) -> df.Scene:
    return df.Scene(
        title="thick cube", domain=df.Domain(min=(0, 0, 0), max=(1, 1, 1)),
        fog=df.Fog(scattering=a * tau, absorption=(1 - a) * tau),
        sun=df.Sun(irradiance=2.0, zenith_deg=30.0), sky=df.Sky(radiance=0.2),
        shapes=(df.Sphere(name="ball", center=(0.5, 0.5, 0.5), radius=0.2, albedo=0.6),))


def run(tau, a, N, M, cap, tol):
    scene = cube(tau, a)
    lat = voxelize(scene, N, M)
    p = Params.from_scene(scene, jnp.float32)
    rows, ref = [], None
    for pre in ("none", "diffusion"):
        s = SweepSolver(M=M, tol=tol, max_iterations=cap, precondition=pre)
        g = s.prepare(scene, lat)
        fn = eqx.filter_jit(s.solve)
        t0 = time.perf_counter()
        light = jax.block_until_ready(fn(g, p))
        first = time.perf_counter() - t0
        ts = []
        for _ in range(2):
            t0 = time.perf_counter()
            light = jax.block_until_ready(fn(g, p))
            ts.append(time.perf_counter() - t0)
        lam = np.asarray(light.fluence, np.float64)
        ref = lam if ref is None else ref
        diff = float(np.max(np.abs(lam - ref)) / max(np.max(np.abs(ref)), 1e-30))
        rows.append(dict(tau=tau, albedo=a, N=N, M=M, precondition=pre,
                         steps=int(light.iterations), result=df.RESULTS(int(light.result)).name,
                         solve_s=round(min(ts), 3), first_call_s=round(first, 2),
                         error_estimate=float(light.error_estimate), diff_vs_none=diff,
                         auto=SweepSolver(M=M).resolved_precondition(g) if pre == "none" else ""))
        print(rows[-1], flush=True)
    return rows


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--N", type=int, default=None, help="default 40; with --quick 16")
    ap.add_argument("--M", type=int, default=2)
    ap.add_argument("--taus", type=float, nargs="+", default=None, help="default 1 10 100")
    ap.add_argument("--albedos", type=float, nargs="+", default=None,
                    help="default 0.9 0.99 0.999 0.9999")
    ap.add_argument("--cap", type=int, default=2000, help="max GMRES steps")
    ap.add_argument("--tol", type=float, default=1e-4)
    ap.add_argument("--out", type=Path, default=C.RESULTS, help="folder of the reports")
    C.add_quick(ap)
    args = C.parse(ap, argv)
    args.N = args.N or (16 if args.quick else 40)
    args.taus = args.taus or ([100.0] if args.quick else [1.0, 10.0, 100.0])
    args.albedos = args.albedos or ([0.9, 0.9999] if args.quick else [0.9, 0.99, 0.999, 0.9999])
    info = C.machine()
    C.print_machine(info)
    load = C.loadavg()
    rows = []
    for tau in args.taus:
        for a in args.albedos:
            rows.extend(run(tau, a, args.N, args.M, args.cap, args.tol))
    args.out.mkdir(parents=True, exist_ok=True)
    with open(args.out / "dsa.csv", "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=list(rows[0]))
        w.writeheader()
        w.writerows(rows)
    table = []
    for none, dsa in zip(rows[::2], rows[1::2]):
        table.append([f"{none['tau']:g}", f"{none['albedo']:g}", str(none["steps"]),
                      str(dsa["steps"]), f"{none['solve_s']:.2f}", f"{dsa['solve_s']:.2f}",
                      f"{none['solve_s'] / dsa['solve_s']:.1f}×", f"{dsa['diff_vs_none']:.1e}",
                      none["auto"]])
    lines = [
        "# GMRES with and without the diffusion preconditioner (benchmarks/bench_dsa.py)",
        "",
        f"Issue 14's cube (open unit cube of fog, a sphere of albedo 0.6, sun and sky), σ_t = τ, "
        f"N = {args.N}, M = {args.M}, float32, tol = {args.tol:g}; load average at start {load}. "
        "Steps = applications of K (six sweeps each); time = warm solve, best of 2; "
        "difference = max relative difference of the two fluences; auto = what "
        "precondition=\"auto\" chooses.",
        "",
        *C.machine_lines(info),
        "",
        *C.md_table(["τ", "albedo", "steps (GMRES)", "steps (+ diffusion)", "s (GMRES)",
                     "s (+ diffusion)", "speed-up", "difference", "auto"], table, "rrrrrrrrl"),
    ]
    C.write_text(args.out / "dsa.md", lines)
    print("\n".join(lines))


if __name__ == "__main__":
    main()
