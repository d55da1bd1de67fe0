"""Gradient memory and time vs the number of Jacobi iterations (implicit adjoint).

    python benchmarks/bench_adjoint_memory.py                 # N = 32, M = 3, iterations 10/40/160
    python benchmarks/bench_adjoint_memory.py --N 24 --M 2 --iterations 10 40
    python benchmarks/bench_adjoint_memory.py --quick         # N = 12, M = 2, iterations 5/20

Each configuration runs in a fresh process (``--worker``) and reports its peak resident
memory, so the figures are comparable.  With the implicit adjoint the gradient's memory should
not depend on the iteration count (unrolling would grow linearly).  The model is the public
sweep model (``difffog.forward_model`` with tol = 0, so exactly that many applications of the
one-bounce operator run: Jacobi iterations with ``--method jacobi``, GMRES steps with the
solver's default ``auto``); the report starts with the machine (JAX backend and devices,
copy bandwidth) measured in the same run.
"""

from __future__ import annotations

import argparse
import json
import resource
import sys

import _common as C


def worker(N: int, M: int, K: int, mode: str, scene: str, method: str) -> dict:
    import equinox as eqx
    import jax
    import jax.numpy as jnp

    import difffog as df

    model = df.forward_model(df.load_scene(scene), "sweep", accuracy=None, resolution=N, M=M,
                             method=method, max_iterations=K, tol=0.0)
    p = model.params()
    target = jax.tree.map(lambda a: 0.9 * a, model(p))

    def loss(m, q):
        imgs = m.images(q)
        return sum(jnp.mean((imgs[k] - target[k]) ** 2) for k in imgs)

    fn = eqx.filter_jit(lambda m, q: jax.grad(lambda x: loss(m, x))(q) if mode == "grad"
                        else loss(m, q))
    t = C.time_calls(lambda: fn(model, p), 1)  # the first call compiles
    rss = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    return {"N": N, "M": M, "iterations": K, "method": method, "mode": mode,
            "compile_plus_run_s": t.first,
            "run_s": t.times[0], "peak_rss_mb": rss}


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--N", type=int, default=None, help="default 32; with --quick 12")
    ap.add_argument("--M", type=int, default=None, help="default 3; with --quick 2")
    C.add_sizes(ap, [10, 40, 160], [5, 20], flag="--iterations", what="Jacobi iterations")
    ap.add_argument("--scene", default="fog-balls")
    ap.add_argument("--method", default="auto", choices=["auto", "jacobi", "gmres"])
    ap.add_argument("--out", default=None, help="write the markdown report here")
    ap.add_argument("--worker", nargs=4, default=None, help=argparse.SUPPRESS)
    a = C.parse(ap, argv)
    if a.worker:
        N, M, K, mode = a.worker
        C.emit_result(worker(int(N), int(M), int(K), mode, a.scene, a.method))
        return 0
    N = a.N or (12 if a.quick else 32)
    M = a.M or (2 if a.quick else 3)
    info = C.machine()
    rows = []
    for K in a.iterations:
        for mode in ("forward", "grad"):
            row = C.run_worker([sys.executable, __file__, "--scene", a.scene, "--method",
                                a.method, "--worker",
                                str(N), str(M), str(K), mode], label=f"K={K} {mode}")
            if row is None:
                return 1
            rows.append(row)
            print(json.dumps(row), flush=True)
    lines = ["# Gradient memory vs iterations (implicit adjoint)", "",
             f"`python benchmarks/bench_adjoint_memory.py --N {N} --M {M} --iterations "
             f"{' '.join(map(str, a.iterations))} --method {a.method}`: {a.scene}, float32, "
             "every case in a fresh process", "", *C.machine_lines(info), ""]
    lines += C.md_table(["N", "M", "iterations", "mode", "run (s)", "compile+run (s)",
                         "peak RSS (MB)"],
                        [[r["N"], r["M"], r["iterations"], r["mode"], f"{r['run_s']:.2f}",
                          f"{r['compile_plus_run_s']:.1f}", f"{r['peak_rss_mb']:.0f}"]
                         for r in rows], "l" * 7)
    print("\n".join(lines))
    if a.out:
        C.write_text(a.out, lines)
    return 0


if __name__ == "__main__":
    sys.exit(main())
