"""The once-scattered sweep's cost (``SweepSolver(once_M=K)``) against one iteration of the
light solve, and the estimate's figure (``difffog.estimate(..., once_M=K)``).

For each (N, K) it builds the scene's sweep model with ``once_M=K`` and times, jitted, after
a first call that compiles: ``SweepSolver._once_scattered`` alone (the sun's first collision
swept on K's directions, sub-stepped) and one Jacobi iteration of the solve without it (M = 3,
the default scheme), best of ``--repeat``; with the machine (copy bandwidth) in the same run.

    python benchmarks/bench_once.py                        # cloud-plane, (24,4) (24,6) (32,6)
    python benchmarks/bench_once.py --settings 64,6 --out benchmarks/results/bench_once.md
    python benchmarks/bench_once.py --quick                # (12,4): a smoke test
"""

from __future__ import annotations

import argparse
import time

import _common as C


def parse_setting(s: str) -> tuple[int, int]:
    n, k = s.split(",")
    return int(n), int(k)


def run(scene_name: str, N: int, K: int, repeat: int) -> dict:
    import equinox as eqx
    import jax
    import jax.numpy as jnp

    import difffog as df
    from difffog.forward.sweep._solver import _jacobi, _zero_state

    scene = df.load_scene(scene_name)
    model = df.forward_model(scene, "sweep", accuracy=None, resolution=N, M=3, once_M=K)
    solver, geom = model.solver, model.geometry
    if geom.once is None:
        raise SystemExit(f"{scene_name}: once_M does not apply (isotropic fog or no sun)")
    p = model.params(jnp.float32)
    plain = eqx.tree_at(lambda g: g.once, geom, None)  # the solve without the once sweep
    pb = jax.jit(solver.problem)(plain, p)
    ones = jnp.ones(geom.shape, jnp.float32)
    once = jax.jit(lambda p: solver._once_scattered(geom, p, pb.sigma_t, ones))
    iteration = jax.jit(lambda s: _jacobi(s, pb))
    out = {"scene": scene_name, "N": N, "K": K, "lattice": "x".join(map(str, geom.shape)),
           "estimate_s": df.estimate(scene, "sweep", resolution=N, once_M=K).once_s}
    for name, f, a in (("once", once, p), ("iteration", iteration, _zero_state(pb))):
        t = time.perf_counter()
        jax.block_until_ready(f(a))
        out[f"{name}_first_s"] = time.perf_counter() - t
        times = []
        for _ in range(repeat):
            t = time.perf_counter()
            jax.block_until_ready(f(a))
            times.append(time.perf_counter() - t)
        out[f"{name}_s"] = min(times)
    return out


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scene", default="cloud-plane")
    ap.add_argument("--settings", nargs="+", type=parse_setting, default=None,
                    help="N,K pairs (default: 24,4 24,6 32,6)")
    ap.add_argument("--repeat", type=int, default=2)
    ap.add_argument("--out", default=None)
    C.add_quick(ap)
    a = C.parse(ap, argv)
    settings = a.settings or ([(12, 4)] if a.quick else [(24, 4), (24, 6), (32, 6)])
    info = C.machine()
    C.print_machine(info)
    rows = []
    for N, K in settings:
        r = run(a.scene, N, K, a.repeat)
        rows.append([r["scene"], N, K, r["lattice"], f"{r['once_s']:.2f}",
                     f"{r['once_first_s']:.1f}", f"{r['iteration_s']:.3f}",
                     f"{r['once_s'] / r['iteration_s']:.0f}", f"{r['estimate_s']:.1f}"])
        print(" | ".join(map(str, rows[-1])), flush=True)
    lines = ["# The once-scattered sweep's cost (`SweepSolver(once_M=K)`)", "",
             "Warm seconds (best of the repeats after a first call that compiles); the "
             "iteration: one Jacobi step of the light solve without the once sweep (M = 3, "
             "the default scheme). `python benchmarks/bench_once.py`.", "",
             *C.machine_lines(info), "",
             *C.md_table(["scene", "N", "K", "lattice", "once sweep s", "first call s",
                          "iteration s", "ratio", "estimate s"], rows, "lrrlrrrrr")]
    print("\n".join(lines))
    if a.out:
        C.write_text(a.out, "\n".join(lines) + "\n")


if __name__ == "__main__":
    main()
