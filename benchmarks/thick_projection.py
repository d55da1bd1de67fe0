"""How far the light a solve returns is from its scheme's fixed point: the residual
max|x − F(x)| / max x of the projected state (Λ ≥ 0, E ≥ 0, ``_solver._non_negative``), per
part of the state.  The linear scheme is not positive: where one lattice step spans many mean
free paths its fixed point dips below 0, and the projection moves the light.

    python benchmarks/thick_projection.py cube100:12:2 cube1000:32:2 cloud-plane:64:3

(``SCENE:N:M``; ``cubeZETA`` is issue 14's thick cube at ζ = ZETA, anything else a scene name
or file; float64, tol 1e-8, the default scheme ("auto").)
"""

from __future__ import annotations

import argparse
import time

import jax
import jax.numpy as jnp

import _common as C
import difffog as df
from difffog import Params, SweepSolver
from difffog.forward.sweep import _solver as S
from difffog.study._semi_infinite import thick_cube


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("cases", nargs="+", help="SCENE:N:M")
    ap.add_argument("--scheme", default="auto", choices=["auto", "step", "linear"])
    args = ap.parse_args(argv)
    jax.config.update("jax_enable_x64", True)
    C.print_machine(C.machine())
    rows = []
    for case in args.cases:
        name, n, m = case.split(":")
        scene = thick_cube(float(name[4:])) if name.startswith("cube") else df.load_scene(name)
        lat = df.voxelize(scene, int(n), int(m))
        s = SweepSolver(M=int(m), tol=1e-8, max_iterations=3000, scheme=args.scheme)
        g = s.prepare(scene, lat)
        pb = s.problem(g, Params.from_scene(scene, jnp.float64))
        t0 = time.perf_counter()
        root, (_, k, _) = jax.jit(S._solve_fixed_point)(pb)
        root = S._non_negative(root, g.channels)
        res = jax.jit(S._rewrite)(root, pb)
        parts = []
        for r, x in zip(res, root):
            peak = float(jnp.max(jnp.abs(x)))
            parts.append(f"{float(jnp.max(jnp.abs(r))) / peak:.1e}" if peak > 0 else
                         ("0" if float(jnp.max(jnp.abs(r))) == 0 else "all clipped"))
        rows.append([case, s.resolved_scheme(scene, lat), str(int(k)), *parts,
                     f"{time.perf_counter() - t0:.0f}"])
        print(rows[-1], flush=True)
    print()
    print("\n".join(C.md_table(["scene:N:M", "scheme", "GMRES steps", "Λ: residual / peak",
                                "E: residual / peak", "s"], rows, "llrrrr")))


if __name__ == "__main__":
    main()
