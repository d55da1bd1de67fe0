"""Time and memory of a fit step (``difffog.fit``), and forward- vs reverse-mode Jacobians.

For fog-balls with 3 unknowns (ζ, γ, walls albedo), both cameras at 1/4 size (32×32 + 40×30 =
2224 pixels), M = 3, at each lattice resolution N:

* one LM fit from ζ×0.6, γ×1.6, albedo−0.15 to the model's own images: time of the first
  step (compiles), the median of the later steps, the steps taken;
* alone, warm: the forward images (one light solve + cameras), the forward-mode Jacobian that
  the fit uses (n tangent solves + n camera passes, ``_Problem.model_and_jacobian``), and one
  reverse-mode gradient of a scalar (one adjoint solve) — a reverse-mode Jacobian would need
  one of those per pixel, so ``rev_jacobian_est_s`` = pixels × that time;
* memory: peak resident set of the process and XLA's temporary buffers of the compiled
  Jacobian (``memory_analysis``).

    PYTHONPATH=src python benchmarks/bench_fit.py --sizes 24 32

Writes ``benchmarks/results/bench_fit.md`` and ``bench_fit.json``.  Record the load average:
this machine is shared.
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import statistics
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

import difffog as df
from difffog._fit import _Coord, _Problem, make_forward

RESULTS = Path(__file__).resolve().parents[1] / "benchmarks" / "results"
TRUTH = {"fog.scattering": 2.0, "fog.absorption": 0.5, "shape.walls.albedo": 0.7}


def timed(fn, *a, repeat=3):
    jax.block_until_ready(fn(*a))  # compile
    ts = []
    for _ in range(repeat):
        t = time.perf_counter()
        jax.block_until_ready(fn(*a))
        ts.append(time.perf_counter() - t)
    return min(ts)


def bench(N: int, M: int) -> dict:
    scene = df.load_scene("fog-balls")
    fwd = make_forward(scene, "sweep", cameras=["top", "oblique"], resolution=N, directions=M,
                       downsample=4)
    targets = {k: np.asarray(v) for k, v in fwd(fwd.params()).items()}
    start = {"fog.scattering": 1.2, "fog.absorption": 0.8, "shape.walls.albedo": 0.55}
    load0 = os.getloadavg()[0]
    res = df.fit(scene, targets, start, forward=fwd, downsample=4)
    t_hist = [h["time_s"] for h in res.history]
    steps = np.diff([0.0] + t_hist)
    out = {"N": N, "M": M, "pixels": int(sum(v.size for v in targets.values())), "unknowns": 3,
           "fit_steps": res.iterations, "fit_result": res.result,
           "first_step_s": float(steps[0]),
           "step_s_median": float(statistics.median(steps[1:])) if len(steps) > 1 else None,
           "fit_total_s": res.time_s}
    # the pieces alone, warm
    coords = tuple(_Coord(p, *b) for p, b in zip(
        TRUTH, [(0.0, float("inf")), (0.0, float("inf")), (0.0, 1.0)]))
    pb = _Problem(fwd, coords, ("top", "oblique"), "linear")
    base = fwd.params()
    u = jnp.asarray([c.to_u(v) for c, v in zip(pb.coords, TRUTH.values())], base.scattering.dtype)
    model = jax.jit(pb.model)
    jac = jax.jit(pb.model_and_jacobian)
    t = time.perf_counter()
    compiled = jac.lower(u, base).compile()
    out["jacobian_compile_s"] = time.perf_counter() - t
    mem = compiled.memory_analysis()
    out["jacobian_xla_temp_mib"] = None if mem is None else mem.temp_size_in_bytes / 2**20
    out["forward_s"] = timed(model, u, base)
    out["jacobian_fwd_s"] = timed(jac, u, base)
    tgt = jnp.concatenate([jnp.ravel(jnp.asarray(targets[n])) for n in pb.names])
    grad = jax.jit(jax.grad(lambda x: jnp.sum((pb.model(x, base) - tgt) ** 2)))
    t = time.perf_counter()
    jax.block_until_ready(grad(u))
    out["grad_rev_compile_s"] = time.perf_counter() - t
    out["grad_rev_s"] = timed(grad, u)
    out["rev_jacobian_est_s"] = out["grad_rev_s"] * out["pixels"]
    out["peak_rss_mib"] = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    out["load"] = round(0.5 * (load0 + os.getloadavg()[0]), 1)
    return out


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sizes", nargs="+", type=int, default=[24, 32])
    ap.add_argument("-M", type=int, default=3)
    args = ap.parse_args()
    rows = []
    for N in args.sizes:
        r = bench(N, args.M)
        print(json.dumps(r), flush=True)
        rows.append(r)
    RESULTS.mkdir(parents=True, exist_ok=True)
    (RESULTS / "bench_fit.json").write_text(json.dumps(rows, indent=1))
    lines = ["# Fit step: time and memory", "",
             "`PYTHONPATH=src python benchmarks/bench_fit.py --sizes " +
             " ".join(map(str, args.sizes)) + "`: fog-balls, 3 unknowns, 2224 pixels (both "
             "cameras at 1/4 size), float32, 2-core CPU shared with other jobs (load column).",
             "",
             "| N | M | steps | first step s (compile) | step s (median) | forward s | "
             "Jacobian fwd s | grad rev s | Jacobian rev (est.) s | Jacobian compile s | "
             "XLA temp MiB | peak RSS MiB | load |",
             "|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|"]
    for r in rows:
        lines.append(
            f"| {r['N']} | {r['M']} | {r['fit_steps']} | {r['first_step_s']:.1f} | "
            f"{r['step_s_median']:.2f} | {r['forward_s']:.2f} | {r['jacobian_fwd_s']:.2f} | "
            f"{r['grad_rev_s']:.2f} | {r['rev_jacobian_est_s']:.0f} | "
            f"{r['jacobian_compile_s']:.1f} | {r['jacobian_xla_temp_mib']:.0f} | "
            f"{r['peak_rss_mib']:.0f} | {r['load']} |")
    lines += ["", "A step evaluates the images and the n-column forward-mode Jacobian at one "
              "point; a reverse-mode Jacobian needs one adjoint per pixel (estimated column), "
              "which is why the fit uses forward mode (the camera's custom reverse pass is "
              "transposed to get its tangent)."]
    (RESULTS / "bench_fit.md").write_text("\n".join(lines) + "\n")


if __name__ == "__main__":
    main()
