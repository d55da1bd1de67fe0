"""Where a sweep model's compile time goes: the size of each compiled program (StableHLO lines,
while loops, functions) and its XLA compile seconds, for the light solve, the cameras, the
whole image program and the gradient of an image loss, with JAX's persistent cache off.

The default test suite is compile-bound (``python -m pytest -q --durations=0``), and so is a
user's first render or fit; this measures what a change to the program's structure buys.

    python benchmarks/compile_cost.py [--scene fog-balls] [--N 12] [--M 2] [--kernel auto]
        [--parts] [--out benchmarks/results/compile_cost.md]

The defaults are the test suite's small sweep model (``tests/helpers.py``: fog-balls reduced,
N = 12, M = 2, supersample 1).
"""

from __future__ import annotations

import argparse
import os
import re
import sys
import time

os.environ["DIFFFOG_CACHE_DIR"] = "off"  # every program compiles here: nothing from the cache

import _common as C  # noqa: E402


def _program(fn, *args):
    """(lines, while loops, functions, lowering s, compile s) of ``eqx.filter_jit(fn)`` at
    ``args``.  The model is passed as an argument, as ``light_jit`` and ``images_jit`` do: a
    closed-over model would bake its lattice into the program as constants (at N = 64, 120 MB
    of StableHLO, and XLA's time spent copying and folding them, not compiling)."""
    import equinox as eqx


    t0 = time.perf_counter()
    low = eqx.filter_jit(fn).lower(*args)
    t1 = time.perf_counter()
    low.compile()
    t2 = time.perf_counter()
    txt = low.as_text()
    return (txt.count("\n"), len(re.findall(r"stablehlo\.while", txt)),
            len(re.findall(r"func\.func", txt)), t1 - t0, t2 - t1)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scene", default="fog-balls")
    ap.add_argument("--N", type=int, default=12)
    ap.add_argument("--M", type=int, default=2)
    ap.add_argument("--kernel", default="auto", choices=["auto", "loop", "batched", "pallas"])
    ap.add_argument("--parts", action="store_true",
                    help="also the light solve's parts: its problem (first-collision sun and "
                         "sky), one Jacobi step, one sweep of all faces, GMRES alone")
    ap.add_argument("--out", default=None, help="write the markdown report here")
    a = ap.parse_args(argv)

    import jax
    import jax.numpy as jnp

    import difffog as df

    sys.path.insert(0, os.path.join(os.path.dirname(__file__), "..", "tests"))
    from helpers import small_scene

    scene = small_scene() if a.scene == "fog-balls" else df.load_scene(a.scene)
    model = df.forward_model(scene, "sweep", accuracy=None, resolution=a.N, M=a.M, tol=1e-6,
                             supersample=1, kernel=a.kernel)
    p = model.params()
    light = model.light(p)  # the cameras' program's input (eqx.filter_jit traces arrays only)
    rows = [("light solve", _program(lambda m, q: m.light(q), model, p)),
            ("cameras (images from a light)", _program(lambda m, l, q: m.images_from(l, q), model,
                                                        light, p)),
            ("images (both)", _program(lambda m, q: m.images(q, throw=False), model, p)),
            ("gradient of Σ images", _program(lambda m, q: jax.grad(
                lambda r: sum(jnp.sum(v) for v in m.images(r, throw=False).values()))(q),
                model, p))]
    if a.parts:
        rows += _parts(model, p)
    out = [f"# Compile cost of a sweep model ({a.scene}{' reduced' if a.scene == 'fog-balls' else ''}, "
           f"N = {a.N}, M = {a.M}, kernel {model.settings()['solver_options']['kernel']})", "",
           f"`python benchmarks/compile_cost.py --scene {a.scene} --N {a.N} --M {a.M} "
           f"--kernel {a.kernel}`; JAX's persistent compilation cache off.", "",
           *C.machine_lines(C.machine()), "",
           "| program | StableHLO lines | while loops | functions | lowering s | XLA compile s |",
           "|---|---:|---:|---:|---:|---:|"]
    for name, (lines, whiles, funcs, t_low, t_comp) in rows:
        out.append(f"| {name} | {lines} | {whiles} | {funcs} | {t_low:.1f} | {t_comp:.1f} |")
    text = "\n".join(out) + "\n"
    print(text)
    if a.out:
        C.write_text(a.out, text)


def _parts(model, p):
    """The light solve's parts, each compiled alone (the problem's first-collision passes are
    compiled with whatever uses them; what a part does not use, XLA drops)."""
    import jax.numpy as jnp

    from difffog.forward.sweep import _krylov
    from difffog.forward.sweep import _solver as S

    def problem(m, q):
        geom, cg, _, _ = m._with_density(q, cameras=False)
        geom, *_ = m._with_sun(q, geom, cg, None)
        return m.solver.problem(geom, q)

    pb = problem(model, p)
    state = S._zero_state(pb)

    def gmres_alone(b):  # its loop, Arnoldi, rotations and error estimate; K = b/2
        return _krylov.gmres(lambda v, on: 0.5 * v + jnp.where(on, b, 0.0), b.shape,
                             b.dtype, restart=pb.restart, max_matvecs=pb.max_iterations,
                             tol=pb.tol)

    return [("part: the problem (first-collision sun and sky)", _program(problem, model, p)),
            ("part: the problem + one sweep of all faces (traced Q, B)",
             _program(lambda m, q, s: S._sweep_all(s[1], s[1], problem(m, q)), model, p,
                      state)),
            ("part: the problem + one Jacobi step (traced state)",
             _program(lambda m, q, s: S._jacobi(s, problem(m, q)), model, p, state)),
            ("part: GMRES alone (a trivial operator)",
             _program(gmres_alone, jnp.ones(state[0].size, state[0].dtype)))]


if __name__ == "__main__":
    main()
