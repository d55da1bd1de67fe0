"""Slabs as cameras see them: the exact slab radiance, and cameras held against it per angle.

The slab rows elsewhere (test_sweep, test_thick) read R and T by a formula over the converged
source (``slab_reflectance``); these render the slab as a scene and read its images, as a user
would (``benchmarks/slab_cameras.py`` has the whole table)."""

import math
import sys
import warnings
from pathlib import Path

import numpy as np
import pytest

import difffog as df
from difffog.study._slab import exact_slab_radiance, exact_slab_rt, isotropic_slab_rows

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))


@pytest.mark.parametrize("tau", [1.0, 4.0, 16.0])
def test_the_exact_slab_matches_adding_doubling(tau):
    """The per-angle truth the cameras are held against integrates to the adding-doubling
    table's R and T (an independent method) within 0.05%, for the sky and both suns (T where
    the table gives it to more than 1e-4)."""
    table = isotropic_slab_rows()
    for albedo in (0.5, 0.9, 0.999):
        for light in ("diffuse", "coll0", "coll60"):
            R_ad, T_ad = table[(tau, albedo, light)]
            R, T = exact_slab_rt(tau, albedo, light)
            assert R == pytest.approx(R_ad, rel=5e-4), (albedo, light)
            if T_ad > 1e-4:  # the table's T has 2-4 significant digits
                assert T == pytest.approx(T_ad, rel=5e-4), (albedo, light)


def test_the_exact_slab_radiance_has_the_known_limits():
    """Single scattering of a thin slab (τ → 0: I = a·F·τ/(4πμ) at the top under a sun
    overhead) and a conservative slab 200 mean free paths thick against Chandrasekhar's
    half-space (``semi_infinite_radiance``, H-functions), which it approaches from below (it
    transmits 0.7%)."""
    from difffog.study._semi_infinite import semi_infinite_radiance

    mus = np.array([0.2, 0.5, 1.0])
    top, _, _, _ = exact_slab_radiance(1e-4, 0.5, "coll0", mus)
    np.testing.assert_allclose(top, 0.5 * 1e-4 / (4 * math.pi * mus), rtol=2e-3)
    top, _, _, _ = exact_slab_radiance(200.0, 1.0 - 1e-9, "coll60", mus, cells_per_tau=16)
    half = np.array([semi_infinite_radiance(1.0, 0.5, m, 0.0) for m in mus])
    assert np.all(top < half) and np.all(top > 0.99 * half)


@pytest.mark.parametrize("light", ["diffuse", "coll60"])
def test_cameras_read_a_resolved_slab_as_the_exact_one(light):
    """A slab of τ = 1 (32 nodes, h = 1/32 mean free path): the cameras' images at four μ above
    and below integrate to R and T within 1% of the exact slab, each image within 2% at μ ≥
    0.3 (grazing views read the face brighter: docs/validation.md, "Slabs as cameras see
    them")."""
    import slab_cameras

    x, w = np.polynomial.legendre.leggauss(4)
    mus, wts = 0.5 * (x + 1), 0.5 * w
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", df.ThinLayerWarning)
        top, bot, _, _, _ = slab_cameras.camera_slab(1.0, 0.99, light, mus, 32, 2, "auto", "beam",
                                                  1e-6)
    top_x, bot_x, inc, direct = exact_slab_radiance(1.0, 0.99, light, mus)
    R, R_x = slab_cameras.flux(top, mus, wts) / inc, slab_cameras.flux(top_x, mus, wts) / inc
    T = (slab_cameras.flux(bot, mus, wts) + direct) / inc
    T_x = (slab_cameras.flux(bot_x, mus, wts) + direct) / inc
    assert R == pytest.approx(R_x, rel=0.01) and T == pytest.approx(T_x, rel=0.01)
    steep = mus >= 0.3
    np.testing.assert_allclose(top[steep], top_x[steep], rtol=0.02)
    np.testing.assert_allclose(bot[steep], bot_x[steep], rtol=0.02)


def test_a_thick_slab_half_a_mean_free_path_a_step_takes_the_linear_scheme():
    """τ = 16, albedo 0.99, sun overhead, N = 48, M = 2 (a step depth of 0.67, fog 16 mean free
    paths across): the default takes the linear scheme, whose light through the slab the
    cameras read +2.2% from the exact slab, where the step scheme reads it +8.3% (its lattice
    diffusion; until stop 77 the default took it at step depths up to 1)."""
    import slab_cameras

    x, w = np.polynomial.legendre.leggauss(4)
    mus, wts = 0.5 * (x + 1), 0.5 * w
    _, bot_x, inc, direct = exact_slab_radiance(16.0, 0.99, "coll0", mus)
    T_x = (slab_cameras.flux(bot_x, mus, wts) + direct) / inc
    T = {}
    for scheme in ("auto", "step"):
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", df.ThickStepWarning)
            _, bot, _, model, _ = slab_cameras.camera_slab(16.0, 0.99, "coll0", mus, 48, 2,
                                                          scheme, "beam", 1e-6)
        T[scheme] = (slab_cameras.flux(bot, mus, wts) + direct) / inc / T_x - 1
        if scheme == "auto":
            assert model.geometry.linear
    assert abs(T["auto"]) < 0.03 and T["step"] > 0.06, T
