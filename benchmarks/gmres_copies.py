"""Whether XLA copies GMRES's Krylov basis every step, and what a light solve takes, for one
or more source trees alternated in one run.

Part 1 (this tree): ``_krylov.gmres`` and ``_krylov.block_gmres`` with a cheap operator
(0.5u + 0.3·roll(u)), compiled: how many whole-basis copies the optimized HLO has (``copy``
ops of the basis' shape, each executed every step inside the loop), and the time per step
(``tol=0``, a fixed number of products, best of 3), for state sizes ``--sizes``.

Part 2 (each tree of ``--trees``, alternated ``--rounds`` times, each in a new process):
``difffog.render`` of fog-balls with ``method="gmres"`` at ``--cases`` N:M, ``--renders``
renders a process; the light solve's seconds (``Rendered.timings["light_s"]``, compile
excluded).  To compare with an earlier commit: ``git worktree add /tmp/old <commit>`` and
``--trees /tmp/old .``.

    PYTHONPATH=src python benchmarks/gmres_copies.py --trees /tmp/old .   # results/gmres_copies.md
"""

from __future__ import annotations

import argparse
import os
import statistics as st
import subprocess
import sys
import time
from pathlib import Path

import _common as C

ROOT = Path(__file__).resolve().parents[1]

CHILD = r"""
import sys, json
import difffog as df
N, M, K = int(sys.argv[1]), int(sys.argv[2]), int(sys.argv[3])
model = df.forward_model(df.load_scene("fog-balls"), "sweep", resolution=N, M=M, method="gmres")
out = [df.render(model).timings["light_s"] for _ in range(K)]
print(json.dumps(out))
"""


def part_hlo(sizes, steps):
    import jax
    import jax.numpy as jnp

    from difffog.forward.sweep._krylov import block_gmres, gmres

    rows = []
    for n in sizes:
        for kind in ("gmres", "block_gmres p=3"):
            if kind == "gmres":
                m, shape = 30, f"[31,{n}]"
                b = jax.random.normal(jax.random.key(0), (n,))
                f = jax.jit(lambda b: gmres(
                    lambda u, w: 0.5 * u + 0.3 * jnp.roll(u, 1) + jnp.where(w, b, 0.0), (n,),
                    jnp.float32, restart=30, max_matvecs=steps, tol=0.0))
                per = steps
            else:
                m, shape = 14, f"[15,3,{n // 3}]"
                b = jax.random.normal(jax.random.key(0), (3, n // 3))
                f = jax.jit(lambda B: block_gmres(
                    lambda U: 0.5 * U + 0.3 * jnp.roll(U, 1, 1), B, restart=14,
                    max_matvecs=3 * (steps // 3), tol=0.0))
                per = steps // 3
            text = f.lower(b).compile().as_text()
            copies = sum(1 for line in text.splitlines()
                         if " copy(" in line and shape in line.split("=")[1].split(" ")[1])
            jax.block_until_ready(f(b))
            ts = []
            for _ in range(3):
                t = time.perf_counter()
                jax.block_until_ready(f(b))
                ts.append(time.perf_counter() - t)
            rows.append([kind, str(n), str(m), str(copies), f"{1e3 * min(ts) / per:.2f}"])
            print(rows[-1], flush=True)
    return rows


def part_render(trees, cases, rounds, renders):
    times = {(t, c): [] for t in trees for c in cases}
    for _ in range(rounds):
        for case in cases:
            N, M = case.split(":")
            for tree in trees:
                env = dict(os.environ, PYTHONPATH=str(Path(tree).resolve() / "src"))
                out = subprocess.run([sys.executable, "-c", CHILD, N, M, str(renders)],
                                     env=env, capture_output=True, text=True, check=True)
                import json
                times[(tree, case)] += json.loads(out.stdout.strip().splitlines()[-1])
                print(tree, case, times[(tree, case)], flush=True)
    return [[tree, case, " / ".join(f"{t:.2f}" for t in times[(tree, case)]),
             f"{st.median(times[(tree, case)]):.2f}"] for case in cases for tree in trees]


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sizes", type=int, nargs="+", default=[500_001, 5_000_001])
    ap.add_argument("--steps", type=int, default=30)
    ap.add_argument("--trees", nargs="+", default=[str(ROOT)])
    ap.add_argument("--cases", nargs="+", default=["96:3", "128:5"])
    ap.add_argument("--rounds", type=int, default=2)
    ap.add_argument("--renders", type=int, default=3)
    ap.add_argument("--no-render", action="store_true", help="part 1 only (e.g. with "
                    "PYTHONPATH=<another tree>/src, to count that tree's copies)")
    ap.add_argument("--out", default=str(C.RESULTS / "gmres_copies.md"))
    a = ap.parse_args(argv)
    info = C.machine()
    hlo = part_hlo([n - n % 3 for n in a.sizes], a.steps)
    renders = [] if a.no_render else part_render(a.trees, a.cases, a.rounds, a.renders)
    lines = ["# GMRES's Krylov basis: copies per step, and the light solve", "",
             "`PYTHONPATH=src python benchmarks/gmres_copies.py` (see its docstring)", "",
             *C.machine_lines(info), "",
             "## Whole-basis copies in the compiled loop, and the time per step (this tree)",
             "", *C.md_table(["solver", "state numbers", "restart", "basis copies",
                              "ms per step"], hlo),
             *([] if a.no_render else [
                 "", "## fog-balls, `method=\"gmres\"`: the light solve's seconds", "",
                 *C.md_table(["tree", "N:M", "light s (each render)", "median"], renders)])]
    C.write_text(a.out, lines)


if __name__ == "__main__":
    main()
