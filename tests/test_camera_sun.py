"""The cameras' single scattering of the sun along their own path (``LatticeFields.sun_depth``):
exact for a uniform fog however many mean free paths a march step spans, and the path towards
the sun that feeds it (``_uncollided.sun_path``, ``_model._sun_path``)."""

import math

import jax.numpy as jnp
import numpy as np
import pytest

import difffog as df
from difffog.forward._camera import hg_phase
from difffog.forward.sweep._march import LatticeFields, render_rays
from difffog.forward.sweep._model import _fog_support, _sun_path
from difffog.forward.sweep._uncollided import sun_path
from difffog.geometry._lattice import voxelize


def _slab_fields(sigma, mu0, h=0.125):
    """A periodic slab of fog z ∈ [0, 1] (one vacuum node above and below), albedo 1, a sun of
    irradiance 1 at μ₀ = cos(zenith): j_sun = σ (unattenuated), the optical depth towards the
    sun σ(1 − z)/μ₀ continued linearly to the vacuum nodes, the march clipped to the slab."""
    n = (2, 2, int(round(1 / h)) + 2)
    z = (np.arange(n[2]) - 0.5) * h  # node centres; origin z = −h
    full = lambda v: np.broadcast_to(np.asarray(v, np.float64), n).copy()  # noqa: E731
    sun = (math.sqrt(1 - mu0 * mu0), 0.0, mu0)
    return LatticeFields(
        sigma_t=full(sigma), j_iso=full(0.0), j_sun=full(sigma), radiosity_ext=full(0.0),
        sdf=full(10.0), origin=(0.0, 0.0, -h), h=h, sun_dir=sun, periodic_xy=True,
        sun_depth=full(sigma * (1.0 - z) / mu0), fog_box=((0.0, 0.0, 0.0), (2 * h, 2 * h, 1.0)))


@pytest.mark.parametrize("sigma", [3.0, 240.0])  # 0.2 and 15 mean free paths per march step
def test_sun_single_scattering_looking_down_is_exact(x64, sigma):
    """L = p·σ ∫ e^(−σt(1 + 1/μ₀)) dt over the slab: p·μ₀/(1 + μ₀)·(1 − e^(−σ(1 + 1/μ₀)))."""
    mu0 = math.cos(math.radians(30.0))
    f = _slab_fields(sigma, mu0)
    d = np.array([[0.0, 0.0, -1.0]])
    out = float(render_rays(f, np.array([[0.1, 0.1, 2.0]]), d)[0])
    p = float(hg_phase(-mu0, 0.0))
    k = 1.0 + 1.0 / mu0
    assert out == pytest.approx(p / k * (1.0 - math.exp(-sigma * k)), rel=1e-9)
    # the same fields with the sun's attenuation sampled at the step ends instead (what a
    # node-based source does): 15 mean free paths per step are far from exact
    if sigma > 100:
        T = np.exp(-np.asarray(f.sun_depth))
        point = LatticeFields(sigma_t=f.sigma_t, j_iso=f.j_iso, j_sun=f.j_sun * T,
                              radiosity_ext=f.radiosity_ext, sdf=f.sdf, origin=f.origin, h=f.h,
                              sun_dir=f.sun_dir, periodic_xy=True, fog_box=f.fog_box)
        sampled = float(render_rays(point, np.array([[0.1, 0.1, 2.0]]), d)[0])
        assert abs(sampled / out - 1.0) > 0.5


def test_sun_single_scattering_towards_the_sun(x64):
    """A ray going up more steeply than the sun's light comes down: the optical depth back to
    the ray's start grows slower than the one towards the sun falls (the exponent's other
    sign).  L = σp·e^(−σ/μ₀)·(1 − e^(−σc))/(σc), c = 1 − 1/μ₀ < 0."""
    sigma, mu0 = 3.0, math.cos(math.radians(30.0))
    f = _slab_fields(sigma, mu0)
    out = float(render_rays(f, np.array([[0.1, 0.1, -1.0]]), np.array([[0.0, 0.0, 1.0]]))[0])
    c = 1.0 - 1.0 / mu0
    p = float(hg_phase(mu0, 0.0))
    expected = sigma * p * math.exp(-sigma / mu0) * (-math.expm1(-sigma * c)) / (sigma * c)
    assert out == pytest.approx(expected, rel=1e-9)


def _box_scene(density=None, azimuth=30.0):
    return df.Scene(title="box", domain=df.Domain((0, 0, 0), (1.0, 0.8, 0.6)),
                    fog=df.Fog(scattering=1.0, absorption=0.0, density=density),
                    sun=df.Sun(1.0, 40.0, azimuth))


@pytest.mark.parametrize("azimuth", [30.0, 200.0])  # towards +x +y, and −x −y
def test_sun_path_uniform_fog_is_the_distance_to_the_box(azimuth):
    """Uniform fog: the path towards the sun from every node is its distance to the fog box's
    face along the sun (exact, also continued outside the box: 0 where the sun enters)."""
    scene = _box_scene(azimuth=azimuth)
    lat = voxelize(scene, 20, 2, margin=3)
    (lo, hi), ranges = _fog_support(scene, lat)
    np.testing.assert_allclose(lo, (0, 0, 0))
    np.testing.assert_allclose(hi, (1.0, 0.8, 0.6))
    path = _sun_path(scene, lat, (lo, hi), ranges)
    s = np.asarray(scene.sun.direction)
    assert np.sign(s[0]) == (1 if azimuth < 90 else -1)
    # a point on the box's top face, and one on its side towards the sun
    for p in ([0.5, 0.4, 0.6], [1.0 if s[0] > 0 else 0.0, 0.4, 0.3]):
        u = (np.asarray(p) - lat.origin) / lat.h - 0.5
        i0 = np.floor(u).astype(int)
        f = u - i0
        val = 0.0
        for corner in np.ndindex(2, 2, 2):
            w = np.prod([f[a] if corner[a] else 1 - f[a] for a in range(3)])
            val += w * path[tuple(i0 + np.asarray(corner))]
        assert val == pytest.approx(0.0, abs=1e-9)
    # inside: the chord to the exit face, checked by marching along the sun
    i = (ranges[0][0] + 5, ranges[1][0] + 3, ranges[2][0] + 2)
    x = lat.origin + (np.asarray(i) + 0.5) * lat.h
    t = min((np.where(s[a] > 0, hi[a], lo[a]) - x[a]) / s[a] for a in range(3))
    assert path[i] == pytest.approx(t, rel=1e-12)
    assert np.all(path[ranges[0][0]:ranges[0][1] + 1, ranges[1][0]:ranges[1][1] + 1,
                       ranges[2][0]:ranges[2][1] + 1] > 0)


def test_sun_path_through_a_density_grid():
    """A density grid: the sheet sweep's path is linear in the density (twice the grid, twice
    the path) and, for a uniform grid, within half a lattice spacing of the exact chord where
    the sun enters through the top (exactly the chord there) and within two spacings where it
    enters through a side (bilinear resampling near the box's edge)."""
    scene = _box_scene(density=np.ones((4, 4, 4)))
    lat = voxelize(scene, 20, 2, margin=3)
    (lo, hi), ranges = _fog_support(scene, lat)
    grid = _sun_path(scene, lat, (lo, hi), ranges)
    exact = _sun_path(_box_scene(), lat, (lo, hi), ranges)
    inside = tuple(slice(r[0], r[1] + 1) for r in ranges)
    err = np.abs(grid - exact)[inside]
    assert err.max() <= 2.0 * lat.h
    # the top layer of nodes (the sun enters them through the top face): exact
    top = np.abs(grid - exact)[inside[0], inside[1], ranges[2][1]]
    s = np.asarray(scene.sun.direction)
    reach = exact[inside[0], inside[1], ranges[2][1]] * np.abs(s[:2]).max() < 0.5 * lat.h
    assert reach.any() and top[reach].max() < 1e-5
    dens = jnp.asarray(lat.fog_density, jnp.float32)
    one = np.asarray(sun_path(dens, s, lat.h, False))
    two = np.asarray(sun_path(2 * dens, s, lat.h, False))
    np.testing.assert_allclose(two, 2 * one, rtol=1e-6)
