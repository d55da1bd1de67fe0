"""Time and memory of a fit step (``difffog.fit``), and forward- vs reverse-mode Jacobians.

For fog-balls with 3 unknowns (ζ, γ, walls albedo), both cameras at 1/4 size (32×32 + 40×30 =
2224 pixels), M = 3, at each lattice resolution N:

* one LM fit from ζ×0.6, γ×1.6, albedo−0.15 to the model's own images: time of the first
  step (compiles), the median of the later steps, the steps taken;
* alone, warm: the forward images (one light solve + cameras), the forward-mode Jacobian that
  the fit uses (n tangent solves + n camera passes, ``FitProblem.model_and_jacobian``), and one
  reverse-mode gradient of a scalar (one adjoint solve) — a reverse-mode Jacobian would need
  one of those per pixel, so ``rev_jacobian_est_s`` = pixels × that time;
* memory: peak resident set of the process and XLA's temporary buffers of the compiled
  Jacobian (``memory_analysis``).

The model is built once with the public API (``_common.fit_model``: ``difffog.forward_model``
at the registry's fit defaults) and handed to ``difffog.fit``; the pieces of a step are timed
alone through the fit's internals on purpose (``difffog.fit._residuals.FitProblem``,
``difffog.fit._unknowns.Coordinate``).  The report starts with the machine (JAX backend and
devices, copy bandwidth) measured in the same run.

    PYTHONPATH=src python benchmarks/bench_fit.py --sizes 24 32
    PYTHONPATH=src python benchmarks/bench_fit.py --quick --out /tmp/fit   # N = 12, 3 steps

Writes ``bench_fit.md`` and ``bench_fit.json`` ({"machine": ..., "rows": [...]}) to ``--out``
(default ``benchmarks/results``).  Record the load average: this machine is shared.
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import statistics
from pathlib import Path

import numpy as np

import _common as C

TRUTH = {"fog.scattering": 2.0, "fog.absorption": 0.5, "shape.walls.albedo": 0.7}
CAMERAS = ("oblique", "top")  # sorted, as difffog.fit orders the views


def bench(N: int, M: int, max_steps: int) -> dict:
    import jax
    import jax.numpy as jnp

    import difffog as df
    from difffog.fit._residuals import FitProblem  # the internals being measured
    from difffog.fit._unknowns import Coordinate

    scene = df.load_scene("fog-balls")
    model = C.fit_model(scene, CAMERAS, N, M, downsample=4)
    targets = {k: np.asarray(v) for k, v in model(model.params()).items()}
    start = {"fog.scattering": 1.2, "fog.absorption": 0.8, "shape.walls.albedo": 0.55}
    load0 = os.getloadavg()[0]
    res = df.fit(scene, targets, start, forward=model, downsample=4, max_steps=max_steps)
    steps = np.diff([0.0] + [h["time_s"] for h in res.history])
    out = {"N": N, "M": M, "pixels": int(sum(v.size for v in targets.values())), "unknowns": 3,
           "fit_steps": res.iterations, "fit_result": res.result,
           "first_step_s": float(steps[0]),
           "step_s_median": float(statistics.median(steps[1:])) if len(steps) > 1 else None,
           "fit_total_s": res.time_s}
    # the pieces alone, warm
    coords = tuple(Coordinate(p, *b) for p, b in zip(
        TRUTH, [(0.0, float("inf")), (0.0, float("inf")), (0.0, 1.0)]))
    pb = FitProblem(model.scene, coords, CAMERAS, "linear")
    base = model.params()
    u = jnp.asarray([c.to_u(v) for c, v in zip(pb.coords, TRUTH.values())], base.scattering.dtype)
    images = lambda m, u, b: pb.model(m, u, b)[0]  # noqa: E731
    fwd, _ = C.compile_timed(images, model, u, base)
    jac, out["jacobian_compile_s"] = C.compile_timed(
        lambda m, u, b: pb.model_and_jacobian(m, u, b)[:2], model, u, base)
    out["jacobian_xla_temp_mib"] = C.xla_mib(jac)
    out["forward_s"] = C.time_calls(lambda: fwd(model, u, base)).best
    out["jacobian_fwd_s"] = C.time_calls(lambda: jac(model, u, base)).best
    tgt = jnp.concatenate([jnp.ravel(jnp.asarray(targets[n])) for n in pb.names])
    grad, out["grad_rev_compile_s"] = C.compile_timed(
        lambda m, x: jax.grad(lambda y: jnp.sum((images(m, y, base) - tgt) ** 2))(x), model, u)
    out["grad_rev_s"] = C.time_calls(lambda: grad(model, u)).best
    out["rev_jacobian_est_s"] = out["grad_rev_s"] * out["pixels"]
    out["peak_rss_mib"] = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    out["load"] = round(0.5 * (load0 + os.getloadavg()[0]), 1)
    return out


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    C.add_sizes(ap, [24, 32], [12])
    ap.add_argument("-M", type=int, default=3)
    ap.add_argument("--max-steps", type=int, default=None, help="of the fit (default 50; "
                    "with --quick 3)")
    ap.add_argument("--out", type=Path, default=C.RESULTS, help="folder of the reports")
    args = C.parse(ap, argv)
    max_steps = args.max_steps or (3 if args.quick else 50)
    info = C.machine()
    C.print_machine(info)
    rows = []
    for N in args.sizes:
        r = bench(N, args.M, max_steps)
        print(json.dumps(r), flush=True)
        rows.append(r)
    C.write_text(args.out / "bench_fit.json", json.dumps({"machine": info, "rows": rows},
                                                         indent=1))
    opt = lambda x, f: "–" if x is None else format(x, f)  # noqa: E731
    lines = ["# Fit step: time and memory", "",
             "`PYTHONPATH=src python benchmarks/bench_fit.py --sizes " +
             " ".join(map(str, args.sizes)) + "`: fog-balls, 3 unknowns, 2224 pixels (both "
             "cameras at 1/4 size), float32, shared CPU (load column).", "",
             *C.machine_lines(info), ""]
    lines += C.md_table(
        ["N", "M", "steps", "first step s (compile)", "step s (median)", "forward s",
         "Jacobian fwd s", "grad rev s", "Jacobian rev (est.) s", "Jacobian compile s",
         "XLA temp MiB", "peak RSS MiB", "load"],
        [[r["N"], r["M"], r["fit_steps"], f"{r['first_step_s']:.1f}",
          opt(r["step_s_median"], ".2f"), f"{r['forward_s']:.2f}",
          f"{r['jacobian_fwd_s']:.2f}", f"{r['grad_rev_s']:.2f}",
          f"{r['rev_jacobian_est_s']:.0f}", f"{r['jacobian_compile_s']:.1f}",
          f"{r['jacobian_xla_temp_mib']:.0f}", f"{r['peak_rss_mib']:.0f}", r["load"]]
         for r in rows], "r" * 13)
    lines += ["", "A step evaluates the images and the n-column forward-mode Jacobian at one "
              "point; a reverse-mode Jacobian needs one adjoint per pixel (estimated column), "
              "which is why the fit uses forward mode (the camera's custom reverse pass is "
              "transposed to get its tangent)."]
    C.write_text(args.out / "bench_fit.md", lines)


if __name__ == "__main__":
    main()
