"""Where a fit's memory goes: XLA's temporaries of the compiled images and of their Jacobian as
the fit computes it (``FitProblem.model_and_jacobian``: the light field's tangents by forward
mode, one tangent light solve per unknown, all at once, fed to the cameras by forward mode),
for cloud-plane with ζ, γ and g unknown, with the run time of each Jacobian (compiled; one
warm run each) and how far its columns are from the fit's.

Beside it: the same with the tangent solves' products linearised (``SweepSolver(tangents=
"linearised")``: ``lx.linearise`` keeps the linearised sweeps' residuals for the solve), with
the tangent solves one after another (``lax.map``), the cameras' part alone, and the route the
fit took before stop 42 (the transpose of the whole VJP, whose light part runs the adjoint's
linearised operator transposed back) with its light field's part alone.

    python benchmarks/fit_memory.py [--N 24] [--downsample 4] [--out FILE.md]
    python benchmarks/fit_memory.py --scaling [L:N:M:scheme ...]
    python benchmarks/fit_memory.py --tangents [L:N:M:scheme:P ...]
    python benchmarks/fit_memory.py --cameras [N:downsample:P ...]

``--scaling``: only the light field's Jacobian (the transpose of its VJP, which linearises the
sweeps as a gradient's adjoint does) for each setting (L:N:M:scheme[:keep|recompute], the
last ``SweepSolver.sweep_residuals``), in bytes per
lattice node and direction, the figure ``difffog._cost`` charges a gradient for (stop 41:
step scheme ~820-950 B, linear ~1700 B, L = 3 ~1980 B); default settings
0:24:2:auto 0:24:3:step 0:24:3:linear 0:32:3:linear 3:16:3:auto 3:24:3:auto 3:32:3:auto.

``--tangents``: the light field's tangents alone as the fit takes them (``jax.jvp``, P unknowns
at once, products matrix-free) per setting, in bytes per number of the solve's state (Λ, its K
moments and E: n·(1 [+ 1] + K)) and tangent, the figure ``difffog._cost`` charges a fit's
Jacobian for (stop 42: ~500-600 B for 3 tangents, ~880 B for one with its light solve's);
default settings 0:24:3:step:1 0:24:3:step:3 0:24:3:linear:3 0:32:3:linear:3 3:24:3:auto:3
3:16:3:auto:3.

``--cameras``: the cameras' part alone (the light held fixed, L = 3, M = 3) per setting, in
bytes per ray and march step (2·max(lattice shape) steps), the figure ``difffog._cost``
charges a gradient or a fit's Jacobian for (stop 42: ~1240-1290 B, once whatever P); default
settings 16:4:3 24:4:3 32:4:3 24:8:3 24:4:1.

(measured by compiling, not by running: ``compiled.memory_analysis()``; the run times need the
memory, so keep N small.)
"""

from __future__ import annotations

import argparse
import time

import _common as C

PATHS = ("fog.scattering", "fog.absorption", "fog.g")


def setup(N: int, M: int, L: int, downsample: int, scheme: str = "auto",
          residuals: str = "keep"):
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
                       model_settings={"M": M, "phase_order": L, "scheme": scheme,
                                       "sweep_residuals": residuals})
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
    ap.add_argument("--tangents", nargs="*", default=None, metavar="L:N:M:SCHEME:P")
    ap.add_argument("--cameras", nargs="*", default=None, metavar="N:DOWNSAMPLE:P")
    a = ap.parse_args(argv)
    info = C.machine()
    if a.scaling is not None:
        return scaling(a.scaling or SCALING, a.downsample, info)
    if a.tangents is not None:
        return tangent_scaling(a.tangents or TANGENTS, a.downsample, info)
    if a.cameras is not None:
        return camera_scaling(a.cameras or CAMERAS, info)

    import dataclasses

    import equinox as eqx
    import jax
    import jax.numpy as jnp

    from difffog.forward.sweep._march import forward_mode

    model, problem, base, u0 = setup(a.N, a.M, 3, a.downsample)
    eye = jnp.eye(u0.shape[0], dtype=u0.dtype)

    def images(u):
        return problem.model(model, u, base)[0]

    def jacobian(u, m=model):
        y, J, _ = problem.model_and_jacobian(m, u, base)
        return y, J

    linearised = eqx.tree_at(lambda m: m.solver, model,
                             dataclasses.replace(model.solver, tangents="linearised"))

    def reverse_route(u):  # the fit's route before stop 42: the transpose of the whole VJP
        y = lambda v: problem.model(model, v, base)[0]  # noqa: E731
        return y(u), transposed_jacobian(y, u).T

    def light_jacobian(u):  # the reverse route, the light field alone
        return transposed_jacobian(
            lambda v: model.light(problem.params(v, base)).fluence.ravel(), u)

    light0 = model.light(base)

    def model_from(light, u):  # FitProblem.model with the light given
        return problem.images_from(model, light, problem.params(u, base), u)

    def camera_jacobian(u):  # the cameras' part, the light held fixed, as the fit takes it
        with forward_mode():
            return jax.jacfwd(lambda v: model_from(light0, v))(u)

    def camera_jacobian_transposed(u):  # the same before stop 60: the transpose of the VJP
        return transposed_jacobian(lambda v: model_from(light0, v), u)

    def one_at_a_time(u):  # the fit's route with the tangent solves one after another
        f = lambda v: model.light(problem.params(v, base))  # noqa: E731
        light = f(u)
        dots = jax.lax.map(lambda e: jax.jvp(f, (u,), (e,))[1], eye)
        floats, rest = eqx.partition(light, eqx.is_inexact_array)
        d_floats = eqx.filter(dots, eqx.is_inexact_array)
        g = lambda fl, v: model_from(eqx.combine(fl, rest), v)  # noqa: E731
        with forward_mode():
            y = g(floats, u)
            cols = jax.lax.map(lambda de: jax.jvp(g, (floats, u), de)[1], (d_floats, eye))
        return y, cols.T

    rows, ref = [], None
    for name, fn, run in (
            ("images (value)", images, False),
            ("Jacobian, the fit's route (tangents matrix-free)", jacobian, True),
            ("  the same, tangents linearised", lambda u: jacobian(u, linearised), True),
            ("  the same, tangent solves one at a time (lax.map)", one_at_a_time, True),
            ("  its cameras alone (light fixed)", camera_jacobian, False),
            ("  its cameras alone, the transpose of their VJP (before stop 60)",
             camera_jacobian_transposed, False),
            ("Jacobian, transpose of the whole VJP (before stop 42)", reverse_route, True),
            ("  its light field alone", light_jacobian, False)):
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
        L, N, M, scheme, *rest = s.split(":")
        L, N, M = int(L), int(N), int(M)
        residuals = rest[0] if rest else "keep"
        model, problem, base, u0 = setup(N, M, L, downsample, scheme, residuals)

        def light_jacobian(u, model=model, problem=problem, base=base):
            return transposed_jacobian(
                lambda v: model.light(problem.params(v, base)).fluence.ravel(), u)

        mib = C.xla_mib(jax.jit(light_jacobian).lower(u0).compile())
        n, D = math.prod(model.geometry.shape), (2 * M + 1) ** 2
        rows.append([str(L), str(N), str(M), ("linear" if model.geometry.linear else
                                             "substep" if model.geometry.substep else "step"),
                     residuals, str(n), f"{mib:.0f}", f"{mib * 2**20 / (n * D):.0f}"])
        print(rows[-1], flush=True)
    print("\n".join([*C.machine_lines(info), "", *C.md_table(
        ["L", "N", "M", "scheme", "sweep residuals", "nodes", "light Jacobian MiB",
         "bytes per node·direction"],
        rows)]))


TANGENTS = ["0:24:3:step:1", "0:24:3:step:3", "0:24:3:linear:3", "0:32:3:linear:3",
            "3:24:3:auto:3", "3:16:3:auto:3"]


def tangent_scaling(settings, downsample: int, info):
    """The light field's forward-mode tangents alone (the fit's route) per setting."""
    import math

    import jax
    import jax.numpy as jnp

    rows = []
    for s in settings:
        L, N, M, scheme, P = s.split(":")
        L, N, M, P = int(L), int(N), int(M), int(P)
        model, problem, base, u0 = setup(N, M, L, downsample, scheme)

        def light_tangents(u, model=model, problem=problem, base=base, P=P):
            f = lambda v: model.light(problem.params(  # noqa: E731
                jnp.concatenate([v, u0[P:]]), base)).fluence
            return jax.vmap(lambda e: jax.jvp(f, (u,), (e,))[1])(jnp.eye(P, dtype=u.dtype))

        mib = C.xla_mib(jax.jit(light_tangents).lower(u0[:P]).compile())
        geom = model.geometry
        n, K = math.prod(geom.shape), (L + 1) ** 2 - 1
        state = n * ((2 if geom.has_surfaces else 1) + K)
        rows.append([str(L), str(N), str(M), "linear" if geom.linear else "step", str(P),
                     str(n), f"{mib:.0f}", f"{mib * 2**20 / (P * state):.0f}"])
        print(rows[-1], flush=True)
    print("\n".join([*C.machine_lines(info), "", *C.md_table(
        ["L", "N", "M", "scheme", "tangents", "nodes", "light tangents MiB",
         "bytes per state number and tangent"], rows)]))


CAMERAS = ["16:4:3", "24:4:3", "32:4:3", "24:8:3", "24:4:1"]


def camera_scaling(settings, info):
    """The cameras' part of the fit's Jacobian alone (the light held fixed) per setting."""
    import jax
    import jax.numpy as jnp

    from difffog._cost import camera_rays

    rows = []
    for s in settings:
        N, ds, P = (int(x) for x in s.split(":"))
        model, problem, base, u0 = setup(N, 3, 3, ds)
        light0 = model.light(base)

        def images(x, model=model, problem=problem, base=base, light0=light0, u0=u0, P=P):
            w = jnp.concatenate([x, u0[P:]])
            return problem.images_from(model, light0, problem.params(w, base), w)

        mib = C.xla_mib(jax.jit(lambda x, f=images: transposed_jacobian(f, x))
                        .lower(u0[:P]).compile())
        rays = camera_rays(model.scene, None, model.supersample)
        steps = 2 * max(model.geometry.shape)
        rows.append([str(N), str(ds), str(P), str(rays), str(steps), f"{mib:.0f}",
                     f"{mib * 2**20 / (rays * steps):.0f}"])
        print(rows[-1], flush=True)
    print("\n".join([*C.machine_lines(info), "", *C.md_table(
        ["N", "downsample", "unknowns", "rays", "steps", "cameras' Jacobian MiB",
         "bytes per ray and step"], rows)]))


if __name__ == "__main__":
    main()
