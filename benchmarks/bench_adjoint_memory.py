"""Gradient memory and time vs the number of Jacobi iterations (implicit adjoint).

    python benchmarks/bench_adjoint_memory.py            # N = 32, M = 3, iterations 10/40/160

Each configuration runs in a fresh process and reports its peak resident memory, so the
figures are comparable.  With the implicit adjoint the gradient's memory should not depend on
the iteration count (unrolling would grow linearly).
"""

import json
import subprocess
import sys

CHILD = r"""
import json, resource, sys, time
import jax, jax.numpy as jnp
from difffog import Renderer, SweepSolver, load_scene
N, M, K, mode = int(sys.argv[1]), int(sys.argv[2]), int(sys.argv[3]), sys.argv[4]
scene = load_scene("fog-balls")
r = Renderer(scene, resolution=N, solver=SweepSolver(M=M, max_iterations=K, tol=0.0))
p = r.params()
target = jax.tree.map(lambda a: 0.9 * a, r(p))
def loss(q):
    imgs = r(q)
    return sum(jnp.mean((imgs[k] - target[k]) ** 2) for k in imgs)
fn = jax.jit(jax.grad(loss) if mode == "grad" else loss)
t = time.perf_counter(); jax.block_until_ready(fn(p)); first = time.perf_counter() - t
t = time.perf_counter(); jax.block_until_ready(fn(p)); run = time.perf_counter() - t
rss = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
print(json.dumps({"N": N, "M": M, "iterations": K, "mode": mode, "compile_plus_run_s": first,
                  "run_s": run, "peak_rss_mb": rss}))
"""


def main():
    N, M = (int(a) for a in (sys.argv[1:3] if len(sys.argv) > 2 else (32, 3)))
    rows = []
    for K in (10, 40, 160):
        for mode in ("forward", "grad"):
            out = subprocess.run([sys.executable, "-c", CHILD, str(N), str(M), str(K), mode],
                                 capture_output=True, text=True, check=True)
            rows.append(json.loads(out.stdout.strip().splitlines()[-1]))
    print(f"| N | M | iterations | mode | run (s) | compile+run (s) | peak RSS (MB) |")
    print("|---|---|---|---|---|---|---|")
    for r in rows:
        print(f"| {r['N']} | {r['M']} | {r['iterations']} | {r['mode']} | {r['run_s']:.2f} | "
              f"{r['compile_plus_run_s']:.1f} | {r['peak_rss_mb']:.0f} |")


if __name__ == "__main__":
    main()
