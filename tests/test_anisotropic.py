"""Henyey–Greenstein scattering in the sweep (``SweepSolver.phase_order``): the angular basis,
exact limits (an isotropic phase through the anisotropic path, the furnace), slabs against
adding-doubling, the two kernels, and gradients against finite differences."""

import dataclasses
import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import difffog as df
from difffog import Params, load_scene
from difffog.forward.sweep._harmonics import basis, delta_m, real_sh
from difffog.forward.sweep._solver import SweepSolver
from difffog.geometry._directions import direction_set
from difffog.geometry._lattice import voxelize
from helpers import (build_model, hg_slab_rt, image_loss_gradient_matches_fd, kernels_agree,
                     random_face_geometry, slab_table_reference, small_scene)


# ---------------------------------------------------------------- the basis
def test_real_harmonics_obey_the_addition_theorem():
    """Σ_m Y_lm(a) Y_lm(b) = (2l+1)/4π · P_l(a·b) for random unit vectors (orthonormal real
    spherical harmonics, whatever their sign convention)."""
    rng = np.random.default_rng(0)
    v = rng.standard_normal((2, 50, 3))
    v /= np.linalg.norm(v, axis=-1, keepdims=True)
    L = 5
    Y = real_sh(v, L)
    cos = (v[0] * v[1]).sum(-1)
    for l in range(L + 1):
        s = (Y[0][:, l * l : (l + 1) ** 2] * Y[1][:, l * l : (l + 1) ** 2]).sum(-1)
        P = np.polynomial.legendre.legval(cos, [0] * l + [1])
        np.testing.assert_allclose(s, (2 * l + 1) / (4 * math.pi) * P, atol=1e-12)


@pytest.mark.parametrize("M", [2, 3, 5])
@pytest.mark.parametrize("L", [1, 3, 4])
def test_basis_is_orthonormal_on_the_lattice_and_conserves(M, L):
    """Under the lattice's own quadrature the basis is orthonormal, and every function of order
    ≥ 1 integrates to 0 (a node re-emits exactly the power it scatters)."""
    B = basis(L, M)
    ds = direction_set(M)
    w = ds.weights.reshape(-1)
    Y = B.faces.reshape(-1, B.K)
    np.testing.assert_allclose(Y.T @ (w[:, None] * Y), np.eye(B.K), atol=1e-12)
    np.testing.assert_allclose(w @ Y, 0.0, atol=1e-12)
    assert list(B.degree) == [l for l in range(1, L + 1) for _ in range(2 * l + 1)]


def test_delta_m_coefficients():
    f, c = delta_m(0.85, 3)
    assert f == pytest.approx(0.85 ** 4)
    np.testing.assert_allclose(c, [(0.85 ** l - f) / (1 - f) for l in (1, 2, 3)])
    f0, c0 = delta_m(0.0, 2)
    assert f0 == 0 and not np.any(c0)
    assert delta_m(0.6, 0)[0] == pytest.approx(0.6)  # order 0 is the δ-isotropic scaling


# ---------------------------------------------------------------- exact limits
@pytest.mark.slow  # 20 s; the furnace below and the kernels' test guard the path by default
def test_isotropic_phase_through_the_anisotropic_path_changes_nothing(x64):
    """g = 0 with phase_order 2 (moments, the sun's cell-averaged phase, the sky's moments) gives
    the isotropic solve's light to rounding (the moments of the radiance are not 0, but an
    isotropic phase does not scatter them)."""
    scene = load_scene("fog-balls", ["shape.walls.thickness=0.1"])
    lat = voxelize(scene, 10, 2)
    p = Params.from_scene(scene, jnp.float64)
    out = {}
    for L in (0, 2):
        solver = SweepSolver(M=2, tol=1e-11, max_iterations=300, phase_order=L)
        geom = solver.prepare(scene, lat)
        out[L] = jax.jit(solver.solve)(geom, p)
    assert out[2].moments.shape == out[0].fluence.shape + (8,)
    np.testing.assert_allclose(out[2].fluence, out[0].fluence, rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(out[2].radiosity, out[0].radiosity, rtol=1e-9, atol=1e-12)
    assert float(jnp.max(jnp.abs(out[2].moments))) > 1e-3 * float(jnp.max(out[0].fluence))


def test_furnace_with_forward_scattering_fog(x64):
    """A closed box (emission 1, albedo 0.9) filled with conservative fog of g = 0.85: the
    radiance is 10 everywhere and isotropic, whatever the phase (scattering an isotropic field
    leaves it isotropic), so the moments vanish."""
    scene = load_scene("furnace", ["fog.phase=henyey-greenstein", "fog.g=0.85"])
    solver = SweepSolver(M=2, tol=1e-10, max_iterations=2000, terms="all", phase_order=3)
    geom = solver.prepare(scene, voxelize(scene, 12, 2))
    light = jax.jit(solver.solve)(geom, Params.from_scene(scene, jnp.float64))
    assert int(light.result) == df.RESULTS.successful
    B = np.asarray(light.radiosity)[np.asarray(geom.surf)]
    J = np.asarray(light.fluence)[~np.asarray(geom.solid)] / (4 * math.pi)
    np.testing.assert_allclose(B, 10.0, rtol=1e-6)
    np.testing.assert_allclose(J, 10.0, rtol=1e-6)
    assert float(jnp.max(jnp.abs(light.moments))) < 1e-6 * 4 * math.pi * 10


# ---------------------------------------------------------------- slabs vs adding-doubling
# Measured at N = 32, M = 3, L = 3 (benchmarks/slab_anisotropic.py; docs/validation.md), the
# bounds ~1 point above: (albedo, tau, illumination) → (|R err|, |T err|)
HG_BOUNDS = {
    (0.9, 1.0, "diffuse"): (0.025, 0.012), (0.99, 4.0, "diffuse"): (0.015, 0.015),
    (0.9, 1.0, "collimated"): (0.035, 0.015), (0.99, 4.0, "collimated"): (0.02, 0.02),
}


@pytest.mark.parametrize("albedo,tau,illumination", [
    (0.99, 4.0, "collimated"),
    pytest.param(0.9, 1.0, "diffuse", marks=pytest.mark.slow),
    pytest.param(0.99, 4.0, "diffuse", marks=pytest.mark.slow),
    pytest.param(0.9, 1.0, "collimated", marks=pytest.mark.slow)])
def test_hg_slab_against_adding_doubling(albedo, tau, illumination, x64):
    sun = (1.0, 0.0) if illumination == "collimated" else None
    R, T = hg_slab_rt(tau, albedo, 0.85, 32, 3, 3, sun=sun)
    R_ref, T_ref = slab_table_reference(albedo, tau, illumination, 0.0 if sun else None, g=0.85)
    eR, eT = HG_BOUNDS[(albedo, tau, illumination)]
    assert abs(R / R_ref - 1) < eR, (R, R_ref)
    assert abs(T / T_ref - 1) < eT, (T, T_ref)


# ---------------------------------------------------------------- kernels
# slow: the default suite's 12-minute budget on 2 cores (stop 56)
@pytest.mark.slow
@pytest.mark.parametrize("sun", [True, False])
def test_kernels_agree_with_an_anisotropic_source(sun):
    """The direction-loop and batched sweeps with per-direction sources (moments, the sun's
    channel), every combination of periodic sides."""
    import itertools

    from difffog.forward.sweep._kernel import face_consts

    M, L, shape = 2, 2, (7, 6, 8)
    B = basis(L, M)
    D = (2 * M + 1) ** 2
    rng = np.random.default_rng(3)
    f32 = lambda a: jnp.asarray(a, jnp.float32)  # noqa: E731
    J = B.K + (1 if sun else 0)
    Q = f32(np.concatenate([rng.random(shape + (1,)), rng.random(shape + (J,)) - 0.5], -1))
    Bv, tau, bc = f32(rng.random(shape)), f32(0.4 * rng.random(shape)), f32(rng.random(D))
    geo = random_face_geometry(rng, shape, D)
    consts = face_consts(direction_set(M), 0, B.faces)
    if sun:
        import dataclasses
        consts = dataclasses.replace(consts, sun_phase=f32(rng.random(D)))
    combos = list(itertools.product([False, True], repeat=3))
    for a in kernels_agree((Q, Bv, tau, bc, geo, consts), M, combos, True, 5e-6):
        assert a[0].shape == shape + (1 + B.K,)


# ---------------------------------------------------------------- gradients
# default again since stop 83 (the suite compiles XLA's code at -O0: 33 s here): the gradients in
# g against differences on every CI run
def test_image_gradients_in_g_and_the_rest_match_finite_differences(x64):
    """The whole chain with an anisotropic light solve (cloud-plane, L = 2): the gradient of an
    image loss with respect to g, ζ, γ, an albedo and the sun against central differences."""
    scene = small_scene("cloud-plane", size=(10, 8))
    m = build_model("sweep", scene, resolution=12, max_iterations=1000, tol=1e-12,
                    adjoint_rtol=1e-11, phase_order=2)
    image_loss_gradient_matches_fd(m, scene, ("fog.g", "fog.scattering", "fog.absorption",
                                               "shape.ground.albedo", "sun.irradiance"))


@pytest.mark.parametrize("M", [2, pytest.param(3, marks=pytest.mark.slow)])  # the budget
def test_the_suns_beam_keeps_the_forward_peak_its_directions_cannot_resolve(M, x64):
    """The sun's first collision on the lattice: the cell-averaged exact phase less the part of
    its forward peak that M's directions cannot resolve (``unresolved_peak``), which the beam
    keeps.  What stays re-emits exactly what the beam loses (Σ w P = 1), is ≥ 0, and moves
    continuously with the sun's direction: over steps of 0.0125° in azimuth from 200° to 220°,
    where the sun crosses cell boundaries and its nearest lattice direction changes (a g = 0.99
    lobe is ~1° wide), no direction's value jumps by more than the plain cell average's does
    (taking the peak from the sun's nearest direction instead jumps 300-750 times as much)."""
    from difffog.forward.sweep import _solver as S

    geom = build_model("sweep", small_scene("cloud-plane"), M=M).geometry
    w = np.asarray(jnp.stack([c.weight for c in geom.consts]))
    th, ph = math.radians(30.0), np.radians(np.linspace(200.0, 220.0, 1601))
    vecs = jnp.asarray(np.stack([np.sin(th) * np.cos(ph), np.sin(th) * np.sin(ph),
                                 np.full_like(ph, np.cos(th))], -1))
    for g in (0.85, 0.95, 0.99):
        peak = S.unresolved_peak(g, M)
        assert 0 < peak < delta_m(g, 3)[0]  # finer than δ-M's own peak at L = 3

        @jax.jit
        @jax.vmap
        def phases(v):
            gm = dataclasses.replace(geom, sun_vec=v)
            P, kept, _ = S._cell_phase(gm, g, jnp.float64, peak)
            return jnp.stack(P), kept, jnp.stack(S._cell_phase(gm, g, jnp.float64)[0])

        P, kept, plain = (np.asarray(x) for x in phases(vecs))
        assert np.abs((w * P).sum((1, 2)) - 1.0).max() < 1e-12 and P.min() >= 0.0
        np.testing.assert_allclose(kept, peak, rtol=1e-9)  # the cells around hold it
        jump = np.abs(np.diff(P * (1 - kept[:, None, None]), axis=0)).max()
        assert jump <= 1.01 * np.abs(np.diff(plain, axis=0)).max() + 1e-12, g
    P0, kept0, _ = S._cell_phase(geom, 0.85, jnp.float64)  # no peak: the plain cell average
    assert float(kept0) == 0.0


def test_as_g_approaches_1_the_fog_stops_scattering(x64):
    """A Henyey–Greenstein fog of g → 1 scatters only straight ahead: its images approach those
    of clear air.  Before the sun's beam kept the forward peak that the lattice's directions
    cannot resolve, the first collision sent it along the nearest direction, half a cell off
    the sun's: translucent-cube's shadow moved, g = 0.999 at 15% of the clear image in the
    mean and 98% at its worst pixel (top view, N = 12; 0.4% and 3.0% now)."""
    scene = small_scene("translucent-cube", ["fog.phase=henyey-greenstein", "fog.g=0.999",
                                              "fog.scattering=3", "fog.absorption=0",
                                              "sky.radiance=0"], size=(24, 24))
    m = build_model("sweep", scene, supersample=2)
    images = m.images  # one program for both: clear air is ζ = 0
    p = m.params()
    forward = {k: np.asarray(v) for k, v in images(p).items()}
    clear = {k: np.asarray(v) for k, v in images(df.set_param(p, scene, "fog.scattering",
                                                               0.0)).items()}
    for cam, (mean_bound, worst_bound) in {"top": (0.01, 0.05), "oblique": (0.015, 0.12)}.items():
        d = np.abs(forward[cam] - clear[cam]) / clear[cam].mean()
        assert d.mean() < mean_bound and d.max() < worst_bound, (cam, d.mean(), d.max())


def test_phase_order_is_checked():
    with pytest.raises(df.SceneError, match="phase_order"):
        SweepSolver(phase_order=-1)
    with pytest.raises(df.SceneError, match="phase_order"):
        SweepSolver(phase_order="high")
    scene = load_scene("cloud-plane")
    assert SweepSolver().resolved_phase_order(scene) == 3
    assert SweepSolver().resolved_phase_order(load_scene("fog-balls")) == 0
    assert SweepSolver(phase_order=1).resolved_phase_order(scene) == 1


def test_a_sun_with_an_angular_radius_is_refused_not_ignored():
    scene = load_scene("cloud-plane", ["sun.angular_radius_deg=2"])
    with pytest.raises(df.SceneError, match="angular_radius_deg = 2: the sweep solver treats"):
        df.forward_model(scene, "sweep", accuracy="draft")


def test_the_estimate_counts_the_moments(monkeypatch):
    """difffog.estimate: the solve's vectors hold Λ and K moments per node, and an iteration
    costs more per moment (measured constants in _cost.py) than XLA's isotropic step loop (a
    CPU's isotropic step sweep is native where it can be: test_cost.py)."""
    from difffog.forward.sweep import _native

    monkeypatch.setattr(_native, "expected", lambda: False)
    scene = load_scene("cloud-plane")
    # one scheme for both (with "auto" the δ-M order changes the step depth, and so the scheme:
    # the linear one's cost is test_cost.py's)
    iso = df.estimate(scene, "sweep", resolution=32, phase_order=0, scheme="step")
    l3 = df.estimate(scene, "sweep", resolution=32, phase_order=3, scheme="step")
    assert l3.memory["Krylov vectors"] == pytest.approx(iso.memory["Krylov vectors"] * 17 / 2)
    assert l3.seconds_per_iteration / iso.seconds_per_iteration == pytest.approx(1 + 0.22 * 15)


@pytest.mark.slow
def test_a_fit_of_g_and_zeta_recovers_its_own_images():
    """The fit machinery with g as an unknown (LM through the anisotropic solve's Jacobian):
    from images the same model rendered at g = 0.8, ζ = 40 it recovers both (the recovery from
    finer images is benchmarks/fit_anisotropic.py's)."""
    scene = small_scene("cloud-plane", size=(16, 12))
    truth = df.apply_overrides(scene, ["fog.g=0.8", "fog.scattering=40"])
    m = build_model("sweep", truth, resolution=12, tol=1e-6, phase_order=2)
    targets = {k: np.asarray(v) for k, v in m(m.params()).items()}
    with pytest.warns(df.ThickStepWarning):  # ζ = 40 on 12 nodes: thick steps, said so
        res = df.fit(scene, targets, {"fog.g": 0.6, "fog.scattering": 30.0}, forward=m)
    assert res.estimates["fog.g"] == pytest.approx(0.8, rel=2e-3)
    assert res.estimates["fog.scattering"] == pytest.approx(40.0, rel=2e-3)
