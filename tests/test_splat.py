"""The splat solver (Zhang & Crawfis): exact Beer–Lambert shadow buffer, the forward-scattering
recurrence, polygon shading conventions, errors, gradients against finite differences."""

import json
import math
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import difffog as df
from difffog._scene import Camera, Domain, Fog, Quad, Scene, Sky, Sun
from difffog._splat import _hg_total_forward, _trilinear_np_jax

ATT_ONLY = dict(forward_scatter=False, back_scatter=False, soft_shadows=False, similarity=False)


def slab_scene(zeta=3.0, gamma=1.0, g=0.0, zenith=30.0, z0=0.3, z1=0.6, sky=0.0, shapes=()):
    top = Camera(name="top", kind="orthographic", position=(0.5, 0.5, 1.5),
                 look_at=(0.5, 0.5, 0.0), up=(0.0, 1.0, 0.0), resolution=(16, 16),
                 extent=(1.0, 1.0))
    return Scene(
        title="test-slab",
        domain=Domain(min=(0.0, 0.0, 0.0), max=(1.0, 1.0, 1.0)),
        fog=Fog(scattering=zeta, absorption=gamma, g=g,
                phase="henyey-greenstein" if g else "isotropic",
                region=((0.0, 0.0, z0), (1.0, 1.0, z1))),
        sun=Sun(irradiance=2.0, zenith_deg=zenith, azimuth_deg=40.0),
        sky=Sky(radiance=sky) if sky else None,
        shapes=tuple(shapes), cameras=(top,))


def test_beer_lambert_through_a_homogeneous_slab():
    # N = 20: the slab faces z = 0.3, 0.6 fall halfway between nodes, so the tent-kernel
    # reconstruction integrates to exactly 0.3 of fog across the slab
    # (a kink of the tent reconstruction inside a footprint segment is the only quadrature
    # error: it falls as the Gauss–Legendre points per segment grow)
    sc = slab_scene()
    # below the slab by more than a sheet: the light there has crossed whole sheets of fog
    pts = np.array([[0.5, 0.5, 0.2], [0.45, 0.55, 0.1], [0.6, 0.4, 0.15]])
    exact = 2.0 * math.exp(-4.0 * 0.3 / math.cos(math.radians(30.0)))
    errs = []
    for q in (2, 16):
        r = df.SplatRenderer(sc, resolution=20, quadrature=q, **ATT_ONLY)
        d, s, b = r.light_at(pts)
        errs.append(np.abs(np.log(d / exact)).max())  # optical-depth error
        assert np.all(s == 0) and np.all(b == 0)  # attenuation only
    assert errs[1] < 3e-4 and errs[1] < errs[0] < 2e-2
    # above the slab: the full sun
    d, _, _ = r.light_at(np.array([[0.5, 0.5, 0.8]]))
    np.testing.assert_allclose(d, 2.0, rtol=1e-6)


def test_beer_lambert_through_the_cloud_grid_matches_a_ray_march():
    sc = df.load_scene("cloud-plane")
    sc = sc.replace(shapes=())  # the cloud alone
    r = df.SplatRenderer(sc, resolution=24, quadrature=4, cameras=["top"], **ATT_ONLY)
    # points where a texel's light ray enters a sheet: there the buffer holds exactly the light
    # that crossed the sheets before (no interpolation between rays or within a sheet)
    (_, _, _), plan, info = r.light_buffers()
    gm = info["geometry"]
    s, a, b, L = (np.asarray(gm[k]) for k in ("s", "a", "b", "L"))
    rng = np.random.default_rng(0)
    hs, ws = plan.buffer_hw
    i, j = rng.integers(0, hs, 400), rng.integers(0, ws, 400)
    k = rng.integers(plan.K // 3, plan.K, 400)
    u = gm["u_min"] + (i + 0.5) * info["texel"]
    v = gm["v_min"] + (j + 0.5) * info["texel"]
    z = gm["z_lo"] + k * gm["dz"]
    pts = u[:, None] * a + v[:, None] * b + (z / float(s @ L))[:, None] * L
    d, _, _ = r.light_at(pts)
    tau_splat = -np.log(d / sc.sun.irradiance)
    # direct march of the same trilinear density towards the sun, 2000 steps per unit length
    lat = r.lattice
    sun = np.asarray(sc.sun.direction)
    ts = (np.arange(4000) + 0.5) / 2000.0
    P = pts[:, None, :] + ts[None, :, None] * sun
    dens = np.asarray(_trilinear_np_jax(jnp.asarray(lat.density), jnp.asarray(lat.origin),
                                        lat.h, jnp.asarray(P, jnp.float32)))
    tau_march = sc.fog.extinction * dens.sum(1) / 2000.0
    assert (tau_march > 3.0).sum() >= 10  # a good number lie deep in the cloud's shadow
    # quadrature of the tent kernel's kinks (4 Gauss points per segment): ≤ 0.3% measured
    np.testing.assert_allclose(tau_splat, tau_march, rtol=5e-3, atol=2e-3)


def test_forward_scattering_recurrence_conserves_the_forward_fraction():
    # conservative, laterally uniform slab, back scattering off: per sheet the buffer keeps
    # T_k + f_A(1 − T_k) of its light (eq. 3 with a kernel that sums to f_A).  Sun at the
    # zenith and a camera looking down: horizontal sheets, each laterally uniform
    sc = slab_scene(zeta=5.0, gamma=0.0, g=0.85, zenith=0.0)
    r = df.SplatRenderer(sc, resolution=16, back_scatter=False, soft_shadows=False,
                         similarity=False)
    (Fd, Fs, B), plan, info = r.light_buffers()
    K = plan.K
    D = np.asarray(plan.light_D[:K], np.float64)
    i, j = np.array(Fd.shape[1:]) // 2
    T = np.exp(-5.0 * D[:, i, j])
    fa = float(_hg_total_forward(0.85))
    expect = 2.0 * np.cumprod(T + fa * (1 - T))
    got = np.asarray(Fd[1:, i, j] + Fs[1:, i, j], np.float64)
    np.testing.assert_allclose(got, expect[:-1], rtol=1e-4)
    np.testing.assert_allclose(np.asarray(Fd[1:, i, j]), 2.0 * np.cumprod(T)[:-1], rtol=1e-4)
    assert abs(fa - 0.9641) < 1e-3  # HG g = 0.85: 96.4% of the phase in the forward hemisphere


def test_scattering_switches_order_the_brightness():
    # the paper's Figs. 1, 2, 4: attenuation only < + forward < + forward and back
    sc = df.load_scene("cloud-plane").replace(shapes=())
    means = []
    for kw in (ATT_ONLY, dict(back_scatter=False, soft_shadows=False, similarity=False),
               dict(soft_shadows=False, similarity=False)):
        r = df.SplatRenderer(sc, resolution=16, cameras=["top"], **kw)
        means.append(float(r()["top"].mean()))
    assert means[0] < means[1] < means[2]


def test_lit_ground_pixel_is_lambertian():
    # a ground quad far from the fog's shadow: radiance = ρ/π·(E cos θ + π·sky)
    ground = Quad(name="ground", corners=((0, 0, 0.05), (1, 0, 0.05), (1, 1, 0.05), (0, 1, 0.05)),
                  albedo=0.6)
    sc = slab_scene(z0=0.7, z1=0.8, sky=0.2, shapes=(ground,)).replace(
        fog=Fog(scattering=3.0, absorption=1.0, region=((0.4, 0.4, 0.7), (0.5, 0.5, 0.8))))
    for soft in (False, True):
        r = df.SplatRenderer(sc, resolution=16, soft_shadows=soft)
        img = np.asarray(r()["top"])
        expect = 0.6 / math.pi * (2.0 * math.cos(math.radians(30.0)) + math.pi * 0.2)
        # the corner pixel (row 0 = +y, col 0 = −x) lies away from the fog box and its shadow
        assert img[0, 0] == pytest.approx(expect, rel=1e-4)


def test_scenes_the_splat_cannot_handle_raise_scene_errors():
    with pytest.raises(df.SceneError, match="no \\[sun\\]"):
        df.SplatRenderer(df.load_scene("furnace"), resolution=8)
    with pytest.raises(df.SceneError, match="periodic-xy"):
        df.SplatRenderer(df.load_scene("slab"), resolution=8)
    with pytest.raises(df.SceneError, match="sheets"):
        df.SplatRenderer(df.load_scene("cloud-plane"), resolution=8, sheets=0)


def test_render_returns_images_and_plan_summary():
    sc = df.load_scene("translucent-cube")
    r = df.SplatRenderer(sc, resolution=16, sheets=12, soft_shadows=False)
    out = r.render()
    assert set(out.images) == {"top", "oblique"}
    assert out.images["oblique"].shape == (120, 160) and out.images["top"].dtype == np.float32
    assert out.light["top"]["sheets"] == 12
    regions = out.light["top"]["regions"]
    assert regions["inside"] > 0 and regions["behind"] > 0  # the ring / the ground
    assert {"render_compile_s", "render_s", "prepare_s"} <= set(out.timings)
    assert r.settings()["solver"] == "splat"


@pytest.mark.parametrize("similarity", [True, pytest.param(False, marks=pytest.mark.slow)])
def test_gradients_match_finite_differences(x64, similarity):
    sc = df.load_scene("cloud-plane", ["fog.scattering=20"])
    sc = sc.replace(cameras=tuple(_small(c) for c in sc.cameras))
    r = df.SplatRenderer(sc, resolution=10, sheets=10, similarity=similarity)
    p0 = r.params(jnp.float64)
    w = {n: jnp.asarray(np.random.default_rng(1).uniform(0.5, 1.5, (c.height, c.width)))
         for n, c in zip([c.name for c in r.cameras], r.cameras)}

    def loss(p):
        imgs = r(p)
        return sum(jnp.sum(w[n] * imgs[n]) for n in imgs)

    grad = jax.jit(jax.grad(loss))(p0)
    f = jax.jit(loss)
    paths = ["fog.scattering", "fog.absorption", "fog.g", "shape.ground.albedo",
             "shape.airplane.albedo", "sun.irradiance", "sky.radiance"]
    for path in paths:
        x = float(df.get_param(p0, sc, path))
        eps = 1e-6 * max(1.0, abs(x))
        fd = (f(df.set_param(p0, sc, path, x + eps)) - f(df.set_param(p0, sc, path, x - eps))) / (
            2 * eps)
        g = float(df.get_param(grad, sc, path))
        assert g == pytest.approx(float(fd), rel=1e-5, abs=1e-8), path


def _small(c):
    import dataclasses

    return dataclasses.replace(c, resolution=(12, 10))


@pytest.mark.parametrize("name", ["fog-balls", "ring-box"])
def test_culled_ray_casting_is_bit_identical_to_brute_force(name):
    # the bounding-volume hierarchy only skips faces a ray cannot hit first: same t, face and
    # barycentrics, bit for bit, as testing every ray against every face (ties: lowest face)
    from difffog._camera import camera_rays
    from difffog._raster import _cast_rays_brute, cast_rays, scene_triangles

    sc = df.load_scene(name)
    tris = scene_triangles(sc)
    rng = np.random.default_rng(0)
    import dataclasses

    o, d = camera_rays(dataclasses.replace(sc.cameras[1], resolution=(24, 18)), 1)
    o, d = o.reshape(-1, 3), d.reshape(-1, 3)
    # random rays from inside and around the domain, some along the axes and some starting on
    # a face of the box walls (0·inf in the slab test), and light-like parallel rays
    ro = rng.uniform(-0.2, 1.2, (600, 3))
    rd = rng.normal(size=(600, 3))
    rd[:100] = np.eye(3)[rng.integers(0, 3, 100)] * rng.choice([-1.0, 1.0], (100, 1))
    ro[100:150, 2] = 0.05  # the floor's top face in fog-balls
    rd /= np.linalg.norm(rd, axis=1, keepdims=True)
    lo = np.concatenate([o, ro, rng.uniform(0, 1, (400, 3)) + [0, 0, 2.0]])
    ld = np.concatenate([d, rd, np.broadcast_to([0.3, -0.2, -0.93], (400, 3))])
    for t_min in (0.0, 1e-7):
        new = cast_rays(tris, lo, ld, t_min=t_min)
        ref = _cast_rays_brute(tris, lo, ld, t_min=t_min)
        assert np.isfinite(ref[0]).mean() > 0.5  # the rays do hit things
        for a, b in zip(new, ref):
            assert a.dtype == b.dtype
            np.testing.assert_array_equal(a, b)


# ---------------------------------------------------------------- against Mitsuba 3 (slow)
# The default splat (similarity-scaled sheets, forward + back scattering, one sheet per voxel,
# N = 64) against the shared Mitsuba 3 references: relative RMSE with the reference noise removed
# in quadrature and the bias of the mean, as `benchmarks/validate_splat.py` measured them
# (`benchmarks/results/splat_references.md`), with a margin of one point.  The render is
# deterministic; the margin covers XLA/CPU differences, not noise.
REFS = Path(__file__).resolve().parents[2] / "shared" / "references"
SPLAT_VS_MITSUBA = {  # (scene, camera): (rel. RMSE corr. bound, |bias| bound); measured
    ("cloud-plane", "top"): (0.143, 0.019),  # 0.1328, -0.0094
    ("cloud-plane", "oblique"): (0.377, 0.066),  # 0.3670, -0.0556
    ("translucent-cube", "top"): (0.140, 0.026),  # 0.1293, -0.0164
    ("translucent-cube", "oblique"): (0.279, 0.092),  # 0.2687, -0.0817
}


@pytest.mark.slow
@pytest.mark.parametrize("name", ["cloud-plane", "translucent-cube"])
def test_default_splat_matches_the_monte_carlo_references(name):
    if not REFS.exists():
        pytest.skip(f"shared references not available ({REFS})")
    images = df.SplatRenderer(df.load_scene(name), resolution=64).render().images
    for cam, img in images.items():
        ref = np.load(REFS / name / f"{cam}.npy").astype(np.float64)
        with open(REFS / name / f"{cam}_stats.json") as f:
            noise = float(json.load(f)["ref_noise_rmse"])
        img = np.asarray(img, np.float64)
        assert img.shape == ref.shape
        mean = ref.mean()
        rmse = math.sqrt(np.mean((img - ref) ** 2))
        err = math.sqrt(max(rmse**2 - noise**2, 0.0)) / mean
        bias = img.mean() / mean - 1.0
        max_err, max_bias = SPLAT_VS_MITSUBA[(name, cam)]
        assert err < max_err, (name, cam, err)
        assert abs(bias) < max_bias, (name, cam, bias)
