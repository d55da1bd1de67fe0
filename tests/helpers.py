"""Shared test helpers: small scenes, the list of forward models every interface test runs,
finite differences, and reference values that need test-only packages (iadpython)."""

from __future__ import annotations

import dataclasses
import os

import jax
import jax.numpy as jnp
import numpy as np

import difffog as df


def small_scene(name: str = "fog-balls", overrides=(), size=(12, 10)):
    """A built-in scene with every camera at ``size`` (width, height) pixels.  fog-balls gets
    walls thick enough for a 12-node lattice."""
    extra = ["shape.walls.thickness=0.1"] if name == "fog-balls" else []
    scene = df.load_scene(name, extra + list(overrides))
    cams = tuple(dataclasses.replace(c, resolution=size) for c in scene.cameras)
    return scene.replace(cameras=cams)


#: (solver name, settings) of the small models every interface test runs; fixture ``model``
#: (conftest.py) builds each once per test session
MODELS = {
    "sweep": dict(resolution=12, M=2, tol=1e-6, supersample=1),
    "splat": dict(resolution=12, supersample=1),
}

#: the fit's view of fog-balls: both cameras reduced 8× (16×16 and 20×15 pixels)
FIT_DOWNSAMPLE = 8
#: the parameters the shared fit tests recover
FIT_TRUTH = {"fog.scattering": 2.0, "fog.absorption": 0.5, "shape.walls.albedo": 0.7}


def build_model(solver: str, scene=None, **extra):
    scene = small_scene() if scene is None else scene
    return df.forward_model(scene, solver, accuracy=None, **{**MODELS[solver], **extra})


def build_fit_model(solver: str):
    """The model ``df.fit(forward=solver, resolution=12, downsample=8)`` builds for fog-balls
    (the solver's fit defaults, M = 2 and tol 1e-6 for the sweep): the models every fit test
    shares, so that their compiled steps are shared too."""
    from difffog.fit._driver import make_model

    settings = {"M": 2, "tol": 1e-6} if solver == "sweep" else {}
    return make_model(fit_scene(), solver, cameras=["top", "oblique"], resolution=12,
                      downsample=FIT_DOWNSAMPLE, model_settings=settings)


def fit_scene():
    return df.load_scene("fog-balls", ["shape.walls.thickness=0.1"])  # > one voxel at N = 12


def central_difference(f, params, scene, path, rel_step=1e-5):
    """(f(p + ε) − f(p − ε)) / 2ε along the dotted parameter ``path`` (ε relative)."""
    v = float(df.get_param(params, scene, path))
    eps = rel_step * max(abs(v), 1e-3)
    hi = f(df.set_param(params, scene, path, v + eps))
    lo = f(df.set_param(params, scene, path, v - eps))
    return jax.tree.map(lambda a, b: (np.asarray(a, np.float64) - np.asarray(b, np.float64))
                        / (2 * eps), hi, lo)


def adding_doubling(albedo: float, tau: float, g: float = 0.0, *, quad_pts: int = 16):
    """(R, T) of a slab under a uniform (diffuse) sky by adding-doubling (iadpython, a test
    dependency; ``difffog/data/references/slab_adding_doubling.csv`` holds a 64-point table)."""
    import iadpython

    s = iadpython.Sample(a=albedo, b=tau, g=g, n=1.0, n_above=1.0, n_below=1.0,
                         quad_pts=quad_pts)
    ur1, ut1, uru, utu = s.rt()
    return float(uru), float(utu)


SRC = os.path.abspath(os.path.join(os.path.dirname(__file__), "..", "src"))


#: how the default suite asks XLA for its optimization level (conftest.py; read when JAX starts
#: its CPU client)
XLA_OPT_FLAG = "--xla_backend_optimization_level"


def host_devices_env(n: int) -> dict:
    """The environment of a subprocess that runs JAX on ``n`` host (CPU) devices: the CPU
    platform forced (on a GPU machine JAX would otherwise pick the one GPU), and this checkout's
    ``src`` first on the path."""
    # XLA's optimization level as the suite set it (conftest.py), the device count replaced
    keep = [f for f in os.environ.get("XLA_FLAGS", "").split()
            if f.startswith(XLA_OPT_FLAG + "=")]
    flags = " ".join([*keep, f"--xla_force_host_platform_device_count={n}"])
    return dict(os.environ, XLA_FLAGS=flags,
                JAX_PLATFORMS="cpu",
                PYTHONPATH=SRC + os.pathsep + os.environ.get("PYTHONPATH", ""))


class ToyLight(df.AbstractLight):
    """A 'light' for test models that have nothing to solve: always converged."""

    result: jax.Array
    iterations: jax.Array
    error_estimate: jax.Array

    def fluence_at(self, points):
        return jnp.zeros(jnp.shape(points)[:-1])

    def report(self):
        return {"iterations": int(self.iterations)}


def random_face_geometry(rng, shape, D: int):
    """A face's FaceGeometry with random FREE/SURFACE nodes, normals and blocked-segment bits
    (the kernels' comparison tests)."""
    from difffog.forward.sweep._kernel import FaceGeometry

    free = rng.random(shape) > 0.2
    return FaceGeometry(
        free=jnp.asarray(free), surf=jnp.asarray(~free & (rng.random(shape) > 0.5)),
        normal=jnp.asarray(rng.standard_normal(shape + (3,)), jnp.float32),
        blocked=jnp.asarray(rng.integers(0, 256, shape + ((D + 7) // 8,)), jnp.uint8))


def kernels_agree(args, M: int, combos, surfaces: bool, tol: float):
    """The loop and batched face sweeps on ``args`` = (Q, B, tau, bc, geo, consts) for every
    periodic combination in ``combos`` (all in one compiled program), asserted equal to
    ``tol``; returns the loop kernel's results per combination."""
    from difffog.forward.sweep._kernel import _sweep_face_batched, _sweep_face_loop

    @jax.jit
    def both(*a):
        out = []
        for periodic in combos:
            kw = dict(M=M, periodic=periodic, warmup=4 if periodic[0] else 0, surfaces=surfaces)
            out.append((_sweep_face_loop(*a, **kw), _sweep_face_batched(*a, **kw)))
        return out

    results = both(*args)
    for periodic, (a, b) in zip(combos, results):
        for x, y in zip(a, b):
            np.testing.assert_allclose(np.asarray(x), np.asarray(y), rtol=tol, atol=tol,
                                       err_msg=str(periodic))
    return [a for a, _ in results]


def slab_table_reference(albedo, tau, illumination="diffuse", zenith=None, g=0.0):
    """(R_total, T_total) of the shipped adding-doubling slab table's row."""
    from difffog.study import references

    for r in references.slab_table():
        if (r["albedo"] == albedo and r["tau"] == tau and r["g"] == g
                and r["illumination"] == illumination
                and (zenith is None or r["zenith_deg"] == zenith)):
            return r["R_total"], r["T_total"]
    raise KeyError((albedo, tau, g, illumination, zenith))


def assert_light_gradient(solver, scene, lat, seed: int,
                          paths=("fog.scattering", "fog.absorption", "sun.irradiance",
                                 "sky.radiance")):
    """A weighted sum of the light solve's fluence (float64): jax.grad through the implicit
    adjoint against central differences (relative 1e-6) for each parameter path."""
    import pytest

    geom = solver.prepare(scene, lat)
    p0 = df.Params.from_scene(scene, jnp.float64)
    wt = jnp.asarray(np.random.default_rng(seed).random(geom.shape))

    def loss(p):
        return jnp.sum(wt * solver.solve(geom, p).fluence)

    f, g = jax.jit(loss), jax.jit(jax.grad(loss))(p0)
    for path in paths:
        fd = float(central_difference(f, p0, scene, path))
        assert float(df.get_param(g, scene, path)) == pytest.approx(fd, rel=1e-6), path


def image_loss_gradient_matches_fd(model, scene, paths, rel: float = 1e-5, scale: float = 0.9):
    """The gradient of an image loss (squared distance to ``scale`` × the model's own images)
    at the model's float64 parameters against central differences of relative step 1e-5, for
    each parameter path (each derivative nonzero)."""
    import pytest

    p0 = model.params(jnp.float64)
    target = jax.tree.map(lambda a: scale * a, model(p0))

    def loss(p):
        imgs = model(p)
        return sum(jnp.sum((imgs[k] - target[k]) ** 2) for k in imgs)

    g = jax.jit(jax.grad(loss))(p0)
    f = jax.jit(loss)
    for path in paths:
        v = float(df.get_param(p0, scene, path))
        eps = 1e-5 * v
        fd = float(f(df.set_param(p0, scene, path, v + eps))
                   - f(df.set_param(p0, scene, path, v - eps))) / (2 * eps)
        assert fd != 0, path
        assert float(df.get_param(g, scene, path)) == pytest.approx(fd, rel=rel), path


def hg_slab_rt(tau, albedo, g, n_fog, M, L, sun=None, once_M=None, scheme="auto"):
    """(R, T) of a Henyey–Greenstein slab as a camera sees it (float64): the lattice's
    scattered light (its moments) plus the sun's single scattering with the exact phase
    (``study._slab.slab_reflectance``); a sky of 1 without a ``sun`` = (irradiance, zenith).
    ``once_M``: the sun's once-scattered light on that direction set (the slab's shell follows
    it), ``scheme``: the solve's."""
    from difffog.forward.sweep._harmonics import basis
    from difffog.forward.sweep._solver import SweepSolver, source_field
    from difffog.study._slab import slab_problem, slab_reflectance, sun_scatter_terms

    solver = SweepSolver(M=M, max_iterations=4000, tol=1e-9, phase_order=L, once_M=once_M,
                         scheme=scheme)
    scene, lat, margin = slab_problem(tau, albedo, n_fog, max(M, once_M or 0), sun=sun,
                                      sky=0.0 if sun else 1.0, g=g)
    geom = solver.prepare(scene, lat)
    assert (geom.once is not None) == (once_M is not None and sun is not None and L > 0)

    @jax.jit
    def run(p):
        light = solver.solve(geom, p)
        pb = solver.problem(geom, p)
        return light, pb.sigma_t, source_field(pb, light, sun=sun is None)

    light, sigma, q = run(df.Params.from_scene(scene, jnp.float64))
    assert int(light.result) == df.RESULTS.successful
    dens = np.asarray(lat.density)[0, 0]
    ss = None
    if sun:  # the exact single scattering, and the sun's beam as the solver attenuates it
        ss = sun_scatter_terms(light, albedo, tau, g, dens)
    q, slope = np.asarray(q)[0, 0], None
    if geom.linear:  # thick steps take the linear scheme: its slope channels (x, y, z) come last
        q, slope = q[..., :-3], q[..., -1]
    return slab_reflectance(np.asarray(sigma)[0, 0], q, None, margin, lat.h,
                            sky=0.0 if sun else 1.0, sun=sun, basis=basis(L, M),
                            sun_scatter=ss, slope=slope)
