"""GMRES with and without the diffusion preconditioner (``SweepSolver(precondition=...)``) over
albedo × optical thickness, in issue 14's thick cube.

    python benchmarks/bench_dsa.py                    # N = 40, M = 2, float32
    python benchmarks/bench_dsa.py --N 64 --M 3
    python benchmarks/bench_dsa.py --quick --out /tmp/dsa   # N = 16, two points
    python benchmarks/bench_dsa.py --adjoint          # a gradient's adjoint solve instead

The scene: the unit cube of fog (open sides), a sphere of albedo 0.6 inside, sun at 30°, sky
0.2; σ_t = τ per unit length (τ = the cube's optical thickness), single-scattering albedo a.
Each method solves to tol = 1e-4; recorded: GMRES steps (applications of the one-bounce
operator K, six sweeps each), the warm solve time (best of 2, compilation apart), the solver's
error estimate and the difference of the two methods' fluence (max relative).  Writes dsa.md
(with the machine: backend, copy bandwidth measured in the same run) and dsa.csv to ``--out``
(default benchmarks/results).

``--adjoint``: the same for a gradient (d mean Λ / dζ through the implicit adjoint,
``adjoint_rtol`` = tol): the adjoint GMRES's products (counted at ``_implicit.gmres``), the warm
value-and-gradient time and the gradients' difference; writes dsa_adjoint.md / .csv.
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


def run_adjoint(tau, a, N, M, cap, tol):
    """One gradient per preconditioner; the adjoint's products counted where it runs GMRES."""
    from difffog.forward.sweep import _implicit

    scene = cube(tau, a)
    lat = voxelize(scene, N, M)
    p = Params.from_scene(scene, jnp.float32)
    counts = []
    orig = _implicit.gmres

    def counted(*args, **kw):
        out = orig(*args, **kw)
        jax.debug.callback(lambda k: counts.append(int(k)), out[2])
        return out

    rows, ref = [], None
    _implicit.gmres = counted
    try:
        for pre in ("none", "diffusion"):
            s = SweepSolver(M=M, tol=tol, max_iterations=cap, precondition=pre,
                            adjoint_rtol=tol)
            g = s.prepare(scene, lat)

            def f(zeta, s=s, g=g):
                light = s.solve(g, eqx.tree_at(lambda q: q.scattering, p, zeta))
                return jnp.mean(light.fluence), light.iterations

            fn = jax.jit(jax.value_and_grad(f, has_aux=True))
            jax.block_until_ready(fn(p.scattering))
            ts = []
            for _ in range(2):
                counts.clear()
                t0 = time.perf_counter()
                (_, its), grad = jax.block_until_ready(fn(p.scattering))
                ts.append(time.perf_counter() - t0)
            grad = float(grad)
            ref = grad if ref is None else ref
            rows.append(dict(tau=tau, albedo=a, N=N, M=M, precondition=pre,
                             forward_steps=int(its), adjoint_steps=counts[-1],
                             grad_s=round(min(ts), 3), gradient=grad,
                             diff_vs_none=abs(grad - ref) / max(abs(ref), 1e-30)))
            print(rows[-1], flush=True)
    finally:
        _implicit.gmres = orig
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
    ap.add_argument("--adjoint", action="store_true",
                    help="time a gradient's adjoint solve instead of the light solve")
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
            rows.extend((run_adjoint if args.adjoint else run)(tau, a, args.N, args.M,
                                                               args.cap, args.tol))
    args.out.mkdir(parents=True, exist_ok=True)
    if args.adjoint:
        return report_adjoint(rows, args, info, load)
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


def report_adjoint(rows, args, info, load):
    with open(args.out / "dsa_adjoint.csv", "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=list(rows[0]))
        w.writeheader()
        w.writerows(rows)
    table = [[f"{n['tau']:g}", f"{n['albedo']:g}", str(n["forward_steps"]),
              str(n["adjoint_steps"]), str(d["adjoint_steps"]), f"{n['grad_s']:.2f}",
              f"{d['grad_s']:.2f}", f"{n['grad_s'] / d['grad_s']:.1f}×", f"{d['diff_vs_none']:.1e}"]
             for n, d in zip(rows[::2], rows[1::2])]
    lines = [
        "# A gradient's adjoint solve with and without the diffusion preconditioner "
        "(benchmarks/bench_dsa.py --adjoint)",
        "",
        f"Issue 14's cube, σ_t = τ, N = {args.N}, M = {args.M}, float32, tol = adjoint_rtol = "
        f"{args.tol:g}; load average at start {load}. The gradient: d mean(Λ) / dζ. Steps = "
        "applications of K; forward steps without the preconditioner; time = warm value and "
        "gradient (forward + adjoint), best of 2; difference = relative difference of the two "
        "gradients.",
        "",
        *C.machine_lines(info),
        "",
        *C.md_table(["τ", "albedo", "forward steps", "adjoint steps (GMRES)",
                     "adjoint steps (+ diffusion)", "s (GMRES)", "s (+ diffusion)", "speed-up",
                     "difference"], table, "rrrrrrrrr"),
    ]
    C.write_text(args.out / "dsa_adjoint.md", lines)
    print("\n".join(lines))


if __name__ == "__main__":
    main()
