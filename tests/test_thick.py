"""Optically thick fog (issue 14): the sweep conserves energy whatever a step's optical depth,
and a thick conservative fog reflects like a semi-infinite conservative medium.

Independent truths: adding-doubling (iadpython) for slabs, Chandrasekhar's H-function for the
semi-infinite medium, and for issue 14's thick cube its own image by a float64 Monte Carlo
random walk (``THICK_CUBE_REFERENCE``, ``benchmarks/thick_cube_mc.py``; checked against
Mitsuba 3).  Figures in docs/validation.md.
"""

import math
import re
import warnings

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import difffog as df
from difffog import Params, SweepSolver
from difffog.study._semi_infinite import THICK_CUBE_REFERENCE, semi_infinite_radiance
from difffog.study._semi_infinite import thick_cube as _thick_cube
from difffog.study._slab import slab_absorption, slab_exits, slab_problem, slab_reflectance
from helpers import adding_doubling, assert_light_gradient, slab_table_reference

# the step scheme's balance, whose formal solution (slab_reflectance) matches its boundary cells;
# the linear scheme's conservation is tested by its exit flux (test_linear_scheme.py)
SLAB_SOLVER = SweepSolver(M=2, max_iterations=4000, tol=1e-9, scheme="step")
_solve = jax.jit(lambda geom, p: SLAB_SOLVER.solve(geom, p))

#: measured at 32 fog nodes, M = 2 (relative R error, R + T + A − 1), with a margin: the energy
#: balance holds to 1% at any step depth; R is still low where one node spans several mean free
#: paths (the first-order step scheme's thick limit: τ = 64 is a step depth of 4 at M = 2)
THICK_SLABS = {  # (albedo, tau): (|R err|, |R + T + A - 1|)
    (0.9, 16.0): (0.06, 0.004), (0.99, 16.0): (0.02, 0.003), (0.999, 16.0): (0.015, 0.002),
    (0.9, 64.0): (0.35, 0.005), (0.99, 64.0): (0.13, 0.012), (0.999, 64.0): (0.05, 0.005),
}


@pytest.mark.parametrize("albedo,tau", list(THICK_SLABS))
def test_thick_slab_conserves_energy(albedo, tau, x64):
    """R + T + A = 1 (A from the solve's own fluence) and R against adding-doubling."""
    n_fog, M = 32, 2
    scene, lat, margin = slab_problem(tau, albedo, n_fog, M, sky=1.0)
    geom = SLAB_SOLVER.prepare(scene, lat)
    p = Params.from_scene(scene, jnp.float64)
    light = _solve(geom, p)
    assert int(light.result) == df.RESULTS.successful
    sigma = np.asarray(SLAB_SOLVER.problem(geom, p).sigma_t)[0, 0]
    slope = None if light.source_slope is None else np.asarray(light.source_slope)[0, 0, :, 2]
    R, T = slab_reflectance(sigma, np.asarray(light.source)[0, 0], None, margin, lat.h, sky=1.0,
                            slope=slope)
    A = slab_absorption(sigma, light, albedo, lat.h, sky=1.0)
    r_err, balance = THICK_SLABS[(albedo, tau)]
    assert abs(R + T + A - 1) <= balance, (R, T, A)
    R_ad, _ = adding_doubling(albedo, tau)
    assert abs(R / R_ad - 1) <= r_err, (R, R_ad)


def _lattice_balance(albedo, tau, zenith, n_fog=16, M=2, first_collision="beam"):
    """(R, T, R + T + A − 1) of a sunlit slab, R and T as the lattice lets light out."""
    scene, lat, margin = slab_problem(tau, albedo, n_fog, M, sky=0.0, sun=(1.0, zenith),
                                      margin=2 * M + 1)
    solver = SweepSolver(M=M, max_iterations=4000, tol=1e-10, terms="all",
                         first_collision=first_collision)
    geom = solver.prepare(scene, lat)
    p = Params.from_scene(scene, jnp.float64)
    light = jax.jit(solver.solve)(geom, p)
    assert int(light.result) == df.RESULTS.successful
    R, T = slab_exits(solver, geom, p, light, margin, sky=0.0, sun=(1.0, zenith))
    sigma = np.asarray(solver.problem(geom, p).sigma_t)[0, 0]
    A = slab_absorption(sigma, light, albedo, lat.h, sky=0.0, sun=(1.0, zenith))
    return R, T, R + T + A - 1


def test_the_lattice_returns_what_a_sunlit_slab_receives(x64):
    """Where every lattice step is optically thin (τ = 2 over 16 nodes, a sun at 60°), the
    light the lattice lets out (its own exit flux, ``slab_exits``) and the fog's absorption
    add up to the sun's within the issue's 0.5% (measured +0.20%; +0.73% over 8 nodes: the
    box filter's error at the fog's faces, below), and R and T agree with adding-doubling
    (measured R −0.4%, T +2.1%)."""
    R, T, balance = _lattice_balance(0.9, 2.0, 60.0)
    assert abs(balance) < 0.005
    R_ref, T_ref = slab_table_reference(0.9, 2.0, "collimated", 60.0)
    assert R == pytest.approx(R_ref, rel=0.01) and T == pytest.approx(T_ref, rel=0.04)


# slow: the default suite's 12-minute budget on 2 cores (stop 56); the deposit is not a default
@pytest.mark.slow
def test_the_deposit_first_collision_returns_what_a_thick_sunlit_slab_receives(x64):
    """``first_collision="deposit"``: the first collision scatters the sun's box-filtered
    deposit, what the beam loses.  τ = 16 over 8 nodes (2 mean free paths per node, a sun at
    60°, albedo 0.999): R + T + A − 1 measured −2.0% (the default "beam": +18.5%, as on τ = 64
    over 32 nodes); what is left is the collided light's exchange at the fog's face, whose
    per-axis σ̄ the node's re-emission does not follow (docs/validation.md).  On the thin
    slab above it is −0.04% (beam +0.20%)."""
    _, _, balance = _lattice_balance(0.999, 16.0, 60.0, n_fog=8, first_collision="deposit")
    assert abs(balance) < 0.03
    _, _, thin = _lattice_balance(0.9, 2.0, 60.0, first_collision="deposit")
    assert abs(thin) < 0.002


# slow: the default suite's 12-minute budget on 2 cores (stop 56); the deposit is not a default
@pytest.mark.slow
def test_a_gradient_through_the_deposit_first_collision_matches_finite_differences(x64):
    """The deposit average (``_solver._deposit_average``: box filters of σ_t·beam over box
    filters of σ_t) is differentiable: a loss of the light solve of a slab with thick steps,
    a sun and a first-collision sky, in float64, against central differences in ζ, γ, the
    sun's irradiance and the sky's radiance."""
    scene, lat, _ = slab_problem(8.0, 0.95, 8, 2, sun=(1.5, 30.0), sky=0.3)
    solver = SweepSolver(M=2, max_iterations=2000, tol=1e-12, adjoint_rtol=1e-11,
                         scheme="step", sky_quadrature=(4, 8), first_collision="deposit")
    assert_light_gradient(solver, scene, lat, seed=7)


def test_first_collision_is_checked_and_reaches_the_command_line():
    with pytest.raises(df.SceneError, match="first_collision must be one of beam, deposit"):
        SweepSolver(first_collision="node")
    from difffog.cli._main import build_parser, model_settings

    args = build_parser().parse_args(["render", "fog-balls", "--first-collision", "deposit"])
    assert model_settings(args, "sweep", accuracy="draft")["first_collision"] == "deposit"
    with pytest.raises(df.DifffogError, match="--first-collision does not apply to --solver"):
        model_settings(args, "splat", accuracy=None)


@pytest.mark.slow
@pytest.mark.xfail(strict=True, reason="open (issue 14): the box-filtered segment depth "
                   "creates light where a sunlit node spans mean free paths (docs/validation.md)")
def test_the_lattice_conserves_a_sunlit_slab_on_thick_steps(x64):
    """The same on τ = 64 over 32 nodes (2 mean free paths per node): R + T + A − 1 is
    +18.7% at 60° (and +5.6% at 0°).  The light solve's σ̄ averages σ_t over each node's
    M-plane segment along every face's axis (``segment_depth``), while the sun's beam loses
    light at each node's own σ_t: the nodes at the sunlit face re-emit more than the beam
    loses there.  ``first_collision="deposit"`` brings it to −1.8% (−2.5% at 0°; the test
    above); without the box filter the balance is exact (0.000%), but either way issue 14's
    thick cube comes out 9–29% too dark, so the default keeps the beam."""
    _, _, balance = _lattice_balance(0.999, 64.0, 60.0, n_fog=32)
    assert abs(balance) < 0.005


def test_semi_infinite_value():
    # H(1) = 2.9078 (Chandrasekhar's table); the limit the thick cube's image tends to
    assert semi_infinite_radiance(4 * math.pi, 1.0, 1.0, 0.0) == pytest.approx(
        0.5 * 2.9078 ** 2, rel=2e-3)


def _mean_image(zeta: float, N: int, scheme: str = "auto") -> float:
    """The cube's image mean; ``render`` must say the steps are thick, and may say the linear
    scheme's fixed point dipped below 0 (clipped: ζ = 1000 / 10000 at N = 32, −12% / −28% of
    the peak), nothing else."""
    m = df.forward_model(_thick_cube(zeta), "sweep", accuracy=None, resolution=N, M=2,
                         tol=1e-4, max_iterations=2000, supersample=1, scheme=scheme)
    with warnings.catch_warnings(record=True) as said:
        warnings.simplefilter("always")
        out = df.render(m)  # raises unless the light solve converged
    said = [(w.category, str(w.message)) for w in said]
    assert any(c is df.ThickStepWarning and re.search(r"optically thick .* resolution >= \d+", t)
               for c, t in said), said
    assert all(c is df.ThickStepWarning and ("optically thick" in t or "dipped below 0" in t)
               for c, t in said), said
    return float(out.images["top"].mean())


def test_thick_conservative_fog_is_bright_not_black_or_blown():
    """ζ = 1000 (a step depth of ~180 at N = 12): 0 with 0.1's scheme, and 10× too bright at
    ζ = 100; now (the linear scheme, which the default takes there, and the cameras' sun along
    its own profile) within 3% of the cube's own image (an independent float64 Monte Carlo,
    0.7668 ± 0.0016, within 1% of the semi-infinite value) at this coarse lattice (measured
    +2.0%)."""
    assert _mean_image(1000.0, 12) == pytest.approx(THICK_CUBE_REFERENCE[1000.0][0], rel=0.03)


_CUBE_AT_100_XFAIL = pytest.mark.xfail(strict=True, reason=(
    "issue 14 open: at ζ = 100 the default reads the cube +5.1% over its own image at N = 32 "
    "(a step depth of 6), just over the issue's 5%; first_collision=\"deposit\" reads it "
    "−2.8% there but −13% at ζ = 1000"))


@pytest.mark.slow
@pytest.mark.parametrize("zeta", [pytest.param(100.0, marks=_CUBE_AT_100_XFAIL), 1000.0,
                                  10000.0])
def test_thick_cube_reads_as_an_independent_monte_carlo(zeta):
    """N = 32, the default scheme (linear at these step depths of 6, 62 and 625): within the
    issue's 5% of the cube's own image by a float64 Monte Carlo (``THICK_CUBE_REFERENCE``;
    measured +5.1%, +3.5%, +1.7%).  Until stop 47 this test held the semi-infinite value
    (0.773) within 3% (−1.2%, +2.7%, +1.3%), which the cube itself misses by 6% at ζ = 100:
    the default's −1.2% there was light it creates (a thick step's sunlit face re-emits more
    than its beam loses) meeting light the finite cube loses."""
    assert _mean_image(zeta, 32) == pytest.approx(THICK_CUBE_REFERENCE[zeta][0], rel=0.05)


@pytest.mark.slow
def test_the_thick_cube_converges_to_the_independent_monte_carlo():
    """ζ = 100: the default's error against the cube's own image falls as the lattice is
    refined and is within 2% at N = 64 (measured +5.1% at N = 32, +1.5% at N = 64; 0.727 at
    N = 128 against the Monte Carlo's 0.7271 ± 0.0007)."""
    ref = THICK_CUBE_REFERENCE[100.0][0]
    e32, e64 = (abs(_mean_image(100.0, n) / ref - 1.0) for n in (32, 64))
    assert e64 < 0.5 * e32 and e64 < 0.02


def test_side_slopes_blend_one_linear_field_and_stop_where_the_fog_does():
    """The cameras' slope channels: in uniform fog both sides carry the node's slope (so the
    blend of the nodes' extrapolations is the linear field between them); towards a neighbour
    with no fog the node's slope is dropped (its cell's mean holds there, as at a sharp face),
    continuously as the neighbour's density goes to 0."""
    from difffog.forward.sweep._model import side_slopes

    rng = np.random.default_rng(3)
    slope = jnp.asarray(rng.standard_normal((4, 3, 5, 3)))
    sig = jnp.full((4, 3, 5), 2.0)
    both = np.asarray(side_slopes(slope, sig, False))
    np.testing.assert_array_equal(both[..., :3], slope)
    np.testing.assert_array_equal(both[..., 3:], slope)
    for top in (0.0, 1e-9, 1.0, 3.0):  # the plane above z index 2 holds top·σ
        s2 = sig.at[:, :, 3:].set(2.0 * top)
        out = np.asarray(side_slopes(slope, s2, False))
        np.testing.assert_allclose(out[:, :, 2, 2], np.asarray(slope)[:, :, 2, 2] * min(top, 1.0))
        np.testing.assert_array_equal(out[:, :, 2, 5], np.asarray(slope)[:, :, 2, 2])
    # periodic x wraps: the last x plane's upper neighbour is the first
    s3 = sig.at[0].set(0.0)
    out = np.asarray(side_slopes(slope, s3, True))
    assert np.all(out[-1, ..., 0] == 0.0) and np.all(out[1, ..., 3] == 0.0)
    np.testing.assert_array_equal(np.asarray(side_slopes(slope, s3, False))[-1, ..., 0],
                                  np.asarray(slope)[-1, ..., 0])


# slow: the default suite's 12-minute budget on 2 cores (stop 56)
@pytest.mark.slow
def test_a_density_grid_falling_to_zero_reflects_like_the_fogs_sharp_face():
    """A half-space whose density varies only with depth reflects as the uniform one: the
    thick cube's fog as a density grid of ones that drops to 0 above z = 1 (trilinear: a ramp
    over one spacing, as a cloud's top) against the semi-infinite value, which the same fog
    ending at a sharp face meets (the test above).  ζ = 1000, N = 12 (a step depth of ~180): the grid was
    +19.7% before the cameras' slopes stopped where the fog does, the face +3.4%; now the grid
    +0.1% (measured; ``benchmarks/thick_top.py`` has all three)."""
    import sys
    from pathlib import Path

    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))
    from thick_top import VARIANTS, scene

    sc, n = scene(1000.0, 12, VARIANTS[2])
    m = df.forward_model(sc, "sweep", accuracy=None, resolution=n, M=2, tol=1e-4,
                         max_iterations=2000, supersample=1)
    with pytest.warns(df.ThickStepWarning):
        grid = float(df.render(m).images["top"].mean())
    assert grid == pytest.approx(THICK_CUBE_REFERENCE[1000.0][0], rel=0.03)


# -- the diffusion preconditioner (issue 14, part 2) ------------------------------------------

def _cube_light(tau, a, N, precondition, dtype=jnp.float32, tol=1e-4):
    scene = _thick_cube(1.0).replace(fog=df.Fog(scattering=a * tau, absorption=(1 - a) * tau))
    lat = df.voxelize(scene, N, 2)
    s = SweepSolver(M=2, tol=tol, max_iterations=2000, precondition=precondition)
    g = s.prepare(scene, lat)
    return s, g, jax.jit(s.solve)(g, Params.from_scene(scene, dtype))


@pytest.mark.slow
def test_diffusion_preconditioner_same_light_in_fewer_steps():
    """Thick nearly conservative fog (τ = 100, albedo 0.9999) at N = 24: the preconditioned
    GMRES reaches the same light (flexible GMRES: the residual is exact whatever the inner
    diffusion solve returns) in fewer applications of K (measured 32 → 24)."""
    _, _, plain = _cube_light(100.0, 0.9999, 24, "none")
    _, _, dsa = _cube_light(100.0, 0.9999, 24, "diffusion")
    for light in (plain, dsa):
        assert int(light.result) == df.RESULTS.successful
    a, b = np.asarray(plain.fluence), np.asarray(dsa.fluence)
    assert np.max(np.abs(a - b)) <= 1e-3 * np.max(a)
    assert int(dsa.iterations) < int(plain.iterations) - 4, (dsa.iterations, plain.iterations)


def test_diffusion_preconditioner_keeps_the_furnace_exact(x64):
    """Closed box, emission 1, walls albedo 0.5, purely scattering fog (ζ = 20): the mean
    radiance Λ/4π is exactly 1/(1 − 0.5) = 2 in the fog, with the preconditioner too."""
    scene = df.load_scene("furnace", ["fog.scattering=20", "fog.absorption=0",
                                      "shape.walls.albedo=0.5", "shape.walls.thickness=0.15"])
    lat = df.voxelize(scene, 8, 2, margin=0)
    s = SweepSolver(M=2, tol=1e-9, max_iterations=400, precondition="diffusion")
    g = s.prepare(scene, lat)
    light = jax.jit(s.solve)(g, Params.from_scene(scene, jnp.float64))
    assert int(light.result) == df.RESULTS.successful
    fog = np.asarray(g.free) & (np.asarray(g.density) > 0)
    J = np.asarray(light.fluence)[fog] / (4 * math.pi)
    assert np.allclose(J, 2.0, rtol=1e-6), (J.min(), J.max())


def test_auto_preconditioner_follows_the_diffusive_size():
    """precondition="auto": diffusion where light diffuses through many mean free paths (τ =
    100, albedo 0.999), not in thin fog (τ = 1) nor where absorption keeps the diffusion length
    short (albedo 0.9: 1.8 mean free paths)."""
    def auto(tau, a):
        scene = _thick_cube(1.0).replace(fog=df.Fog(scattering=a * tau, absorption=(1 - a) * tau))
        s = SweepSolver(M=2)
        return s.resolved_precondition(s.prepare(scene, df.voxelize(scene, 8, 2)))

    assert auto(100.0, 0.999) == "diffusion"
    assert auto(1.0, 0.999) == "none"
    assert auto(100.0, 0.9) == "none"
    with pytest.raises(df.SceneError, match="precondition must be one of"):
        SweepSolver(precondition="multigrid")


def test_the_adjoint_preconditioner_is_the_transpose_of_the_forward_one(x64, monkeypatch):
    """The adjoint light solve is preconditioned by (I + A⁻¹σ_s)ᵀ = I + σ_s A⁻¹: dense matrices
    of both on a small fog block with a hole (inner solve to 1e-13, so both are linear) are each
    other's transpose, and the surfaces' part of the state passes through."""
    from difffog.forward.sweep import _dsa

    monkeypatch.setattr(_dsa, "CG_RTOL", 1e-13)
    rng = np.random.default_rng(3)
    shape = (4, 3, 5)
    sigma_t = jnp.asarray(rng.uniform(5.0, 60.0, shape))
    sigma_t = sigma_t.at[1, 1, 2].set(0.0)  # a node without fog
    solid = jnp.zeros(shape, bool).at[3, 0, 0].set(True)
    ssa = jnp.full(shape, 0.99)
    pre = _dsa.DiffusionPreconditioner(sigma_t, ssa, solid, 0.0, h=0.1, periodic_xy=False, M=2,
                                       channels=False)
    n = math.prod(shape)
    irr = jnp.asarray(rng.normal(size=shape))

    def dense(p):
        cols = jax.jit(jax.vmap(lambda e: p.apply((e.reshape(shape), irr))[0].ravel()))
        return np.asarray(cols(jnp.eye(n))).T

    P, PT = dense(pre), dense(pre.transpose())
    assert np.max(np.abs(P - np.eye(n))) > 0.1  # it does something
    np.testing.assert_allclose(PT, P.T, atol=1e-9 * np.max(np.abs(P)))
    assert pre.transpose().transpose() == pre
    np.testing.assert_array_equal(np.asarray(pre.transpose().apply((sigma_t, irr))[1]), irr)


# default again since stop 83 (the suite compiles XLA's code at -O0: 20 s here; slow since stop 40)
def test_a_gradient_through_the_preconditioned_adjoint_matches_finite_differences(x64):
    """Thick, nearly conservative fog (τ = 100, albedo 0.999) with the diffusion preconditioner:
    the tangent and adjoint solves are preconditioned too (as the forward GMRES is), and the
    gradient in ζ through them agrees with central differences (the unpreconditioned adjoint's
    agrees with it to 1e-10, measured).  At N = 8 a lattice step spans ~25 mean free paths:
    the linear scheme's fixed point dips below 0 at a quarter of the fog nodes and the light is
    projected onto Λ, E ≥ 0; the gradient is the projected light's (it was the unprojected
    one's, taken at the projected point: 0.5% from the differences)."""
    scene = _thick_cube(1.0).replace(fog=df.Fog(scattering=99.9, absorption=0.1))
    lat = df.voxelize(scene, 8, 2)
    s = SweepSolver(M=2, tol=1e-10, max_iterations=2000, precondition="diffusion",
                    adjoint_rtol=1e-10)
    assert s.resolved_scheme(scene, lat) == "linear"
    g = s.prepare(scene, lat)
    p0 = Params.from_scene(scene, jnp.float64)

    def f(zeta):
        light = s.solve(g, eqx.tree_at(lambda q: q.scattering, p0, zeta))
        return (jnp.sum(light.fluence ** 2) ** 0.5 + jnp.sum(light.irradiance ** 2) ** 0.5,
                light.result)

    vg, zeta = jax.jit(jax.value_and_grad(f, has_aux=True)), p0.scattering
    (_, code), grad = vg(zeta)
    assert int(code) == df.RESULTS.successful
    eps = 1e-3  # the differences from the same compiled program's values
    fd = (vg(zeta + eps)[0][0] - vg(zeta - eps)[0][0]) / (2 * eps)
    assert abs(float(grad) - float(fd)) <= 1e-6 * abs(float(fd)), (float(grad), float(fd))


@pytest.mark.slow
def test_a_float32_gradient_in_thick_fog_is_finite_and_right():
    """Deep in a thick cloud (τ = 100, N = 16: ~12 mean free paths per step, the linear
    scheme) the uncollided sun underflows in float32, and the limiter of its slope divided by
    a norm whose square underflowed: every d/dζ came out NaN.  Now finite, and within 1e-3 of
    the same gradient in float64."""
    scene = _thick_cube(1.0).replace(fog=df.Fog(scattering=99.0, absorption=1.0))
    lat = df.voxelize(scene, 16, 2)
    s = SweepSolver(M=2, tol=1e-5, max_iterations=2000, precondition="none", adjoint_rtol=1e-5)
    g = s.prepare(scene, lat)
    assert s.resolved_scheme(scene, lat) == "linear"

    def grad(dtype):
        p = Params.from_scene(scene, dtype)

        def f(zeta):
            return jnp.mean(s.solve(g, eqx.tree_at(lambda q: q.scattering, p, zeta)).fluence)
        return float(jax.jit(jax.grad(f))(p.scattering))

    g32 = grad(jnp.float32)
    with jax.enable_x64(True):
        g64 = grad(jnp.float64)
    assert np.isfinite(g32) and abs(g64) > 0
    assert abs(g32 - g64) <= 1e-3 * abs(g64), (g32, g64)


def test_a_fixed_point_below_zero_is_reported_not_clipped_silently():
    """The linear scheme's fixed point can dip below 0 where a step spans tens of mean free
    paths (a slab τ = 256 over 8 nodes, M = 2: a step depth of 64, measured −4.5% of the peak);
    the solve clips it to 0 and says by how much (``LightField.dip``), and ``render`` warns
    above 1% of the peak.  The step scheme's update is positive: its dip is GMRES's residual."""
    from difffog.forward._model import dip_warning

    scene, lat, _ = slab_problem(256.0, 0.999, 8, 2, sky=0.0, sun=(1.0, 30.0))
    dips = {}
    for scheme in ("linear", "step"):
        solver = SweepSolver(M=2, max_iterations=3000, tol=1e-6, scheme=scheme)
        light = jax.jit(solver.solve)(solver.prepare(scene, lat),
                                      Params.from_scene(scene, jnp.float32))
        assert int(light.result) == df.RESULTS.successful
        assert float(np.min(light.fluence)) >= 0.0
        dips[scheme] = (float(light.dip), dip_warning(light))
    assert dips["linear"][0] > 0.02 and "dipped below 0" in dips["linear"][1]
    assert dips["step"][0] < 1e-3 and dips["step"][1] is None
