"""Cameras: ray generation, and the lattice ray march against analytic answers."""

import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from difffog import Camera, SceneError
from difffog.forward._camera import camera_basis, camera_rays, hg_phase
from difffog.forward.sweep._march import (
    LatticeFields,
    camera_hits,
    forward_mode,
    march_steps,
    render_camera,
    render_rays,
    trace_rays,
)


@pytest.fixture
def x64():
    prev = jax.config.jax_enable_x64
    jax.config.update("jax_enable_x64", True)
    yield
    jax.config.update("jax_enable_x64", prev)


def persp(position=(0, 0, 0), look_at=(0, 1, 0), up=(0, 0, 1), fov=60.0, res=(9, 7)):
    return Camera("p", "perspective", tuple(map(float, position)), tuple(map(float, look_at)),
                  tuple(map(float, up)), res, fov_deg=fov)


def ortho(position, look_at, up=(0, 1, 0), extent=(1.0, 1.0), res=(16, 16)):
    return Camera("o", "orthographic", tuple(map(float, position)), tuple(map(float, look_at)),
                  tuple(map(float, up)), res, extent=extent)


def fields(n=(8, 8, 8), h=1 / 8, origin=(0, 0, 0), sigma=0.0, j_iso=0.0, j_sun=0.0, rad=0.0,
           sdf=10.0, **kw):
    full = lambda v: np.broadcast_to(np.asarray(v, np.float64), n).copy()  # noqa: E731
    return LatticeFields(sigma_t=full(sigma), j_iso=full(j_iso), j_sun=full(j_sun),
                         radiosity_ext=full(rad), sdf=full(sdf), origin=origin, h=h, **kw)


# ------------------------------------------------------------------------------------------
# (a) ray generation
# ------------------------------------------------------------------------------------------
@pytest.mark.parametrize("s", [1, 2, 3])
def test_centre_pixel_looks_at_target(s):
    cam = persp(position=(1, 2, 3), look_at=(2, 4, 2.5), up=(0, 0, 1), res=(9, 7))
    o, d = camera_rays(cam, s)
    assert o.shape == d.shape == (7, 9, s * s, 3) and o.dtype == np.float64
    np.testing.assert_allclose(np.linalg.norm(d, axis=-1), 1.0, rtol=1e-12)
    fwd = np.subtract(cam.look_at, cam.position)
    fwd /= np.linalg.norm(fwd)
    mean = d[3, 4].mean(axis=0)
    np.testing.assert_allclose(mean / np.linalg.norm(mean), fwd, atol=1e-12)
    np.testing.assert_allclose(o, np.broadcast_to(cam.position, o.shape))


def test_left_column_points_left_and_row0_is_top():
    cam = persp(position=(0, 0, 0), look_at=(0, 1, 0), up=(0, 0, 1), res=(9, 7))
    fwd, right, up = camera_basis(cam)
    np.testing.assert_allclose(right, [1, 0, 0], atol=1e-15)  # forward × up = +x here
    np.testing.assert_allclose(up, [0, 0, 1], atol=1e-15)
    _, d = camera_rays(cam, 1)
    assert (d[:, 0, 0] @ right < 0).all() and (d[:, -1, 0] @ right > 0).all()
    assert (d[0, :, 0] @ up > 0).all() and (d[-1, :, 0] @ up < 0).all()
    # monotone across the image
    assert (np.diff(d[3, :, 0, 0]) > 0).all() and (np.diff(d[:, 4, 0, 2]) < 0).all()


def test_top_view_orientation():
    """The shared scenes' top view: +x to the right, +y up the image."""
    cam = ortho((0.5, 0.5, 1.5), (0.5, 0.5, 0.0), up=(0, 1, 0), res=(4, 4))
    o, d = camera_rays(cam, 1)
    np.testing.assert_allclose(d, np.broadcast_to([0, 0, -1.0], d.shape), atol=1e-15)
    assert o[0, 0, 0, 0] < 0.5 and o[0, 0, 0, 1] > 0.5  # top-left pixel: -x, +y


@pytest.mark.parametrize("s", [1, 2, 3])
def test_orthographic_origins_span_extent(s):
    cam = ortho((1, 2, 5), (1, 2, 0), up=(0, 1, 0), extent=(2.0, 1.5), res=(8, 6))
    o, d = camera_rays(cam, s)
    fwd, right, up = camera_basis(cam)
    rel = o - np.asarray(cam.position)
    x, y = rel @ right, rel @ up
    np.testing.assert_allclose(rel @ fwd, 0.0, atol=1e-14)
    half_w, half_h = 1.0, 0.75
    np.testing.assert_allclose([x.min(), x.max()], [-half_w + 2 * half_w / (8 * 2 * s),
                                                    half_w - 2 * half_w / (8 * 2 * s)])
    np.testing.assert_allclose([y.min(), y.max()], [-half_h + 2 * half_h / (6 * 2 * s),
                                                    half_h - 2 * half_h / (6 * 2 * s)])
    # the mean over S is the pixel centre (box filter), row 0 at the top
    cx = -half_w + (np.arange(8) + 0.5) * 2 * half_w / 8
    cy = half_h - (np.arange(6) + 0.5) * 2 * half_h / 6
    np.testing.assert_allclose(x.mean(-1), np.broadcast_to(cx, (6, 8)), atol=1e-14)
    np.testing.assert_allclose(y.mean(-1), np.broadcast_to(cy[:, None], (6, 8)), atol=1e-14)
    np.testing.assert_allclose(d, np.broadcast_to(fwd, d.shape), atol=1e-15)


@pytest.mark.parametrize("fov", [30.0, 60.0, 120.0])
def test_horizontal_fov(fov):
    cam = persp(position=(0.3, -1, 0.2), look_at=(1, 2, -0.5), up=(0, 0, 1), fov=fov,
                res=(11, 5))
    fwd, right, up = camera_basis(cam)
    _, d = camera_rays(cam, 3)  # odd H and s: sub-row 1 of row 2 is the horizontal midline
    plane = d / (d @ fwd)[..., None]  # points on the image plane at distance 1
    row = plane[2].reshape(11, 3, 3, 3)[:, 1]  # (W, sub-column, 3)
    step = row[0, 1] - row[0, 0]  # sub-samples are 1/3 pixel apart, the first 1/6 in
    left = row[0, 0] - step / 2
    right_edge = row[-1, 2] + step / 2
    cosang = left @ right_edge / (np.linalg.norm(left) * np.linalg.norm(right_edge))
    assert math.degrees(math.acos(cosang)) == pytest.approx(fov, abs=1e-9)
    # the vertical field of view follows from the aspect ratio (square pixels)
    col = plane[:, 5].reshape(5, 3, 3, 3)[:, :, 1]  # (H, sub-row, 3)
    top, bottom = col[0, 0] - (col[0, 1] - col[0, 0]) / 2, col[-1, 2] + (col[0, 1] - col[0, 0]) / 2
    assert np.linalg.norm(top - bottom) == pytest.approx(
        2 * math.tan(math.radians(fov) / 2) * 5 / 11, rel=1e-12)


def test_bad_cameras():
    with pytest.raises(SceneError, match="parallel"):
        camera_rays(persp(look_at=(0, 0, 1), up=(0, 0, 1)))
    with pytest.raises(SceneError, match="fov"):
        camera_rays(persp(fov=180.0))
    with pytest.raises(ValueError, match="supersample"):
        camera_rays(persp(), 0)


# ------------------------------------------------------------------------------------------
# (b), (c) transport through homogeneous fog
# ------------------------------------------------------------------------------------------
@pytest.mark.parametrize("step", [None, 0.07])
def test_beer_lambert_looking_up(x64, step):
    sigma, sky = 1.7, 2.5
    f = fields(n=(8, 8, 10), h=0.125, origin=(-0.5, -0.5, 0.0), sigma=sigma, sky=sky)
    z0 = 0.05  # inside the bottom of the domain (top at 1.25)
    cam = ortho((0, 0, z0), (0, 0, 1), up=(0, 1, 0), extent=(0.9, 0.9), res=(6, 6))
    img = render_camera(f, cam, supersample=2, step=step)
    assert img.shape == (6, 6) and img.dtype == jnp.float64
    np.testing.assert_allclose(img, sky * math.exp(-sigma * (1.25 - z0)), rtol=1e-6)


@pytest.mark.parametrize("sigma", [0.8, 0.0])
def test_constant_emission_looking_down(x64, sigma):
    j, depth = 0.6, 1.0
    f = fields(n=(8, 8, 8), h=0.125, sigma=sigma, j_iso=j, sky=3.0)  # no sky from below
    expect = lambda L: j * L if sigma == 0 else j / sigma * -math.expm1(-sigma * L)  # noqa
    cam = ortho((0.5, 0.5, 2.0), (0.5, 0.5, 0.0), extent=(0.8, 0.8), res=(5, 5))
    img = np.asarray(render_camera(f, cam, supersample=2))
    assert np.isfinite(img).all()
    np.testing.assert_allclose(img, expect(depth), rtol=1e-6)
    # oblique rays from above, through the top face and out of a side (partial last step)
    d = np.array([[0.3, 0.2, -1.0], [-0.5, 0.1, -1.0], [0.05, -0.9, -0.4]])
    d /= np.linalg.norm(d, axis=-1, keepdims=True)
    o = np.array([0.5, 0.5, 1.0]) - 0.5 * d  # each enters the top face at (0.5, 0.5, 1)
    t_out = np.min(np.where(d != 0, (np.where(d > 0, 1.0, 0.0) - (o + 0.5 * d)) / d, np.inf), -1)
    out = np.asarray(render_rays(f, o, d))
    np.testing.assert_allclose(out, [expect(t) for t in t_out], rtol=1e-6)


def test_no_nan_gradient_at_zero_extinction(x64):
    f = fields(sigma=0.0, j_iso=1.0)
    o, d = np.array([[0.5, 0.5, 2.0]]), np.array([[0.0, 0.0, -1.0]])
    scale = lambda a: render_rays(eqx_replace(f, sigma_t=a * f.sigma_t + a), o, d).sum()  # noqa
    g = jax.grad(scale)(0.0)
    assert g == pytest.approx(-0.5, rel=1e-9)  # d/dσ of (1 - e^{-σ})/σ at 0, L = 1


def eqx_replace(f, **changes):
    import equinox as eqx

    return eqx.tree_at(lambda m: [getattr(m, k) for k in changes], f, list(changes.values()))


def test_rays_missing_the_box():
    f = fields(sigma=5.0, sky=2.0)
    o = np.array([[5.0, 5.0, 5.0], [5.0, 5.0, 5.0], [0.5, 0.5, 5.0], [2.0, 0.5, 0.5]])
    d = np.array([[0.0, 0.0, 1.0], [0.0, 0.0, -1.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])
    r = trace_rays(f, o, d)
    np.testing.assert_allclose(r.radiance, [2.0, 0.0, 0.0, 0.0])  # horizontal rays: no sky
    np.testing.assert_allclose(r.transmittance, 1.0)
    assert not r.hit.any()


# ------------------------------------------------------------------------------------------
# (d) surfaces
# ------------------------------------------------------------------------------------------
def test_sphere_hit_area_and_depth(x64):
    n, c, r = 64, np.array([0.5, 0.5, 0.5]), 0.3
    h = 1.0 / n
    x = (np.arange(n) + 0.5) * h
    P = np.stack(np.meshgrid(x, x, x, indexing="ij"), -1)
    sdf = np.linalg.norm(P - c, axis=-1) - r
    f = fields(n=(n,) * 3, h=h, rad=1.0, sky=0.0)
    f = eqx_replace(f, sdf=jnp.asarray(sdf))
    res = 128
    cam = ortho((0.5, 0.5, 1.5), (0.5, 0.5, 0.0), extent=(1.0, 1.0), res=(res, res))
    img = np.asarray(render_camera(f, cam, supersample=2))
    area = (img > 0.5).sum() / res**2
    assert area == pytest.approx(math.pi * r * r, rel=0.02)
    assert img.max() == pytest.approx(1.0, abs=1e-9) and img.min() == 0.0
    # depth against the analytic ray-sphere intersection, away from the grazing rim
    o, d = camera_rays(cam, 1)
    o, d = o.reshape(-1, 3), d.reshape(-1, 3)
    out = trace_rays(f, o, d)
    b2 = ((o[:, :2] - c[:2]) ** 2).sum(-1)
    inner = b2 < (0.9 * r) ** 2
    t_true = (o[:, 2] - c[2]) - np.sqrt(np.maximum(r * r - b2, 0.0))
    assert np.asarray(out.hit)[inner].all() and not np.asarray(out.hit)[b2 > (1.05 * r) ** 2].any()
    err = np.abs(np.asarray(out.depth)[inner] - t_true[inner])
    assert err.max() < h / 4


def test_surface_behind_fog_and_camera_in_solid(x64):
    sigma = 1.3
    n = 8
    z = (np.arange(n) + 0.5) / n
    sdf = np.broadcast_to(z - 0.3, (n, n, n)).copy()  # floor: solid below z = 0.3
    f = eqx_replace(fields(sigma=sigma, rad=0.7, sky=5.0), sdf=jnp.asarray(sdf))
    o = np.array([[0.5, 0.5, 2.0], [0.5, 0.5, 0.1]])
    d = np.array([[0.0, 0.0, -1.0], [0.0, 0.0, 1.0]])
    r = trace_rays(f, o, d)
    np.testing.assert_allclose(r.depth[0], 2.0 - 0.3, rtol=1e-9)
    np.testing.assert_allclose(r.radiance[0], 0.7 * math.exp(-sigma * 0.7), rtol=1e-9)
    assert bool(r.hit[1]) and float(r.depth[1]) == 0.0  # starts inside the solid: hit at once


# ------------------------------------------------------------------------------------------
# (e) phase function and the sun term
# ------------------------------------------------------------------------------------------
@pytest.mark.parametrize("g", [-0.5, 0.0, 0.85])
def test_hg_normalised(x64, g):
    # Gauss-Legendre in μ = cos θ (the azimuth integral is 2π): ∫ p dΩ = 2π ∫ p(μ) dμ
    mu, w = np.polynomial.legendre.leggauss(400)
    total = 2 * math.pi * float(np.sum(w * np.asarray(hg_phase(mu, g))))
    assert total == pytest.approx(1.0, rel=1e-8)
    mean_cos = 2 * math.pi * float(np.sum(w * mu * np.asarray(hg_phase(mu, g))))
    assert mean_cos == pytest.approx(g, abs=1e-8)
    if g == 0.0:
        np.testing.assert_allclose(hg_phase(mu, g), 1 / (4 * math.pi), rtol=1e-15)


def test_sun_term_uses_forward_scattering(x64):
    """Looking towards the sun is forward scattering: cos θ = dot(sun_dir, d)."""
    g, j, L = 0.6, 0.9, 1.0
    sun = np.array([0.0, 0.6, 0.8])
    f = fields(j_sun=j, g=g, sun_dir=tuple(sun))
    o = np.array([[0.5, 0.5, 2.0], [0.5, 0.5, -1.0], [0.5, 0.5, 2.0]])
    d = np.array([[0.0, 0.0, -1.0], [0.0, 0.0, 1.0], [0.0, 0.0, -1.0]])
    out = np.asarray(render_rays(f, o, d))
    np.testing.assert_allclose(out[:2], [j * L * float(hg_phase(-0.8, g)),
                                         j * L * float(hg_phase(0.8, g))], rtol=1e-9)
    assert out[1] > out[0]
    no_sun = fields(j_sun=j, g=g)  # sun_dir None: the j_sun term is off
    np.testing.assert_allclose(render_rays(no_sun, o, d), 0.0)


# ------------------------------------------------------------------------------------------
# (f) gradients
# ------------------------------------------------------------------------------------------
@pytest.mark.slow  # the suite's budget; the default camera path's (exact hits) is checked by
# test_exact_hit_gradients_match_finite_differences
def test_gradients_match_finite_differences(x64):
    rng = np.random.default_rng(0)
    n = (10, 9, 8)
    h = 0.1
    P = np.stack(np.meshgrid(*[(np.arange(k) + 0.5) * h for k in n], indexing="ij"), -1)
    sdf = np.linalg.norm(P - [0.5, 0.45, 0.2], axis=-1) - 0.25
    base = LatticeFields(
        sigma_t=1.0 + 0.5 * rng.random(n), j_iso=0.3 * rng.random(n), j_sun=rng.random(n),
        radiosity_ext=0.5 + rng.random(n), sdf=sdf, origin=(0, 0, 0), h=h,
        g=0.5, sun_dir=(0.3, -0.2, 0.9), sky=1.5)
    cams = [persp(position=(0.5, -0.6, 1.2), look_at=(0.5, 0.45, 0.3), fov=50, res=(8, 6)),
            ortho((0.5, 0.45, 0.01), (0.5, 0.45, 1.0), extent=(0.9, 0.8), res=(5, 4))]

    def loss(a, sky, g):
        f = eqx_replace(base, sigma_t=a * base.sigma_t, sky=sky, g=g)
        return sum(render_camera(f, c, supersample=2).sum() for c in cams)

    args = (1.0, 1.5, 0.5)
    grads = jax.jit(jax.grad(loss, argnums=(0, 1, 2)))(*args)
    loss = jax.jit(loss)
    for i, gr in enumerate(grads):
        eps = 1e-5
        hi = list(args); hi[i] += eps  # noqa: E702
        lo = list(args); lo[i] -= eps  # noqa: E702
        fd = (loss(*hi) - loss(*lo)) / (2 * eps)
        assert float(gr) == pytest.approx(float(fd), rel=1e-5), i
        assert abs(float(gr)) > 1e-3
    # every float field has a finite gradient
    gf = jax.jit(jax.grad(lambda f: render_camera(f, cams[0]).sum()))(base)
    for name in ("sigma_t", "j_iso", "j_sun", "radiosity_ext", "sdf", "g", "sky"):
        assert np.isfinite(getattr(gf, name)).all(), name


def _exact_hit_scene():
    """The small scene of ``_exact_hit_case``: a sphere and a floor under a sun."""
    import difffog as df

    return df.Scene(title="t", domain=df.Domain((0, 0, 0), (1.0, 0.9, 0.8)),
                    sun=df.Sun(2.0, 30.0, 40.0),
                    shapes=[df.Sphere("ball", center=(0.5, 0.45, 0.3), radius=0.2),
                            df.Quad("floor", corners=((0, 0, 0.05), (1, 0, 0.05),
                                                      (1, 0.9, 0.05), (0, 0.9, 0.05)))])


def _exact_hit_case(sun_apart: bool):
    """(fields, camera, hits, fields_at): a small scene's exact hits (a sphere, a floor, the
    sky) through random fields in float64, camera inside the fog; fields_at(a, e, alb, em)
    scales σ_t (and the sun's extinction and depth), the irradiance, the albedos and the
    emissions."""
    rng = np.random.default_rng(1)
    n, h = (10, 9, 8), 0.1
    scene = _exact_hit_scene()
    cam = persp(position=(0.2, 0.1, 0.6), look_at=(0.5, 0.45, 0.2), fov=70, res=(6, 5))
    density = 0.5 + rng.random(n)
    hits = camera_hits(scene, cam, 2, density, (0, 0, 0), h, n)
    assert {0, 1} <= set(np.unique(np.asarray(hits.shape)).tolist())  # both shapes and the sky
    nrm = rng.normal(size=n + (3,))
    nrm /= np.linalg.norm(nrm, axis=-1, keepdims=True)
    base = LatticeFields(
        sigma_t=density, j_iso=0.3 * rng.random(n), j_sun=rng.random(n),
        radiosity_ext=np.zeros(n), sdf=np.full(n, 10.0), origin=(0, 0, 0), h=h, g=0.5,
        sun_dir=tuple(scene.sun.direction), sky=1.5, surface_normal=nrm,
        irradiance=0.5 + rng.random(n), albedo=np.array([0.6, 0.3]),
        emission=np.array([0.1, 0.0]), sun_irradiance=2.0, sun_extinction=1.0,
        **(dict(sun_depth=3.0 * rng.random(n), fog_box=((0.05, 0.0, 0.1), (0.95, 0.9, 0.7)))
           if sun_apart else {}))

    def fields_at(a, e, alb, em):
        f = eqx_replace(base, sigma_t=a * base.sigma_t, irradiance=e * base.irradiance,
                        albedo=alb * base.albedo, emission=em * base.emission,
                        sun_extinction=a * base.sun_extinction)
        return eqx_replace(f, sun_depth=a * base.sun_depth) if sun_apart else f

    return base, cam, hits, fields_at


@pytest.mark.parametrize("sun_apart", [False, True])
def test_exact_hit_gradients_match_finite_differences(x64, sun_apart):
    """The march with exact hits (fog up to the hit, the hit's irradiance, albedo, emission and
    its sun through the fog) against central differences, camera inside the fog.
    ``sun_apart``: the fog's single scattering of the sun attenuated along each step by the
    optical depth towards the sun (``sun_depth``), the march clipped to a fog box."""
    _, cam, hits, fields_at = _exact_hit_case(sun_apart)

    def loss(a, e, alb, em):
        return render_camera(fields_at(a, e, alb, em), cam, supersample=2, hits=hits).sum()

    args = (1.0, 1.0, 1.0, 1.0)
    value_and_grad = jax.jit(jax.value_and_grad(loss, argnums=(0, 1, 2, 3)))
    _, grads = value_and_grad(*args)
    for i, gr in enumerate(grads):
        eps = 1e-6
        hi = list(args); hi[i] += eps  # noqa: E702
        lo = list(args); lo[i] -= eps  # noqa: E702
        fd = (value_and_grad(*hi)[0] - value_and_grad(*lo)[0]) / (2 * eps)
        assert float(gr) == pytest.approx(float(fd), rel=1e-6), i
        assert abs(float(gr)) > 1e-3


def test_forward_mode_march_gives_the_reverse_modes_jacobian(x64):
    """Inside ``forward_mode()`` the cameras take ``jax.jvp`` (the plain scan; a fit's
    Jacobian columns): the same image Jacobian as reverse mode through the march's
    hand-written backward pass, in float64, for every kind of input the march reads; outside
    it, ``jax.jvp`` is refused (a custom VJP has no forward mode)."""
    _, cam, hits, fields_at = _exact_hit_case(True)
    x = jnp.ones(4)

    def image(x):
        return render_camera(fields_at(*x), cam, supersample=2, hits=hits).ravel()

    with forward_mode():
        fwd = jax.jit(jax.jacfwd(image))(x)
    rev = jax.jit(jax.jacrev(image))(x)
    assert np.abs(rev).max(axis=0).min() > 1e-3  # every column seen
    np.testing.assert_allclose(fwd, rev, rtol=1e-10, atol=1e-12 * float(np.abs(rev).max()))
    with pytest.raises(TypeError, match="custom_vjp"):
        jax.jvp(image, (x,), (x,))


def _two_cameras():
    """(fields, fields_at, cameras, hits) of ``_exact_hit_case``'s scene seen by a camera whose
    rays end soon (on the floor) and one that looks across the box."""
    base, _, _, fields_at = _exact_hit_case(True)
    scene = _exact_hit_scene()
    cams = [persp(position=(0.15, 0.15, 0.3), look_at=(0.15, 0.2, 0.0), fov=30, res=(6, 5)),
            persp(position=(0.95, 0.85, 0.75), look_at=(0.1, 0.1, 0.1), fov=40, res=(5, 4))]
    hits = [camera_hits(scene, c, 2, np.asarray(base.sigma_t), (0, 0, 0), 0.1, (10, 9, 8))
            for c in cams]
    assert hits[1].max_length > 3 * hits[0].max_length  # the far camera marches longer
    return base, fields_at, cams, hits


def test_cameras_marched_together_equal_each_alone(x64, monkeypatch):
    """``render_cameras`` marches several cameras' rays together in at most ``lanes`` marches
    (one compiled march body per lane however many cameras), each chunk of rays for its own
    rays' step count: the images equal those of each camera marched alone (capped at its own
    longest path), though the second camera's paths are longer than the first's, whose chunk
    stops well short of them.  (Without exact hits, and the gradient: the slow test below.)"""
    from difffog.forward.sweep import _march as cm

    base, _, cams, hits = _two_cameras()
    alone = [render_camera(base, c, supersample=2, hits=h) for c, h in zip(cams, hits)]
    # one lane in many small chunks (the last one padded, each with its own steps), and two
    # lanes in the backend's chunks (``MARCH_CHUNK_CPU`` here, or as given)
    assert cm.march_chunk() == cm.MARCH_CHUNK_CPU and cm.march_chunk(100) == 100
    assert sum(h.pixel.shape[0] for h in hits) < cm.MARCH_CHUNK_CPU
    for lanes, chunk in ((1, 7), (2, None)):
        together = cm.render_cameras(base, cams, supersample=2, hits=hits, lanes=lanes,
                                     chunk=chunk)
        for a, b in zip(together, alone):
            np.testing.assert_allclose(a, b, rtol=1e-12, atol=1e-14)
    # the near camera's rays end long before the far one's: its chunk takes fewer steps
    near = hits[0]
    cfg = cm._MarchConfig(((0.0, 0.0, 0.0), 0.1, (10, 9, 8), False), 0,
                          cm.step_count(hits[1].max_length, 0.05), 0.05)
    t0 = jnp.zeros(near.t.shape[0])
    assert int(cm._live_steps(t0, jnp.minimum(near.t, near.max_length), cfg)) < cfg.n_steps
    assert cm.march_lanes([5.0, 1.0, 1.0, 1.0, 4.0], 2) == [[0, 2], [1, 3, 4]]
    # a CPU's own choice: one lane (as fast at 4096-ray chunks, half the compile)
    assert cm.march_lanes([5.0, 1.0, 4.0]) == [[0, 1, 2]]
    assert sorted(cm.march_lanes([1.0, 2.0], 4)) == [[0], [1]]  # no more lanes than cameras
    # off a CPU (a GPU): one march per camera over its static step count, the same images
    # (another chunk size: a new trace, which reads the backend's choice)
    monkeypatch.setattr(cm, "_chunk_steps", lambda: False)
    assert cm.march_lanes([5.0, 1.0, 4.0]) == [[0], [2], [1]]
    for a, b in zip(cm.render_cameras(base, cams, supersample=2, hits=hits, chunk=2048), alone):
        np.testing.assert_allclose(a, b, rtol=1e-12, atol=1e-14)


@pytest.mark.slow  # ~25 s: four more marches to compile, two of them gradients
def test_cameras_marched_together_without_hits_and_their_gradient(x64, monkeypatch):
    """As above, without exact hits (the lattice's sdf), and the gradient through one lane of
    both cameras against the sum of each camera's alone; and off a CPU's choice (one march per
    camera over its static step count) the same gradient."""
    from difffog.forward.sweep import _march as cm

    base, fields_at, cams, hits = _two_cameras()
    plain = cm.render_cameras(base, cams, supersample=1, lanes=1)
    for a, c in zip(plain, cams):
        np.testing.assert_allclose(a, render_camera(base, c, supersample=1), rtol=1e-12,
                                   atol=1e-14)

    def loss(x, together):
        f = fields_at(*x)
        if together:
            return sum(i.sum() for i in cm.render_cameras(f, cams, hits=hits, lanes=1))
        return sum(render_camera(f, c, hits=h).sum() for c, h in zip(cams, hits))
    x = jnp.ones(4)
    g1, g2 = (jax.jit(jax.grad(lambda x, t=t: loss(x, t)))(x) for t in (True, False))
    assert float(jnp.min(jnp.abs(g2))) > 1e-3
    np.testing.assert_allclose(g1, g2, rtol=1e-10)
    monkeypatch.setattr(cm, "_chunk_steps", lambda: False)
    g3 = jax.jit(jax.grad(lambda x: sum(
        i.sum() for i in cm.render_cameras(fields_at(*x), cams, hits=hits, chunk=2048))))(x)
    np.testing.assert_allclose(g3, g2, rtol=1e-10)


# ------------------------------------------------------------------------------------------
# (g) periodic slabs
# ------------------------------------------------------------------------------------------
@pytest.mark.parametrize("zenith_deg", [0.0, 45.0, 70.0])
def test_periodic_slab_oblique(x64, zenith_deg):
    sigma, thick, sky = 0.9, 0.5, 2.0
    f = fields(n=(4, 4, 4), h=0.125, sigma=sigma, sky=sky, periodic_xy=True)
    th = math.radians(zenith_deg)
    d = np.array([[math.sin(th), 0.3 * math.sin(th), math.cos(th)]])
    d /= np.linalg.norm(d)
    o = np.array([[3.7, -2.2, -0.4]])  # far outside the lattice laterally
    out = np.asarray(render_rays(f, o, d))
    np.testing.assert_allclose(out, sky * math.exp(-sigma * thick / d[0, 2]), rtol=1e-6)
    # a non-periodic lattice at the same place is missed entirely
    f_open = fields(n=(4, 4, 4), h=0.125, sigma=sigma, sky=sky)
    np.testing.assert_allclose(render_rays(f_open, o, d), sky)


def test_march_steps():
    f = fields(n=(8, 8, 8), h=0.125)
    assert march_steps(f, 0.0625) == math.ceil(math.sqrt(3) / 0.0625) + 1
    o, d = np.array([[0.5, 0.5, 2.0]]), np.array([[0.0, 0.0, -1.0]])
    assert march_steps(f, 0.0625, o, d) == 16 + 1  # tight for concrete rays


def _rays_through_node_planes():
    """(fields, origins, directions): rays straight down through a random linear-scheme
    lattice, their march points falling on node planes every few steps (float64 under x64)."""
    rng = np.random.default_rng(0)
    n, h = (8, 7, 12), 1.0 / 12
    f = LatticeFields(sigma_t=1.0 + 5 * rng.random(n), j_iso=rng.random(n), j_sun=rng.random(n),
                      radiosity_ext=rng.random(n), sdf=np.full(n, 10.0), origin=(-0.25,) * 3,
                      h=h, g=0.5, sun_dir=(0.3, -0.2, 0.9), sky=1.0,
                      j_slope=rng.standard_normal(n + (6,)), sun_depth=3.0 * rng.random(n))
    R = 24
    o = np.column_stack([rng.uniform(-0.2, 0.3, (R, 2)), np.full(R, 1.5)])
    d = np.tile([0.0, 0.0, -1.0], (R, 1))
    return f, o, d


# slow: the default suite's 12-minute budget on 2 cores (stop 56);
# by default test_sweep.py's gradients against differences go through the compiled march
@pytest.mark.slow
def test_the_compiled_march_equals_the_march_op_by_op(x64):
    """Rays straight down through a linear-scheme lattice: their march points fall on node
    planes every few steps.  Compiled, XLA recomputed a point's coordinates in each fusion that
    read them, rounding them differently (FMA), and a point on a plane took its node from one
    rounding and its offset from the other, so that its slope channels read a whole spacing's
    offset: every ray here was off the same march run op by op (up to 0.034), cloud-plane's
    top camera 149 of 365 rays (up to 7%), and its image gradients 2-11% off central
    differences (test_anisotropic.py, slow).  The march now carries each point's coordinates
    through its scan: compiled and op by op agree to rounding."""
    f, o, d = _rays_through_node_planes()
    compiled = jax.jit(lambda f: render_rays(f, o, d))(f)
    with jax.disable_jit():
        plain = render_rays(f, o, d)
    assert float(jnp.min(plain)) > 0.02
    np.testing.assert_allclose(compiled, plain, rtol=1e-12, atol=1e-14)


def test_the_suites_xla_level_computes_what_users_run(x64):
    """The default suite compiles XLA's code at LLVM's -O0 (conftest.py: it is bound by
    compiles), users at XLA's default (-O3).  The two must compute the same values to rounding,
    or the suite would pass code that users' builds get wrong: the rounding-sensitive march of
    the test above (rays whose points fall on node planes, which -O3's FMA once read a whole
    spacing off), compiled at each level, agrees to 1e-12."""
    f, o, d = _rays_through_node_planes()
    march = {level: jax.jit(lambda f: render_rays(f, o, d),
                            compiler_options={"xla_backend_optimization_level": level})(f)
             for level in (0, 3)}
    assert float(jnp.min(march[3])) > 0.02
    np.testing.assert_allclose(march[0], march[3], rtol=1e-12, atol=1e-14)


# slow since stop 56 (the default suite's 12-minute budget on 2 cores; the periodic case
# before): by default the gradients against differences of test_sweep.py and test_camera.py
# go through this backward
@pytest.mark.slow
@pytest.mark.parametrize("periodic,slopes,sun", [
    (False, False, False), (False, True, True),
    (True, False, False)])
def test_custom_backward_matches_autodiff(x64, periodic, slopes, sun):
    """The march's hand-scheduled backward equals JAX's autodiff of the plain forward scan
    (``slopes``: with the linear scheme's six side slope channels, sampled with offsets; ``sun``:
    the sun's term apart, attenuated along each step by an optical-depth channel that grows
    and falls along the rays, so that both signs of the step's exponent occur, and dips below 0
    in places, where the exponent is held at 0)."""
    from difffog.forward.sweep import _march as cm

    rng = np.random.default_rng(1)
    n, h = (7, 6, 5), 0.15
    P = np.stack(np.meshgrid(*[(np.arange(k) + 0.5) * h for k in n], indexing="ij"), -1)
    sdf = np.linalg.norm(P - [0.5, 0.45, 0.3], axis=-1) - 0.2
    # σ_t, j_iso, two channels with per-ray coefficients (the sun's phase, an anisotropic
    # source's basis value, which has either sign), sdf
    chans = [0.5 + 3 * rng.random(n), rng.random(n), rng.random(n), rng.random(n) - 0.5]
    chans += ([0.3 * rng.standard_normal(n) for _ in range(cm.SLOPE_CHANNELS)] if slopes
              else [])
    chans += [5.0 * rng.random(n) - 1.0] if sun else []  # some < 0: the exponent held at 0
    chans += [sdf]
    table = cm._flat_table([jnp.asarray(c) for c in chans], jnp.float64)
    R = 40
    o = np.column_stack([rng.uniform(-0.2, 1.2, R), rng.uniform(-0.2, 1.1, R),
                         np.full(R, 1.2)])
    d = np.column_stack([rng.normal(0, 0.4, R), rng.normal(0, 0.4, R), -np.ones(R)])
    d /= np.linalg.norm(d, axis=-1, keepdims=True)
    o, d = jnp.asarray(o), jnp.asarray(d)
    lo, hi = jnp.zeros(3), jnp.asarray(n) * h
    t0, t1 = cm._clip(lo, hi, o, d, periodic, jnp)
    valid = t1 > t0
    t0 = jnp.where(valid, t0, 0.0)
    t_end = jnp.where(valid, jnp.minimum(t1, t0 + 2.0), 0.0)
    cfg = cm._MarchConfig(((0.0, 0.0, 0.0), h, n, periodic), 2, 40, h / 2, slopes=slopes,
                          sun_exp=sun)
    phase = jnp.asarray(rng.random((R, 2)))
    wT, wL, wH = (jnp.asarray(rng.random(R)) for _ in range(3))

    def loss(march):
        def f(tab, ph):
            T, L, t_hit = march(tab, ph)
            return jnp.sum(wT * T + wL * L + wH * jnp.where(jnp.isfinite(t_hit), t_hit, 0.0))
        return jax.jit(jax.grad(f, argnums=(0, 1)))(table, phase)

    custom = loss(lambda tab, ph: cm._march(tab, ph, o, d, t0, t_end, cfg))
    plain = loss(lambda tab, ph: [
        cm._march_fused(tab, ph, o, d, t0, t_end, cfg, every_step=True)[i] for i in (0, 1, 3)])
    hits = np.isfinite(cm._march(table, phase, o, d, t0, t_end, cfg)[2])
    assert 0 < hits.sum() < R and np.asarray(custom[0]).any()
    for a, b in zip(custom, plain):
        np.testing.assert_allclose(a, b, rtol=1e-10, atol=1e-12)
