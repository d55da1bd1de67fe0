"""How many GMRES steps a fit's tangent solves save by starting from the previous
Levenberg–Marquardt step's tangents (measured at stop 60 for a possible change, built at stop
61: the fit's tangent solves now start from the last accepted step's, ``FitProblem.
jacobian_and_tangents``; this script runs the solves directly, from zero and from the last
point's, to compare them).

Along the README API example's path (fog-balls, N = 28, both views / 4, the unknowns ζ, γ and
the walls' albedo at the values its LM steps took), each unknown's tangent system
(I − K)ẋ = −∂G/∂θ·θ̇ is solved by the sweep's GMRES (tol 1e-4, the fit's ``adjoint_rtol``)
from zero and from the previous point's solution; the table gives the steps of each and how
far the two answers are apart (max-norm, relative).  The report starts with the machine and
its copy bandwidth.

    PYTHONPATH=src python benchmarks/tangent_warm_start.py   # results/tangent_warm_start.md
"""

from __future__ import annotations

import argparse

import _common as C

#: (ζ, γ, walls' albedo) at the README example's LM steps 2-5 (its history at stop 60)
PATH = ((2.715, 0.468, 0.691), (1.959, 0.491, 0.700), (1.944, 0.5038, 0.7006),
        (1.9443, 0.50383, 0.70061))
UNKNOWNS = ("fog.scattering", "fog.absorption", "shape.walls.albedo")


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", default=str(C.RESULTS / "tangent_warm_start.md"))
    a = ap.parse_args(argv)
    info = C.machine()
    import jax
    import jax.numpy as jnp

    import difffog as df
    from difffog.fit import _driver as D
    from difffog.fit._residuals import FitProblem
    from difffog.fit._unknowns import as_unknowns, coordinates
    from difffog.forward.sweep import _solver as S
    from difffog.forward.sweep._krylov import gmres

    scene = df.load_scene("fog-balls")
    names = ["oblique", "top"]
    model = D.make_model(scene, "sweep", cameras=names, downsample=4, resolution=28,
                         unknowns=3)
    base = model.params(jnp.float32)
    coords, _ = coordinates(model.scene, base, as_unknowns(list(UNKNOWNS)))
    prob = FitProblem(model.scene, tuple(coords), tuple(names), "linear")
    solver = model.solver

    def tangents(u, guesses):
        p = prob.params(u, base)
        geom, *_ = model._with_density(p, cameras=False)
        pb = solver.problem(geom, p)
        root = solver.solve(geom, p).state
        n = root[0].size

        def flat(t):
            return jnp.concatenate([t[0].ravel(), t[1].ravel()])

        def unflat(v):
            return v[:n].reshape(root[0].shape), v[n:].reshape(root[1].shape)

        out = []
        for i in range(u.shape[0]):
            e = jnp.zeros_like(u).at[i].set(1.0)
            _, pdot = jax.jvp(lambda x: solver.problem(geom, prob.params(x, base)), (u,), (e,))
            _, gdot = jax.jvp(lambda q: S._rewrite(root, q), (pb,), (pdot,))
            b = -flat(gdot)

            def apply_k(v, with_sources, b=b):
                return v - flat(S._rewrite_linear(unflat(v), pb)) + jnp.where(with_sources, b,
                                                                                0.0)

            x, _, k, _ = gmres(apply_k, b.shape, b.dtype, restart=40, max_matvecs=200,
                               tol=float(solver.adjoint_rtol),
                               x0=None if guesses is None else guesses[i])
            out.append((x, k))
        return out

    run = jax.jit(tangents)
    rows, prev = [], None
    for k, vals in enumerate(PATH):
        u = jnp.asarray([c.to_u(v) for c, v in zip(coords, vals)], jnp.float32)
        cold = run(u, None)
        row = [str(k + 2), ", ".join(f"{v:g}" for v in vals),
               " / ".join(str(int(s)) for _, s in cold)]
        if prev is None:
            row += ["", ""]
        else:
            warm = run(u, [x for x, _ in prev])
            row += [" / ".join(str(int(s)) for _, s in warm),
                    f"{max(float(jnp.max(jnp.abs(w[0] - c[0])) / jnp.max(jnp.abs(c[0]))) for w, c in zip(warm, cold)):.1e}"]  # noqa: E501
        rows.append(row)
        prev = cold
        print(row, flush=True)
    lines = ["# Tangent solves from the previous step's tangents", "",
             "`PYTHONPATH=src python benchmarks/tangent_warm_start.py` (see its docstring)", "",
             *C.machine_lines(info), "",
             *C.md_table(["LM step", "ζ, γ, walls' albedo", "GMRES steps from zero (ζ / γ / "
                          "albedo)", "from the last step's tangents", "answers apart"], rows)]
    C.write_text(a.out, lines)


if __name__ == "__main__":
    main()
