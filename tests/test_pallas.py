"""The Pallas slab step (``forward/sweep/_pallas.py``, ``kernel="pallas"``): on this CPU in
Pallas's interpret mode, against the batched XLA program it stands for (the reference); and,
where JAX's CUDA plugin is installed, its lowering to a Triton kernel."""

import warnings

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from test_native import CASES, _face, _general_form

import difffog as df
from difffog import Params, SweepSolver, load_scene, voxelize
from difffog.forward.sweep import _kernel as K


def _sweep(args, kernel, **kw):
    return jax.jit(lambda *a: K.sweep_face(*a, kernel=kernel, **kw))(*args)


@pytest.mark.parametrize("dtype", ["float64", "float32"])
@pytest.mark.parametrize("M,surfaces,periodic,vol", CASES[:4])
def test_pallas_face_sweep_equals_the_batched_program(M, surfaces, periodic, vol, dtype, x64):
    """Λ, E and the exit radiance of one face sweep: open and periodic sides (the shift's
    fill and wrap), surfaces (blocking bits, normals, the irradiance), no fluence; a plane
    that is not a multiple of the kernel's (16, 32) tile (the masked stores).  The exit
    radiance is the same arithmetic (equal to rounding); Λ and E add the direction blocks'
    partial sums, a different order of the same terms."""
    dt = jnp.dtype(dtype)
    args = _face(M, (11, 9, 7), dt)
    kw = dict(M=M, periodic=periodic, warmup=2 * M + 1, surfaces=surfaces, fluence=vol[1])
    ref = _sweep(args, "batched", **kw)
    got = _sweep(args, "pallas", **kw)
    rtol = 1e-13 if dtype == "float64" else 1e-6
    for r, g in zip(ref, got):
        assert g.shape == r.shape and g.dtype == r.dtype
        np.testing.assert_allclose(np.asarray(g), np.asarray(r), rtol=rtol,
                                   atol=rtol * float(jnp.max(jnp.abs(r))))
    lam, irr, exit_ = got
    assert float(jnp.max(exit_)) > 0
    assert float(jnp.max(lam if vol[1] else irr)) > 0  # something was summed
    if not vol[1]:
        assert float(jnp.max(jnp.abs(lam))) == 0.0


# (True, 1, True) has all three forms at once; the other two alone run with -m slow since stop
# 80 (~10 s each there: the default suite's 12-minute budget on 2 cores)
@pytest.mark.parametrize("linear,order,sun", [
    pytest.param(True, 0, False, marks=pytest.mark.slow),
    pytest.param(False, 1, True, marks=pytest.mark.slow), (True, 1, True)])
def test_pallas_face_sweep_with_moments_and_slopes(linear, order, sun, x64):
    """The anisotropic and linear-source forms: a source per direction from the moments'
    channels (``order``: the δ-M order's basis) and the sun's phase channel, the slope
    channels of the linear scheme (its three-part node update), the moments of Λ; open and
    periodic sides, with surfaces, float64."""
    from helpers import random_face_geometry

    M, shape = 2, (9, 8, 10)
    D = (2 * M + 1) ** 2
    rng = np.random.default_rng(3)
    Q, consts = _general_form(M, shape, jnp.float64, rng, linear, order, sun, face=0)
    args = (Q, jnp.asarray(rng.random(shape)), jnp.asarray(1.5 * rng.random(shape)),
            jnp.asarray(rng.random(D)), random_face_geometry(rng, shape, D), consts)
    for periodic in [(False, False, False), (True, True, False)]:
        kw = dict(M=M, periodic=periodic, warmup=4 if periodic[0] else 0, surfaces=True)
        ref, got = _sweep(args, "batched", **kw), _sweep(args, "pallas", **kw)
        for r, g in zip(ref, got):
            assert g.shape == r.shape
            np.testing.assert_allclose(np.asarray(g), np.asarray(r), rtol=1e-13,
                                       atol=1e-13 * float(jnp.max(jnp.abs(r))))
        if order:
            assert ref[0].shape == shape + ((order + 1) ** 2,)
            assert float(jnp.max(jnp.abs(got[0][..., 1:]))) > 0  # the moments were summed


def test_pallas_sweep_derivatives_are_the_batched_programs(x64):
    """``sweep_face``'s JVP with kernel="pallas" is the batched program's (values from the
    kernel, tangents from XLA): equal to the batched kernel's JVP."""
    args = _face(2, (7, 6, 5), jnp.dtype("float64"))
    kw = dict(M=2, periodic=(False, False, False), warmup=5, surfaces=True)
    dq = jnp.asarray(np.random.default_rng(4).random(args[0].shape))

    def jvp(kernel):
        f = lambda q: K.sweep_face(q, *args[1:], kernel=kernel, **kw)[0]  # noqa: E731
        return jax.jit(lambda q, t: jax.jvp(f, (q,), (t,)))(args[0], dq)

    (va, ta), (vb, tb) = jvp("batched"), jvp("pallas")
    np.testing.assert_allclose(np.asarray(vb), np.asarray(va), rtol=1e-13)
    np.testing.assert_allclose(np.asarray(tb), np.asarray(ta), rtol=1e-13)
    assert float(jnp.max(jnp.abs(ta))) > 0


def test_solver_with_the_pallas_kernel_equals_the_batched_one(x64):
    """A whole light solve (fog-balls, float64, GMRES to 1e-11) with kernel="pallas" gives the
    batched kernel's light field, in the same number of iterations; asked for on a CPU, where
    Pallas only interprets, the solver says so in one line (and not for "batched")."""
    scene = load_scene("fog-balls", ["shape.walls.thickness=0.1"])
    out = {}
    for k in ("batched", "pallas"):
        with warnings.catch_warnings(record=True) as seen:
            warnings.simplefilter("always")
            solver = SweepSolver(M=2, tol=1e-11, max_iterations=400, kernel=k)
        said = [str(w.message) for w in seen if "interpret mode" in str(w.message)]
        assert len(said) == (k == "pallas" and jax.default_backend() == "cpu"), said
        assert all("\n" not in m and 'kernel="auto"' in m for m in said)
        geom = solver.prepare(scene, voxelize(scene, 10, 2))
        light = jax.jit(solver.solve)(geom, Params.from_scene(scene, jnp.float64))
        assert int(light.result) == df.RESULTS.successful
        out[k] = light
    a, b = out["batched"], out["pallas"]
    assert int(a.iterations) == int(b.iterations)
    for f in ("fluence", "radiosity"):
        x, y = np.asarray(getattr(a, f)), np.asarray(getattr(b, f))
        assert x.max() > 0
        np.testing.assert_allclose(y, x, rtol=1e-12, atol=1e-14 * x.max())


def _triton_plugin() -> bool:
    try:
        from jax._src.lib import gpu_triton
    except ImportError:
        return False
    return hasattr(gpu_triton, "TritonKernel")


# slow: it needs JAX's CUDA plugin (Pallas's Triton lowering), which CI's CPU machine has not:
# run by hand where it is installed (the default suite skips nothing)
@pytest.mark.slow
@pytest.mark.skipif(not _triton_plugin(), reason="JAX's CUDA plugin (Pallas's Triton lowering) "
                    "is not installed here")
@pytest.mark.parametrize("M,nu,nv,surfaces,periodic,nj,nk,linear", [
    (5, 140, 140, True, (False, False), 0, 0, False),
    (3, 72, 80, False, (True, False), 0, 0, False),
    (3, 40, 40, True, (True, True), 16, 15, True)])  # δ-M order 3, the sun's phase, slopes
def test_pallas_kernel_lowers_to_triton_for_cuda(M, nu, nv, surfaces, periodic, nj, nk, linear):
    """The compiled (not interpreted) kernel lowers for CUDA to one Triton kernel call (checks
    what Pallas's Triton lowering checks: block shapes, the ops it supports); compiling that
    to PTX needs a GPU."""
    from jax import export

    from difffog.forward.sweep import _pallas

    S = jax.ShapeDtypeStruct
    D = (2 * M + 1) ** 2
    f32 = jnp.float32
    plane = S((M, nu, nv), f32)
    args = (S((D, 2), jnp.int32), S((D,), f32), S((D,), f32), S((D,), f32), S((D, 3), f32),
            S((D, max(nj, 1)), f32), S((D, 3), f32), S((M, D, nu, nv), f32),
            S((1 + nj + 3 * linear, M, nu, nv), f32), plane, plane, S((M, nu, nv), jnp.uint8),
            S((3, M, nu, nv), f32), S((M, (D + 7) // 8, nu, nv), jnp.uint8))
    call = _pallas._call(M, nu, nv, "float32", *periodic, surfaces, True, False, nj, nk, linear)
    target = "__gpu$xla.gpu.triton"
    exp = export.export(jax.jit(call), platforms=["cuda"],
                        disabled_checks=[export.DisabledSafetyCheck.custom_call(target)])(*args)
    assert exp.mlir_module().count(f"stablehlo.custom_call @{target}") == 1
