"""Optically thick fog (issue 14): the sweep conserves energy whatever a step's optical depth,
and a thick conservative fog reflects like a semi-infinite conservative medium.

Independent truths: adding-doubling (iadpython) for slabs, Chandrasekhar's H-function for the
semi-infinite medium.  Figures in docs/validation.md.
"""

import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import difffog as df
from difffog import Params, SweepSolver
from difffog.study._slab import slab_problem, slab_reflectance
from helpers import adding_doubling

SLAB_SOLVER = SweepSolver(M=2, max_iterations=4000, tol=1e-9)
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
    A = float(np.sum((1 - albedo) * sigma * np.asarray(light.fluence)[0, 0] * lat.h)) / math.pi
    r_err, balance = THICK_SLABS[(albedo, tau)]
    assert abs(R + T + A - 1) <= balance, (R, T, A)
    R_ad, _ = adding_doubling(albedo, tau)
    assert abs(R / R_ad - 1) <= r_err, (R, R_ad)


def semi_infinite_radiance(F: float, mu0: float, mu: float, sky: float) -> float:
    """Radiance leaving a semi-infinite conservative isotropic medium towards μ, under a sun of
    irradiance F (on a plane across the beam) at μ₀ and a uniform sky: Chandrasekhar's
    F/(4π)·μ₀/(μ + μ₀)·H(μ)H(μ₀), plus the sky (a conservative half-space returns a uniform
    sky unchanged)."""
    x, w = np.polynomial.legendre.leggauss(128)
    nodes, wts = 0.5 * (x + 1.0), 0.5 * w
    H = np.ones_like(nodes)
    for _ in range(3000):  # H = 1 / (1 − μ/2 ∫ H(μ')/(μ + μ') dμ')
        H = 1.0 / (1.0 - 0.5 * nodes * np.sum(wts * H / (nodes[:, None] + nodes), axis=1))

    def h(m):
        return 1.0 / (1.0 - 0.5 * m * np.sum(wts * H / (m + nodes)))

    return F / (4 * math.pi) * mu0 / (mu + mu0) * h(mu) * h(mu0) + sky


def _thick_cube(zeta: float) -> df.Scene:
    """Issue 14's scene: the unit cube of fog (open sides), a sphere of albedo 0.6 inside, sun
    at 30° (irradiance 2), sky 0.2, an orthographic camera looking straight down."""
    return df.Scene(
        title="thick cube", domain=df.Domain(min=(0, 0, 0), max=(1, 1, 1)),
        fog=df.Fog(scattering=zeta, absorption=0.001),
        sun=df.Sun(irradiance=2.0, zenith_deg=30.0), sky=df.Sky(radiance=0.2),
        shapes=(df.Sphere(name="ball", center=(0.5, 0.5, 0.5), radius=0.2, albedo=0.6),),
        cameras=(df.Camera(name="top", kind="orthographic", position=(0.5, 0.5, 1.5),
                           look_at=(0.5, 0.5, 0.5), up=(0, 1, 0), extent=(0.8, 0.8),
                           resolution=(16, 16)),))


def test_semi_infinite_value():
    # H(1) = 2.9078 (Chandrasekhar's table); the reference value the tests below use
    assert semi_infinite_radiance(4 * math.pi, 1.0, 1.0, 0.0) == pytest.approx(
        0.5 * 2.9078 ** 2, rel=2e-3)


def _mean_image(zeta: float, N: int, scheme: str = "step") -> float:
    m = df.forward_model(_thick_cube(zeta), "sweep", accuracy=None, resolution=N, M=2,
                         tol=1e-4, max_iterations=2000, supersample=1, scheme=scheme)
    with pytest.warns(df.ThickStepWarning, match=r"optically thick .* resolution >= \d+"):
        out = df.render(m)  # raises unless the light solve converged
    return float(out.images["top"].mean())


def test_thick_conservative_fog_is_bright_not_black_or_blown():
    """ζ = 1000 (a step depth of ~180 at N = 12): 0 with 0.1's scheme, and 10× too bright at
    ζ = 100; now within 12% of the semi-infinite value at this coarse lattice."""
    expected = semi_infinite_radiance(2.0, math.cos(math.radians(30)), 1.0, 0.2)
    assert _mean_image(1000.0, 12) == pytest.approx(expected, rel=0.12)


@pytest.mark.slow
@pytest.mark.parametrize("zeta", [100.0, 1000.0, 10000.0])
def test_thick_conservative_fog_reflects_like_a_semi_infinite_medium(zeta):
    """N = 32: within 5% of the semi-infinite value (measured −2.6%, +3.7%, +3.8%; the open
    sides let light out near the image's edges)."""
    expected = semi_infinite_radiance(2.0, math.cos(math.radians(30)), 1.0, 0.2)
    assert _mean_image(zeta, 32) == pytest.approx(expected, rel=0.05)


@pytest.mark.slow
@pytest.mark.parametrize("zeta,rel", [(100.0, 0.03), (10000.0, 0.2)])
def test_linear_scheme_thick_cube(zeta, rel):
    """The linear-source scheme with the cameras reading its slopes, N = 32 (measured +1.1% at
    ζ = 100, a step depth of 6; +14% at ζ = 10000, a step depth of 625, where a linear source
    spans 300 mean free paths per node), in float32 (its GMRES converges there)."""
    expected = semi_infinite_radiance(2.0, math.cos(math.radians(30)), 1.0, 0.2)
    assert _mean_image(zeta, 32, "linear") == pytest.approx(expected, rel=rel)


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
