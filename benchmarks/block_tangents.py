"""A fit's tangent solves together (block GMRES) or one per unknown (GMRES each, vmapped in
lockstep): products, time and memory of the solves, and the README API example's fit with each.

A fit's Jacobian solves (I − K)ẋ_k = b_k for every unknown k with one operator.  Vmapped, the
sweep's GMRES runs the n solves in lockstep, n products per step until the slowest has
converged; ``SweepSolver(block_tangents=True)`` (the default since stop 79) solves them as one
block GMRES (``_krylov.block_gmres``) on the Krylov space of all n right-hand sides, restarted
every ⌈40/n⌉ block steps (at least 8), so its basis is as large as one single solve's.

Part 1, the solves: at the README example's Levenberg–Marquardt path (fog-balls, N = 28, both
views / 4, ζ, γ and the walls' albedo; ``tangent_warm_start.py``'s points) and at cloud-plane's
own values (N = ``--cloud-N``, ζ, γ and g, with its moments), the tangent systems are built
as the fit builds them and solved both ways, from zero and (along the path) from the last
point's solutions: products, wall time (median of ``--repeat``), the answers' distance to a
solve to 1e-3 × the tolerance, and the Krylov vectors each keeps.

Part 2, the fit: the README API example's ``difffog.fit`` (``model_error="refine"``) with
``model_settings={"block_tangents": ...}`` alternately, warm (after one compiling run of
each): wall time, LM steps and estimates.

    PYTHONPATH=src python benchmarks/block_tangents.py      # results/block_tangents.md
"""

from __future__ import annotations

import argparse
import statistics as st
import time

import _common as C

#: (ζ, γ, walls' albedo) at the README example's LM steps 2-5 (``tangent_warm_start.py``)
PATH = ((2.715, 0.468, 0.691), (1.959, 0.491, 0.700), (1.944, 0.5038, 0.7006),
        (1.9443, 0.50383, 0.70061))


def _systems(scene_name, unknowns, names, N, points):
    """For each point (unknowns' values, None: the scene's own), the tangent systems as the
    fit's Jacobian poses them: (apply_a on (n, size) blocks, B (n, size), tol)."""
    import jax
    import jax.numpy as jnp

    import difffog as df
    from difffog.fit import _driver as D
    from difffog.fit._residuals import FitProblem
    from difffog.fit._unknowns import as_unknowns, coordinates
    from difffog.forward.sweep import _solver as S
    from difffog.scene._params import get_param

    scene = df.load_scene(scene_name)
    model = D.make_model(scene, "sweep", cameras=names, downsample=4, resolution=N,
                         unknowns=len(unknowns))
    base = model.params(jnp.float32)
    coords, _ = coordinates(model.scene, base, as_unknowns(list(unknowns)))
    prob = FitProblem(model.scene, tuple(coords), tuple(names), "linear")
    solver = model.solver
    out = []
    for vals in points:
        if vals is None:
            vals = [float(get_param(base, model.scene, c.path)) for c in coords]
        u = jnp.asarray([c.to_u(v) for c, v in zip(coords, vals)], jnp.float32)
        p = prob.params(u, base)
        geom, *_ = model._with_density(p, cameras=False)
        pb = solver.problem(geom, p)
        root = solver.solve(geom, p).state
        flat_root, unravel = jax.flatten_util.ravel_pytree(root)

        def column(e, u=u, geom=geom, pb=pb, root=root):
            _, pdot = jax.jvp(lambda x: solver.problem(geom, prob.params(x, base)), (u,), (e,))
            _, gdot = jax.jvp(lambda q: S._rewrite(root, q), (pb,), (pdot,))
            return -jax.flatten_util.ravel_pytree(gdot)[0]

        B = jax.jit(jax.vmap(column))(jnp.eye(len(coords), dtype=jnp.float32))

        def apply_a(U, pb=pb, unravel=unravel):
            return jax.vmap(lambda v: jax.flatten_util.ravel_pytree(
                S._rewrite_linear(unravel(v), pb))[0])(U)

        pre = S._preconditioner(pb)
        out.append((vals, apply_a, B, float(solver.adjoint_rtol), pre, unravel,
                    flat_root.size))
    return out


def _rows_preconditioner(pre, unravel):
    """The light solve's preconditioner (or None) on the rows of a (n, size) block."""
    import jax

    if pre is None:
        return None
    return lambda U: jax.vmap(lambda v: jax.flatten_util.ravel_pytree(
        pre.apply(unravel(v)))[0])(U)


def _solve_both(apply_a, B, tol, pre, unravel, X0, repeat):
    """((lockstep products per column, seconds, X), (block products, seconds, X))."""
    import jax
    import jax.numpy as jnp

    from difffog.forward.sweep._krylov import block_gmres, gmres

    n = B.shape[0]
    precondition = _rows_preconditioner(pre, unravel)

    def one(b, x0):
        def apply_k(v, with_sources):
            return v - apply_a(v[None])[0] + jnp.where(with_sources, b, 0.0)
        pc = None if precondition is None else (lambda v: precondition(v[None])[0])
        x, _, k, _ = gmres(apply_k, b.shape, b.dtype, restart=40, max_matvecs=400, tol=tol,
                           precondition=pc, x0=x0)
        return x, k

    lock = jax.jit(lambda B, X0: jax.vmap(one)(B, X0) if X0 is not None
                   else jax.vmap(lambda b: one(b, None))(B))
    blk = jax.jit(lambda B, X0: block_gmres(apply_a, B, restart=max(-(-40 // n), 8),
                                            max_matvecs=400 * n, tol=tol,
                                            precondition=precondition, X0=X0))

    def timed(f):
        r = jax.block_until_ready(f(B, X0))
        ts = []
        for _ in range(repeat):
            t = time.perf_counter()
            r = jax.block_until_ready(f(B, X0))
            ts.append(time.perf_counter() - t)
        return r, st.median(ts)

    (xl, kl), tl = timed(lock)
    (xb, kb, _), tb = timed(blk)
    return ([int(k) for k in kl], tl, xl), (int(kb), tb, xb)


def _reference(apply_a, B, tol, pre, unravel):
    import jax

    from difffog.forward.sweep._krylov import block_gmres

    precondition = _rows_preconditioner(pre, unravel)
    return jax.jit(lambda B: block_gmres(apply_a, B, restart=40, max_matvecs=4000,
                                         tol=tol * 1e-3, precondition=precondition))(B)[0]


def _apart(X, ref):
    import numpy as np

    X, ref = np.asarray(X, np.float64), np.asarray(ref, np.float64)
    return float(max(np.abs(x - r).max() / np.abs(r).max() for x, r in zip(X, ref)))


def part_solves(args):
    rows = []
    cases = [("fog-balls", ("fog.scattering", "fog.absorption", "shape.walls.albedo"),
              ["oblique", "top"], 28, PATH)]
    if args.cloud_N:
        cases.append(("cloud-plane", ("fog.scattering", "fog.absorption", "fog.g"),
                      ["top", "oblique"], args.cloud_N, (None,)))
    for scene, unknowns, names, N, points in cases:
        systems = _systems(scene, unknowns, names, N, points)
        prev = None
        for step, (vals, apply_a, B, tol, pre, unravel, size) in enumerate(systems):
            n = B.shape[0]
            ref = _reference(apply_a, B, tol, pre, unravel)
            for start in ("zero", "last point's") if prev is not None else ("zero",):
                X0 = None if start == "zero" else prev
                (kl, tl, xl), (kb, tb, xb) = _solve_both(apply_a, B, tol, pre, unravel, X0,
                                                         args.repeat)
                rows.append([f"{scene} N={N}" + (f" step {step + 2}" if len(points) > 1
                                                 else ""),
                             ", ".join(f"{v:.4g}" for v in vals), start,
                             " / ".join(map(str, kl)), str(n * max(kl)), str(kb),
                             f"{tl:.3f}", f"{tb:.3f}", f"{_apart(xl, ref):.1e}",
                             f"{_apart(xb, ref):.1e}",
                             f"{n * 41} / {(max(-(-40 // n), 8) + 1) * n}"])
                print(rows[-1], flush=True)
            prev = ref
    return rows


README_FIT = dict(unknowns={"fog.scattering": 1.0, "fog.absorption": 0.8,
                            "shape.walls.albedo": 0.5},
                  resolution=28, downsample=4, model_error="refine")
TRUTH = {"fog.scattering": 2.0, "fog.absorption": 0.5, "shape.walls.albedo": 0.7}


def part_fit(args):
    import difffog as df
    from difffog.study.references import reference

    scene = df.load_scene("fog-balls")
    targets = {cam: reference("fog-balls", cam)[0] for cam in ("top", "oblique")}
    runs = {True: [], False: []}
    for rep in range(args.fit_repeat + 1):
        for block in (False, True):
            t = time.perf_counter()
            r = df.fit(scene, targets, README_FIT["unknowns"], resolution=28, downsample=4,
                       model_error="refine", model_settings={"block_tangents": block})
            wall = time.perf_counter() - t
            print(block, rep, round(wall, 2), r.estimates, flush=True)
            if rep:  # the first of each compiles
                runs[block].append((wall, r))
    rows = []
    for block in (False, True):
        walls = [w for w, _ in runs[block]]
        r = runs[block][-1][1]
        rows.append(["block GMRES" if block else "one GMRES per unknown (lockstep)",
                     " / ".join(f"{w:.1f}" for w in walls), str(len(r.history)),
                     ", ".join(f"{100 * (r.estimates[k] / v - 1):+.3f}%"
                               for k, v in TRUTH.items())])
    return rows


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeat", type=int, default=5)
    ap.add_argument("--fit-repeat", type=int, default=3)
    ap.add_argument("--cloud-N", type=int, default=32, help="0: no cloud-plane rows")
    ap.add_argument("--no-fit", action="store_true")
    ap.add_argument("--out", default=str(C.RESULTS / "block_tangents.md"))
    a = ap.parse_args(argv)
    info = C.machine()
    solves = part_solves(a)
    lines = ["# A fit's tangent solves: one block GMRES or one GMRES per unknown", "",
             "`PYTHONPATH=src python benchmarks/block_tangents.py` (see its docstring)", "",
             *C.machine_lines(info), "",
             "## The solves (float32, tolerance = the fit's `adjoint_rtol`)", "",
             *C.md_table(["case", "unknowns' values", "start", "GMRES products per unknown",
                          "lockstep products", "block products", "lockstep s", "block s",
                          "lockstep apart", "block apart", "Krylov vectors lockstep / block"],
                         solves)]
    if not a.no_fit:
        fits = part_fit(a)
        lines += ["", "## The README API example's fit, warm (each way compiled once first)",
                  "", *C.md_table(["tangent solves", "fit wall s (runs alternating)",
                                   "LM steps", "ζ, γ, walls vs truth"], fits)]
    C.write_text(a.out, lines)


if __name__ == "__main__":
    main()
