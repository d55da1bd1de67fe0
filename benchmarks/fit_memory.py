"""Where a fit's memory goes: XLA's temporaries of the compiled images, of their Jacobian as the
fit computes it (``FitProblem.model_and_jacobian``: the transpose of the VJP, one column per
unknown), and of its two parts alone (the light field's Jacobian by the same route; the
cameras' with the light held fixed), for cloud-plane with ζ, γ and g unknown.

An alternative route is measured beside them: the light's tangents by forward mode
(``jax.jvp`` through the implicit function: one tangent solve per unknown) fed to the cameras'
transposed VJP, vmapped over the unknowns or one after another (``lax.map``), with its run
time against the fit's route (both compiled; one warm run each).

    python benchmarks/fit_memory.py [--N 24] [--downsample 4] [--out FILE.md]
    python benchmarks/fit_memory.py --scaling [L:N:M:scheme ...]

``--scaling``: only the light field's Jacobian (the fit's route) for each setting, in bytes per
lattice node and direction, the figure ``difffog._cost`` charges a gradient for (stop 41:
step scheme ~820-950 B, linear ~1700 B, L = 3 ~1980 B); default settings
0:24:2:auto 0:24:3:step 0:24:3:linear 0:32:3:linear 3:16:3:auto 3:24:3:auto 3:32:3:auto.

(measured by compiling, not by running: ``compiled.memory_analysis()``; the run times need the
memory, so keep N small.)
"""

from __future__ import annotations

import argparse
import time

import _common as C

PATHS = ("fog.scattering", "fog.absorption", "fog.g")


def setup(N: int, M: int, L: int, downsample: int, scheme: str = "auto"):
    """cloud-plane's fit model (both cameras / ``downsample``), its ``FitProblem`` for ζ, γ, g,
    the base parameters and the unknowns at the scene's values."""
    import jax.numpy as jnp

    import difffog as df
    from difffog.fit._driver import make_model
    from difffog.fit._residuals import FitProblem
    from difffog.fit._unknowns import Coordinate

    names = ("oblique", "top")
    model = make_model(df.load_scene("cloud-plane"), "sweep", cameras=list(names),
                       downsample=downsample, resolution=N,
                       model_settings={"M": M, "phase_order": L, "scheme": scheme})
    base = model.params(jnp.float32)
    coords = tuple(Coordinate(p, 0.0, float("inf")) for p in PATHS[:2]) + (
        Coordinate("fog.g", -0.99, 0.99),)
    problem = FitProblem(model.scene, coords, names, "linear")
    u0 = jnp.asarray([c.to_u(float(df.get_param(base, model.scene, c.path))) for c in coords],
                     jnp.float32)
    return model, problem, base, u0


def transposed_jacobian(f, u):
    """The columns (n, P) of f's Jacobian at u by the fit's route: the transpose of the VJP,
    vmapped over the unknowns."""
    import jax
    import jax.numpy as jnp

    y, vjp = jax.vjp(f, u)
    jt = jax.linear_transpose(vjp, y)
    return jax.vmap(lambda e: jt((e,))[0])(jnp.eye(u.shape[0], dtype=u.dtype))


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--N", type=int, default=24)
    ap.add_argument("--M", type=int, default=3)
    ap.add_argument("--downsample", type=int, default=4)
    ap.add_argument("--out", default=None)
    ap.add_argument("--scaling", nargs="*", default=None, metavar="L:N:M:SCHEME")
    a = ap.parse_args(argv)
    info = C.machine()
    if a.scaling is not None:
        return scaling(a.scaling or SCALING, a.downsample, info)

    import equinox as eqx
    import jax
    import jax.numpy as jnp

    model, problem, base, u0 = setup(a.N, a.M, 3, a.downsample)
    eye = jnp.eye(u0.shape[0], dtype=u0.dtype)

    def images(u):
        return problem.model(model, u, base)[0]

    def jacobian(u):
        y, J, _ = problem.model_and_jacobian(model, u, base)
        return y, J

    def light_jacobian(u):  # the same route, the light field alone
        return transposed_jacobian(
            lambda v: model.light(problem.params(v, base)).fluence.ravel(), u)

    light0 = model.light(base)

    def model_from(light, u):  # FitProblem.model with the light given
        p = problem.params(u, base)
        imgs = model.images_from(light, p)
        g = problem.gains(u)
        return jnp.concatenate([g[n] * jnp.ravel(imgs[n]) for n in problem.names])

    def camera_jacobian(u):  # the same route, the light held fixed
        return transposed_jacobian(lambda v: model_from(light0, v), u)

    def forward_light(batch: str):
        def jac(u):
            f = lambda v: model.light(problem.params(v, base))  # noqa: E731
            light = f(u)
            if batch == "vmap":
                dots = jax.vmap(lambda e: jax.jvp(f, (u,), (e,))[1])(eye)
            else:
                dots = jax.lax.map(lambda e: jax.jvp(f, (u,), (e,))[1], eye)
            floats, rest = eqx.partition(light, eqx.is_inexact_array)
            d_floats = eqx.filter(dots, eqx.is_inexact_array)
            g = lambda fl, v: model_from(eqx.combine(fl, rest), v)  # noqa: E731
            y, vjp = jax.vjp(g, floats, u)
            jt = jax.linear_transpose(vjp, y)
            step = lambda de: jt(de)[0]  # noqa: E731
            cols = (jax.vmap(step)((d_floats, eye)) if batch == "vmap"
                    else jax.lax.map(step, (d_floats, eye)))
            return y, cols.T
        return jac

    rows, ref = [], None
    for name, fn, run in (("images (value)", images, False),
                          ("Jacobian, the fit's route", jacobian, True),
                          ("  its light field alone", light_jacobian, False),
                          ("  its cameras alone (light fixed)", camera_jacobian, False),
                          ("Jacobian, forward-mode light, vmap", forward_light("vmap"), True),
                          ("Jacobian, forward-mode light, lax.map", forward_light("map"), True)):
        compiled = jax.jit(fn).lower(u0).compile()
        mib = C.xla_mib(compiled)
        secs = diff = ""
        if run:
            out = jax.block_until_ready(compiled(u0))
            t = time.perf_counter()
            out = jax.block_until_ready(compiled(u0))
            secs = f"{time.perf_counter() - t:.1f}"
            if ref is None:
                ref = out[1]
            else:
                diff = f"{float(jnp.max(jnp.abs(out[1] - ref)) / jnp.max(jnp.abs(ref))):.1e}"
        rows.append([name, f"{mib:.0f}", secs, diff])
        print(rows[-1], flush=True)

    lines = [f"# Where a fit's memory goes (cloud-plane, N = {a.N}, M = {a.M}, L = 3, both "
             f"cameras / {a.downsample}, 3 unknowns, float32)", "",
             *C.machine_lines(info), "",
             *C.md_table(["program", "XLA temporaries MiB", "warm run s",
                          "J vs the fit's route (max rel.)"], rows)]
    text = "\n".join(lines)
    print(text)
    if a.out:
        C.write_text(a.out, text + "\n")


SCALING = ["0:24:2:auto", "0:24:3:step", "0:24:3:linear", "0:32:3:linear", "3:16:3:auto",
           "3:24:3:auto", "3:32:3:auto"]


def scaling(settings, downsample: int, info):
    """The light field's Jacobian alone (3 unknowns, the fit's route) per setting."""
    import math

    import jax

    rows = []
    for s in settings:
        L, N, M, scheme = s.split(":")
        L, N, M = int(L), int(N), int(M)
        model, problem, base, u0 = setup(N, M, L, downsample, scheme)

        def light_jacobian(u, model=model, problem=problem, base=base):
            return transposed_jacobian(
                lambda v: model.light(problem.params(v, base)).fluence.ravel(), u)

        mib = C.xla_mib(jax.jit(light_jacobian).lower(u0).compile())
        n, D = math.prod(model.geometry.shape), (2 * M + 1) ** 2
        rows.append([str(L), str(N), str(M), "linear" if model.geometry.linear else "step",
                     str(n), f"{mib:.0f}", f"{mib * 2**20 / (n * D):.0f}"])
        print(rows[-1], flush=True)
    print("\n".join([*C.machine_lines(info), "", *C.md_table(
        ["L", "N", "M", "scheme", "nodes", "light Jacobian MiB", "bytes per node·direction"],
        rows)]))


if __name__ == "__main__":
    main()
