"""The linear-source scheme (``SweepSolver(scheme="linear")``, issue 14): the source varies
linearly along each lattice segment, which gives the sweep the true diffusion limit in
optically thick fog.

Independent truths: the exact solution of dR/dτ = Q(τ) − R with a linear Q (the node update),
exact conservation (a purely scattering slab returns all it receives, whatever its depth),
adding-doubling for slabs (the table shipped with difffog, ``difffog.study.references``),
finite differences for gradients.
"""

import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import difffog as df
from difffog import Params, SweepSolver
from difffog.forward.sweep._solver import _sources, _sweep_all
from difffog.geometry._directions import FACE_AXES
from difffog.study._slab import slab_problem, slab_reflectance
from helpers import (assert_light_gradient, kernels_agree, random_face_geometry,
                     slab_table_reference)


@pytest.mark.parametrize("tau", [1e-4, 0.3, 0.7, 3.0, 40.0])
def test_linear_node_is_the_exact_solution(tau, x64):
    """Both half-segments of a node with the source q − s/2 → q → q + s/2: the radiance at the
    node, leaving it, and its mean over the segment, against a fine numerical integration of
    dR/du = Q(u) − R (u: optical depth)."""
    from difffog._numerics import linear_source_terms
    from difffog.forward.sweep._kernel import _linear_node

    r_in, q, s = 0.7, 0.4, 0.3
    phi, psi, _, _ = linear_source_terms(jnp.float64(tau))
    em = jnp.expm1(-jnp.float64(tau))
    node, out, avg = (float(x) for x in _linear_node(r_in, q, s, em, 0.5 * tau * psi, phi, psi))

    from scipy.integrate import quad

    def Q(u):
        return q - s / 2 + s * u / (2 * tau)

    def R(u):  # r_in e^{−u} + ∫₀^u e^{−(u−v)} Q(v) dv
        return r_in * math.exp(-u) + quad(lambda v: math.exp(-(u - v)) * Q(v), 0.0, u,
                                          epsabs=1e-14, epsrel=1e-12)[0]

    mean = quad(R, 0.0, 2 * tau, epsabs=1e-13, epsrel=1e-10)[0] / (2 * tau)
    assert node == pytest.approx(R(tau), rel=1e-9, abs=1e-12)
    assert out == pytest.approx(R(2 * tau), rel=1e-9, abs=1e-12)
    assert avg == pytest.approx(mean, rel=1e-8)


# slow: the default suite's 12-minute budget on 2 cores (stop 56)
@pytest.mark.slow
def test_loop_kernel_matches_batched_kernel_with_slopes():
    """The CPU's loop kernel and the GPU's batched kernel with the slope channels (and with
    surfaces, blocked segments, open and periodic sides)."""
    from difffog.forward.sweep._kernel import _sweep_face_batched, face_consts
    from difffog.geometry._directions import direction_set

    M, shape = 2, (9, 8, 10)
    D = (2 * M + 1) ** 2
    rng = np.random.default_rng(3)
    f32 = lambda a: jnp.asarray(a, jnp.float32)  # noqa: E731
    Q = f32(np.concatenate([rng.random(shape + (1,)), 0.2 * rng.standard_normal(shape + (3,))],
                           axis=-1))
    B, tau = f32(rng.random(shape)), f32(1.5 * rng.random(shape))
    bc = f32(rng.random(D))
    geo = random_face_geometry(rng, shape, D)
    consts = face_consts(direction_set(M), 0, linear=True)
    combos = [(False, False, False), (True, True, False), (False, True, True)]
    loop = kernels_agree((Q, B, tau, bc, geo, consts), M, combos, True, 2e-5)
    # the slopes matter: without them the sweep differs
    step = jax.jit(lambda *a: _sweep_face_batched(*a, M=M, periodic=combos[0], warmup=0,
                                                  surfaces=True))(
        Q[..., 0], B, tau, bc, geo, face_consts(direction_set(M), 0))
    assert float(jnp.max(jnp.abs(step[0] - loop[0][0]))) > 1e-3


def _solve(scene, lat, solver):
    geom = solver.prepare(scene, lat)
    p = Params.from_scene(scene, jnp.float64)
    return geom, p, jax.jit(solver.solve)(geom, p)


@pytest.mark.parametrize("scheme", [pytest.param("step", marks=pytest.mark.slow), "linear",
                                    pytest.param("substep", marks=pytest.mark.slow)])
def test_conservative_slab_returns_what_it_receives(scheme, x64):
    """A purely scattering slab neither creates nor destroys light, whatever its optical depth:
    the sky light leaving through the top and the bottom (the sweep's own exit radiance) sums
    to the same value at τ = 1, 16 and 64 (4 mean free paths per node)."""
    solver = SweepSolver(M=2, max_iterations=4000, tol=1e-11, scheme=scheme)
    scene, lat, _ = slab_problem(1.0, 1.0, 16, 2)
    geom = solver.prepare(scene, lat)

    @jax.jit
    def leaving(p):  # Σ_d w_d L̂_z R_exit over the ±z sweeps (one compiled program)
        light = solver.solve(geom, p)
        pb = solver.problem(geom, p)
        q, b = _sources((light.fluence, jnp.zeros_like(light.fluence)), pb)
        _, exits = _sweep_all(q, b, pb, return_exits=True)
        out = 0.0
        for f, (axis, _) in enumerate(FACE_AXES):
            if axis == 2:
                c = geom.consts[f]
                flux = (c.weight[None, :, None, None] * c.unit[None, :, 2, None, None]
                        * exits[f])
                out = out + flux.sum(1).mean()
        return out, light.result

    totals = []
    for tau in (1.0, 16.0, 64.0):
        out, result = leaving(Params.from_scene(slab_problem(tau, 1.0, 16, 2)[0], jnp.float64))
        assert int(result) == df.RESULTS.successful
        totals.append(float(out))
    assert totals[1] == pytest.approx(totals[0], rel=1e-7)
    assert totals[2] == pytest.approx(totals[0], rel=1e-7)


def _slab(tau, albedo, scheme, sun=None, n_fog=32, sky_quadrature=(0, 0)):
    scene, lat, margin = slab_problem(tau, albedo, n_fog, 2, sun=sun, sky=0.0 if sun else 1.0)
    solver = SweepSolver(M=2, max_iterations=4000, tol=1e-9, scheme=scheme,
                         sky_quadrature=sky_quadrature)
    geom, p, light = _solve(scene, lat, solver)
    assert int(light.result) == df.RESULTS.successful
    sigma = np.asarray(solver.problem(geom, p).sigma_t)[0, 0]
    slope = None if light.source_slope is None else np.asarray(light.source_slope)[0, 0, :, 2]
    return slab_reflectance(sigma, np.asarray(light.source)[0, 0], None, margin, lat.h,
                            sky=0.0 if sun else 1.0, sun=sun, slope=slope)


#: measured at 32 fog nodes, M = 2, against adding-doubling (relative R / T errors in %), with
#: a margin; the step scheme's for comparison: docs/validation.md
THICK_BOUNDS = {  # (albedo, tau, zenith or None = diffuse sky): (|R err|, |T err|)
    (0.99, 16.0, None): (0.012, 0.05),   # linear −0.6 / +3.2   (step −1.4 / +23.5)
    (0.999, 64.0, None): (0.025, 0.30),  # linear −1.1 / +20    (step −4.0 / ×5.5)
    (0.99, 16.0, 0.0): (0.03, 0.025),    # linear +1.6 / +0.7   (step +0.6 / +17)
}


@pytest.mark.parametrize("albedo,tau,zenith", [
    pytest.param(*k, marks=pytest.mark.slow) if k[2] is not None else k for k in THICK_BOUNDS])
def test_thick_slab_against_adding_doubling(albedo, tau, zenith, x64):
    sun = None if zenith is None else (1.0, zenith)
    R, T = _slab(tau, albedo, "linear", sun=sun)
    R_ref, T_ref = slab_table_reference(albedo, tau, "diffuse" if sun is None else "collimated",
                                        zenith)
    eR, eT = THICK_BOUNDS[(albedo, tau, zenith)]
    assert abs(R / R_ref - 1) < eR, (R, R_ref)
    assert abs(T / T_ref - 1) < eT, (T, T_ref)


@pytest.mark.slow
def test_thin_slab_is_the_step_scheme(x64):
    """Where a lattice step is optically thin the two schemes agree (τ = 1, 32 nodes: the
    source's slope changes a segment's radiance by O(τ_seg²))."""
    a = _slab(1.0, 0.9, "linear")
    b = _slab(1.0, 0.9, "step")
    assert a == pytest.approx(b, rel=1e-3)


# default again since stop 83 (the suite compiles XLA's code at -O0: 15 s here): the clouds'
# scheme's gradients against differences on every CI run
def test_gradients_match_finite_differences(x64):
    """Image-free loss of a thick slab under sun and a first-collision sky (the slopes of
    both uncollided beams and of the collided light), in float64: jax.grad through the
    implicit adjoint against central differences."""
    scene, lat, _ = slab_problem(16.0, 0.95, 12, 2, sun=(1.5, 30.0), sky=0.3)
    solver = SweepSolver(M=2, max_iterations=2000, tol=1e-12, adjoint_rtol=1e-11,
                         scheme="linear", sky_quadrature=(4, 8))
    assert_light_gradient(solver, scene, lat, seed=5)


def test_scheme_is_checked_and_reaches_the_command_line():
    with pytest.raises(df.SceneError, match="scheme must be one of auto, step, linear, substep"):
        SweepSolver(scheme="cubic")
    from difffog.cli._main import build_parser, model_settings

    args = build_parser().parse_args(["render", "fog-balls", "--scheme", "linear"])
    assert model_settings(args, "sweep", accuracy="draft")["scheme"] == "linear"
    with pytest.raises(df.DifffogError, match="--scheme does not apply to --solver splat"):
        model_settings(args, "splat", accuracy=None)


def test_auto_scheme_takes_linear_where_a_step_is_thick():
    """scheme="auto" (the default): "linear" where one lattice step spans more than
    ``LINEAR_STEP_DEPTH`` mean free paths at the scene's values (δ-M scaled), and at any step
    depth in fog at least ``LINEAR_FOG_SIZE`` mean free paths across (fog-balls' domain at
    N = 24, M = 2: 12 mean free paths across per unit of step depth; at N = 4 under 5 up to a
    step depth of 1), else "step"; the model's settings name the scheme it runs."""
    from difffog.forward.sweep._solver import LINEAR_FOG_SIZE, LINEAR_STEP_DEPTH
    from difffog.geometry._lattice import voxelize

    scene = df.load_scene("fog-balls")
    solver = SweepSolver(M=2)
    assert solver.scheme == "auto"
    lat = voxelize(scene, 24, 2, margin=3)
    bare = scene.replace(shapes=())  # no walls thinner than a coarse lattice's voxel
    coarse = voxelize(bare, 4, 2, margin=3)
    depth_per_unit = lat.max_segment_optical_depth(1.0, 0.0)  # per unit σ_t
    extent = max(b - a for a, b in zip(scene.domain.min, scene.domain.max))
    at_size = LINEAR_FOG_SIZE / extent * depth_per_unit  # the step depth of fog 5 across
    assert at_size < 0.5 * LINEAR_STEP_DEPTH
    # thin steps: the fog's size decides; thick ones: linear whatever the size
    for depth, want in ((0.9 * at_size, "step"), (1.1 * at_size, "linear"),
                        (0.9 * LINEAR_STEP_DEPTH, "linear"), (1.1 * LINEAR_STEP_DEPTH, "linear")):
        ext = depth / depth_per_unit
        thick = scene.replace(fog=df.Fog(scattering=0.8 * ext, absorption=0.2 * ext))
        assert solver.resolved_scheme(thick, lat) == want, depth
        # a forward-scattering fog is judged after δ-scaling: ζ(1 − g) with g = 0.5
        hg = thick.replace(fog=df.Fog(scattering=1.6 * ext, absorption=0.2 * ext,
                                      phase="henyey-greenstein", g=0.5))
        assert SweepSolver(M=2, phase_order=0).resolved_scheme(hg, lat) == want, depth
    # the same step depths on a coarse lattice, fog of fewer mean free paths across: only
    # LINEAR_STEP_DEPTH counts
    per_coarse = coarse.max_segment_optical_depth(1.0, 0.0)
    for depth, want in ((0.9 * LINEAR_STEP_DEPTH, "step"), (1.1 * LINEAR_STEP_DEPTH, "linear")):
        thin = bare.replace(fog=df.Fog(scattering=depth / per_coarse, absorption=0.0))
        assert solver.resolved_scheme(thin, coarse) == want, depth
    assert SweepSolver(M=2, scheme="step").resolved_scheme(thick, lat) == "step"
    m = df.forward_model(scene, "sweep", accuracy="draft")
    assert m.settings()["solver_options"]["scheme"] == "step"
    assert not m.geometry.linear
