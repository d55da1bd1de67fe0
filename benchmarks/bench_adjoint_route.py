"""A gradient's adjoint light solve by each route: hand-written transposed face sweeps
(``SweepSolver(adjoint="transposed")``) against JAX's transpose of the linearised batched
sweep (``adjoint="linearised"``): a value and gradient of an image loss (both views, float32,
compiled ahead of time, median of 3 warm calls), XLA's temporaries, and how far the two
gradients are apart.  Each case runs in a fresh process.

    python benchmarks/bench_adjoint_route.py [--cases fog-balls:32:3 cloud-tomo:32:3
        cloud-plane:24:3] [--scheme step] [--out benchmarks/results/adjoint_route.md]
"""

from __future__ import annotations

import argparse
import sys

import _common as C


def worker(scene: str, N: int, M: int, adjoint: str, scheme: str) -> dict:
    import jax
    import jax.numpy as jnp
    import numpy as np

    import difffog as df

    m = df.forward_model(df.load_scene(scene), "sweep", accuracy=None, resolution=N, M=M,
                         supersample=1, adjoint=adjoint, scheme=scheme)
    p = m.params()
    target = jax.tree.map(lambda a: 0.9 * a, m(p))

    def value_and_grad(model, q):
        def loss(x):
            imgs = model.images(x)
            return sum(jnp.mean((imgs[k] - target[k]) ** 2) for k in imgs)
        return jax.value_and_grad(loss)(q)

    c, comp = C.compile_timed(value_and_grad, m, p)
    t = C.time_calls(lambda: c(m, p), 3)
    grads = [np.asarray(g).ravel() for g in jax.tree.leaves(t.value[1])]
    return dict(scene=scene, N=N, M=M, adjoint=adjoint,
                route=m.solver.resolved_adjoint(m.solver.problem(m.geometry, p)),
                compile_s=comp, s=t.median, temp_mib=C.xla_mib(c),
                grad=np.concatenate(grads).tolist())


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cases", nargs="+", default=["fog-balls:32:3", "cloud-tomo:32:3",
                                                   "cloud-plane:24:3"])
    ap.add_argument("--scheme", default="step", help="the transport scheme (the transposed "
                    "route has the step scheme)")
    ap.add_argument("--out", default=None)
    ap.add_argument("--worker", nargs=5, default=None, help=argparse.SUPPRESS)
    a = ap.parse_args(argv)
    if a.worker:
        scene, N, M, adjoint, scheme = a.worker
        C.emit_result(worker(scene, int(N), int(M), adjoint, scheme))
        return
    import numpy as np

    info = C.machine()
    rows = []
    for case in a.cases:
        scene, N, M = case.split(":")
        res = {}
        for adjoint in ("linearised", "transposed"):
            res[adjoint] = C.run_worker([sys.executable, __file__, "--worker", scene, N, M,
                                         adjoint, a.scheme], label=f"{case} {adjoint}")
        lin, tr = res["linearised"], res["transposed"]
        if lin is None or tr is None:
            continue
        g1, g2 = np.asarray(lin["grad"]), np.asarray(tr["grad"])
        diff = float(np.max(np.abs(g1 - g2)) / max(np.max(np.abs(g1)), 1e-30))
        rows.append([scene, N, M, a.scheme, f"{lin['s']:.2f}", f"{tr['s']:.2f}",
                     f"{lin['s'] / tr['s']:.2f}×", f"{lin['temp_mib']:.0f} / {tr['temp_mib']:.0f}",
                     f"{lin['compile_s']:.0f} / {tr['compile_s']:.0f}", f"{diff:.1e}"])
        print(rows[-1], flush=True)
    text = ["# The adjoint's route: transposed sweeps against JAX's transpose", "",
            f"`python benchmarks/bench_adjoint_route.py {' '.join(argv or sys.argv[1:])}`"
            " (module docstring)", "", *C.machine_lines(info), "",
            *C.md_table(["scene", "N", "M", "scheme", "linearised s", "transposed s",
                         "speed-up", "XLA temp MiB (lin. / tr.)", "compile s (lin. / tr.)",
                         "gradients apart (max rel.)"], rows)]
    print("\n".join(text))
    if a.out:
        C.write_text(a.out, text)


if __name__ == "__main__":
    main()
