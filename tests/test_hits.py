"""Exact geometry where camera rays meet surfaces: hits on the exact shapes, edge pixels with the
right mix of their surfaces, and the direct sun at a hit exact (shadow edges, Beer–Lambert)."""

import math

import numpy as np
import pytest

import difffog as df
from difffog.geometry._hits import first_hits
from difffog.geometry._rays import cast_rays, scene_triangles


def _rays_towards(center, spread, n, seed):
    rng = np.random.default_rng(seed)
    o = rng.normal(size=(n, 3))
    o = center + 3.0 * o / np.linalg.norm(o, axis=1, keepdims=True)
    target = center + spread * rng.uniform(-1, 1, size=(n, 3))
    d = target - o
    return o, d / np.linalg.norm(d, axis=1, keepdims=True)


def _scene(shapes, **kw):
    return df.Scene(title="t", domain=df.Domain((0, 0, 0), (1, 1, 1)), shapes=shapes, **kw)


SHAPES = {
    "sphere": (df.Sphere("s", center=(0.5, 0.5, 0.5), radius=0.3),
               lambda p: np.linalg.norm(p - 0.5, axis=-1) - 0.3),
    "torus": (df.Torus("t", center=(0.5, 0.5, 0.5), major_radius=0.3, minor_radius=0.1,
                       axis=(0.3, -0.2, 1.0)), None),
    "box": (df.Box("b", min=(0.3, 0.2, 0.4), max=(0.7, 0.6, 0.5)), None),
}


def _torus_sdf(p, s):
    a = np.asarray(s.axis) / np.linalg.norm(s.axis)
    v = p - np.asarray(s.center)
    z = v @ a
    rho = np.sqrt(np.maximum((v * v).sum(-1) - z * z, 0))
    return np.hypot(rho - s.major_radius, z) - s.minor_radius


def _box_sdf(p, s):
    lo, hi = np.asarray(s.min), np.asarray(s.max)
    q = np.abs(p - (lo + hi) / 2) - (hi - lo) / 2
    return np.linalg.norm(np.maximum(q, 0), axis=-1) + np.minimum(q.max(-1), 0)


@pytest.mark.parametrize("kind", sorted(SHAPES))
def test_hits_lie_on_the_exact_shape(kind):
    shape = SHAPES[kind][0]
    scene = _scene([shape])
    o, d = _rays_towards(np.full(3, 0.5), 0.45, 4000, seed=1)
    hits = first_hits(scene, o, d)
    p = o + np.where(hits.hit, hits.t, 0)[:, None] * d
    sdf = {"sphere": SHAPES["sphere"][1], "torus": lambda q: _torus_sdf(q, shape),
           "box": lambda q: _box_sdf(q, shape)}[kind]
    assert 0.1 < hits.hit.mean() < 0.95  # the rays sample hits and misses
    assert np.abs(sdf(p[hits.hit])).max() < 1e-9
    # the ray is outside the shape just before its hit (the first hit, not a later one)
    before = o + (hits.t - 1e-6)[:, None] * d
    assert (sdf(before[hits.hit]) > 0).all()
    # the normal is the shape's outward unit normal, facing the ray
    assert np.allclose(np.linalg.norm(hits.normal[hits.hit], axis=1), 1.0)
    assert ((hits.normal[hits.hit] * d[hits.hit]).sum(-1) <= 0).all()
    # against a fine tessellation (vertices on the shape)
    tris = scene_triangles(scene, sphere_subdivisions=5, torus_sections=(256, 96))
    t_mesh, face, _, _ = cast_rays(tris, o, d)
    met = face >= 0
    if kind == "box":  # the box's 12 triangles are the box
        assert np.array_equal(met, hits.hit)
        assert np.allclose(t_mesh[met], hits.t[met], atol=1e-12)
    elif kind == "sphere":  # convex: the mesh lies inside, so meeting it means meeting the shape
        assert hits.hit[met].all()
        assert (hits.t[met] <= t_mesh[met] + 1e-12).all()
        assert (hits.hit & ~met).mean() < 0.01  # the mesh misses a sliver at the silhouette
    else:  # the torus's saddle bulges out of its mesh: they agree to the mesh's chord error
        both = met & hits.hit
        dt = np.abs(hits.t[both] - t_mesh[both])  # chord error / the grazing cosine
        assert np.quantile(dt, 0.99) < 1e-3 and dt.max() < 1e-2
        assert (met != hits.hit).mean() < 0.01


def _top_camera(x0, x1, width):
    """An orthographic camera looking straight down at x ∈ [x0, x1] (pixels along x), one row."""
    span = x1 - x0
    return df.Camera("top", "orthographic", position=((x0 + x1) / 2, 0.5, 1.5),
                     look_at=((x0 + x1) / 2, 0.5, 0.0), up=(0.0, 1.0, 0.0),
                     resolution=(width, 1), extent=(span, span / width))


def _quad_edge_scene():
    """An emitting quad (radiance 1) whose edge x = 0.5 + 0.3·(pixel width) lies inside the
    third of four pixels, over black."""
    px = 0.05
    edge = 0.5 + 0.3 * px
    quad = df.Quad("q", corners=((edge, 0.0, 0.3), (1.0, 0.0, 0.3), (1.0, 1.0, 0.3),
                                 (edge, 1.0, 0.3)), albedo=0.0, emission=1.0)
    return _scene([quad], cameras=(_top_camera(0.5 - 2 * px, 0.5 + 2 * px, 4),))


def test_an_edge_pixel_mixes_its_two_surfaces_by_their_coverage():
    # the quad's edge pixel's value is the quad's share of its footprint
    scene = _quad_edge_scene()
    img = df.render(df.forward_model(scene, "sweep", resolution=16, M=2)).images["top"][0]
    np.testing.assert_allclose(img, [0.0, 0.0, 0.7, 1.0], atol=1.0 / 32)
    # with 2×2 samples per pixel and nothing else, this pixel would read 0.5
    assert abs(img[2] - 0.7) < 0.05


def _shadow_edge_scene(zen=30.0, gamma=2.0, a=0.5, F=2.0):
    """A black box above purely absorbing fog (γ, 0.4 deep) over a grey floor, no sky, the sun
    in the xz-plane; five pixels in a row, the third crossed by the box's shadow edge at 0.6
    of its width."""
    floor = df.Quad("floor", corners=((0, 0, 0.05), (1, 0, 0.05), (1, 1, 0.05), (0, 1, 0.05)),
                    albedo=a)
    box = df.Box("box", min=(0.55, 0.2, 0.7), max=(0.9, 0.8, 0.8), albedo=0.0)
    x_edge = 0.55 - (0.8 - 0.05) * math.tan(math.radians(zen))  # the shadow's left edge
    px = 0.02
    x0 = x_edge - 2.6 * px
    fog = df.Fog(scattering=0.0, absorption=gamma, region=((0, 0, 0.1), (1, 1, 0.5)))
    return _scene([floor, box], sun=df.Sun(F, zen, 0.0), fog=fog,
                  cameras=(_top_camera(x0, x0 + 5 * px, 5),))


def test_a_shadow_edge_and_the_sun_through_absorbing_fog_are_exact():
    # the lit floor's radiance is exactly albedo/π·F·cos θ·e^(-γ·0.4/cos θ) seen through
    # e^(-γ·0.4) (Beer–Lambert on both paths, nothing else lights it), the box's shadow is
    # black, and the pixel the shadow's edge crosses at 0.6 of its width reads 0.6
    zen, gamma, a, F = 30.0, 2.0, 0.5, 2.0
    scene = _shadow_edge_scene(zen, gamma, a, F)
    img = df.render(df.forward_model(scene, "sweep", resolution=20, M=2)).images["top"][0]
    mu = math.cos(math.radians(zen))
    lit = a / math.pi * F * mu * math.exp(-gamma * 0.4 / mu) * math.exp(-gamma * 0.4)
    # the fog's depth is integrated by the midpoint rule in steps of h/2 through the trilinear
    # density (towards the sun and along the camera's march): a few 1e-3 here
    np.testing.assert_allclose(img[:2], lit, rtol=5e-3)
    np.testing.assert_allclose(img / lit, [1.0, 1.0, 0.6, 0.0, 0.0], atol=1.0 / 32)


def test_edge_pixels_are_the_pixels_a_silhouette_or_a_shadow_edge_crosses():
    # (host only: the model's exact hits, no light solve) the quad's edge and the box's shadow
    # edge each cross one pixel of their row
    for scene, want in ((_quad_edge_scene(), [0, 0, 1, 0]),
                        (_shadow_edge_scene(), [0, 0, 1, 0, 0])):
        edges = df.forward_model(scene, "sweep", resolution=16, M=2).edge_pixels()
        assert set(edges) == {"top"}
        np.testing.assert_array_equal(edges["top"][0], np.array(want, bool))


def test_a_curved_surface_is_no_edge_only_its_silhouette_is():
    # a ball seen from above on a 24×24 view, no sun: a pixel is an edge pixel only where the
    # ball's outline crosses its footprint (not where its normal turns within the pixel), and
    # every pixel the ball covers 10-90% of is one (a sliver can escape the pixel's samples)
    r, n, k = 0.3, 24, 32
    cam = df.Camera("top", "orthographic", position=(0.5, 0.5, 1.5), look_at=(0.5, 0.5, 0.0),
                    up=(0.0, 1.0, 0.0), resolution=(n, n), extent=(1.0, 1.0))
    scene = _scene([df.Sphere("s", center=(0.5, 0.5, 0.5), radius=r)], cameras=(cam,))
    edges = df.forward_model(scene, "sweep", resolution=12, M=1).edge_pixels()["top"]
    c = (np.arange(n * k) + 0.5) / (n * k)  # k×k points per pixel (symmetric: rows' order
    inside = np.hypot(*np.meshgrid(c - 0.5, c - 0.5)) < r  # does not matter)
    cover = inside.reshape(n, k, n, k).mean(axis=(1, 3))
    crossed = (cover > 0) & (cover < 1)
    assert edges.sum() > 20 and not (edges & ~crossed).any()
    assert edges[(cover > 0.1) & (cover < 0.9)].all()


@pytest.mark.slow  # compiles the float64 light solve and its adjoint (~40 s); the march with
# exact hits has its default-suite check in test_camera.py
def test_image_gradient_with_a_camera_inside_the_fog_matches_finite_differences(x64):
    # the exact-hit path (the hit's albedo, its exact sun through the fog, the march up to the
    # hit) differentiated through the implicit light solve, against central differences
    import jax
    import jax.numpy as jnp

    from helpers import build_model, central_difference, small_scene

    scene = small_scene(size=(8, 6))
    inside = df.Camera("inside", "perspective", position=(0.2, 0.25, 0.45),
                       look_at=(0.5, 0.5, 0.3), resolution=(8, 6), fov_deg=70.0)
    scene = scene.replace(cameras=(inside,))
    m = build_model("sweep", scene, max_iterations=1000, tol=1e-12, adjoint_rtol=1e-11)
    hits = m.hits[0]
    assert np.asarray(hits.shape).min() >= 0  # every ray of this camera ends on a surface
    p0 = m.params(jnp.float64)
    w = np.random.default_rng(3).random((6, 8))

    def loss(p):
        return jnp.sum(w * m(p)["inside"])

    g = jax.jit(jax.grad(loss))(p0)
    f = jax.jit(loss)
    for path in ("fog.scattering", "fog.absorption", "shape.ball-mid.albedo", "sun.irradiance"):
        fd = float(central_difference(f, p0, scene, path))
        assert float(df.get_param(g, scene, path)) == pytest.approx(fd, rel=1e-6), path


@pytest.mark.parametrize("resolution", [24, 32])
def test_the_suns_depth_at_hits_ends_at_the_fogs_box(resolution):
    """translucent-cube's fog box [0.2, 0.8]² × [0.1, 0.7]: the sun's density-weighted path
    from every lit hit equals the exact chord through the box, wherever the nodes fall against
    its faces (at N = 32 the outer nodes lie 0.003 inside them; through the nodes' trilinear
    ramp the path was up to 0.06 too long there, 0.045 at N = 24; depths are float32)."""
    import dataclasses

    sc = df.load_scene("translucent-cube")
    sc = sc.replace(cameras=tuple(dataclasses.replace(c, resolution=(40, 30))
                                  for c in sc.cameras))
    m = df.forward_model(sc, "sweep", accuracy=None, resolution=resolution, M=2,
                         supersample=1)
    s = np.asarray(sc.sun.direction, float)
    s /= np.linalg.norm(s)
    lo, hi = np.array([0.2, 0.2, 0.1]), np.array([0.8, 0.8, 0.7])
    checked = 0
    for h in m.hits:
        lit = np.asarray(h.sun_cos) > 0
        p = (np.asarray(h.origins) + np.asarray(h.t)[:, None] * np.asarray(h.directions))[lit]
        with np.errstate(divide="ignore"):
            t1, t2 = (lo - p) / s, (hi - p) / s
        chord = np.clip(np.maximum(t1, t2).min(1) - np.minimum(t1, t2).max(1).clip(0), 0, None)
        np.testing.assert_allclose(np.asarray(h.sun_depth)[lit], chord, rtol=0, atol=1e-6)  # float32
        checked += int((chord > 0.05).sum())
    assert checked > 100  # many of the lit hits see the sun through the fog


def _slab_shadow_volume(k: float) -> float:
    """The volume of [0, 1]³ outside the slab [0.2, 0.8] × [0.3, 0.7] × [0.6, 0.7] from which
    the sun (towards +x, tan of its zenith angle k) meets the slab: at height z the shadow
    spans x ∈ [0.2 − (0.7 − z)·k, 0.8 − (0.6 − z)⁺·k] in the slab's y-range (the slab itself
    left out), integrated by a fine midpoint rule in z."""
    z = (np.arange(70000) + 0.5) / 100000  # 0 … 0.7
    lo = np.clip(0.2 - (0.7 - z) * k, 0, 1)
    hi = np.clip(0.8 - np.clip(0.6 - z, 0, None) * k, 0, 1)
    width = np.clip(hi - lo, 0, None) - np.where(z > 0.6, 0.6, 0.0)
    return float(width.sum() * 1e-5 * 0.4)


@pytest.mark.parametrize("resolution", [20, 40])
def test_the_suns_visibility_is_the_lit_share_of_each_cell(resolution):
    """The sun's visibility at the nodes (exact shadow rays, box-filtered over each cell's
    fluid) carries the exact lit volume: Σ V·h³ over the fluid cells of a slab's scene equals
    the domain's fluid volume less the slab's shadow (analytic), at zenith 25° (its shadow
    edges cross the cells obliquely).  The lattice's shadow buffer (the SOLID nodes marched
    towards the sun) puts 4.6% / 2.4% of the shadow's volume in the light at N = 20 / 40;
    this is within 0.03% (measured)."""
    from difffog.forward.sweep._uncollided import sun_transmittance
    from difffog.geometry._hits import sun_visibility
    from difffog.geometry._lattice import SOLID, voxelize

    sc = _scene((df.Box("slab", min=(0.2, 0.3, 0.6), max=(0.8, 0.7, 0.7)),),
                sun=df.Sun(irradiance=1.0, zenith_deg=25.0, azimuth_deg=0.0))
    lat = voxelize(sc, resolution, 1)  # the slab's faces lie on cell faces: cells are all
    fluid = np.asarray(lat.node_type) != SOLID  # fluid or all solid
    s = np.asarray(sc.sun.direction)
    V = sun_visibility(sc, fluid.shape, lat.origin, lat.h, s)
    assert V.min() >= 0 and V.max() <= 1 and np.all(V[~fluid] == 0)
    shadow = _slab_shadow_volume(math.tan(math.radians(25.0)))
    lit = 1.0 - 0.6 * 0.4 * 0.1 - shadow
    got = float(V[fluid].sum() * lat.h**3)
    assert abs(got - lit) < 0.005 * shadow, (got, lit)
    old = np.asarray(sun_transmittance(np.zeros(V.shape, np.float32), fluid == 0, s, lat.h,
                                       False))
    assert abs(float(old[fluid].sum() * lat.h**3) - lit) > 0.02 * shadow  # what it fixes


# slow: the default suite's 12-minute budget on 2 cores (stop 56)
@pytest.mark.slow
def test_more_edge_samples_place_an_outline_finer():
    # an emitting disc (a sphere of radiance 1 seen from above, no fog, no sun) on an 8×8 view:
    # a pixel reads the share of its footprint the outline encloses.  16 Hammersley rays in
    # an edge pixel leave up to 0.117 of it wrong (measured), 64 up to 0.031; a fit that
    # reduces its cameras 4-fold takes 64 (difffog.fit: 16 per reduction)
    from difffog.fit._driver import make_model

    r, n, k = 0.3, 8, 64
    cam = df.Camera("top", "orthographic", position=(0.5, 0.5, 1.5), look_at=(0.5, 0.5, 0.0),
                    up=(0.0, 1.0, 0.0), resolution=(n, n), extent=(1.0, 1.0))
    scene = _scene([df.Sphere("s", center=(0.5, 0.5, 0.5), radius=r, albedo=0.0,
                              emission=1.0)], cameras=(cam,))
    c = (np.arange(n * k) + 0.5) / (n * k)
    cover = (np.hypot(*np.meshgrid(c - 0.5, c - 0.5)) < r).reshape(n, k, n, k).mean(axis=(1, 3))
    err = {}
    for e in (16, 64):
        model = df.forward_model(scene, "sweep", resolution=12, M=1, edge_samples=e)
        assert model.settings()["edge_samples"] == e
        img = np.asarray(df.render(model).images["top"], np.float64)
        assert img[n // 2, n // 2] == pytest.approx(1.0, rel=1e-5)  # inside: the emission
        err[e] = np.abs(img - cover).max()
    assert err[64] < 0.04 and err[64] < 0.5 * err[16], err
    fit_scene = df.load_scene("fog-balls", ["shape.walls.thickness=0.1"])
    kw = dict(cameras=["top"], resolution=12, model_settings={"M": 1})
    assert make_model(fit_scene, "sweep", downsample=4, **kw).edge_samples == 64
    assert make_model(fit_scene, "sweep", downsample=1, **kw).edge_samples == 16
    assert make_model(fit_scene, "sweep", downsample=4, cameras=["top"], resolution=12,
                      model_settings={"M": 1, "edge_samples": 16}).edge_samples == 16
    with pytest.raises(df.SceneError, match="edge_samples=0"):
        df.forward_model(scene, "sweep", resolution=12, M=1, edge_samples=0)


@pytest.mark.parametrize("name", ["fog-balls", "ring-box", "translucent-cube"])
def test_shadow_rays_along_one_direction_see_what_first_hits_sees(name):
    """``_sun_lit`` (the sun's visibility's caster: one direction, spheres and boxes on the
    lattice's broadcast axes, tori and triangles only where a ray reaches their bounds) gives
    exactly ``first_hits``' answers (no hit; origin outside every shape) on a grid and on points
    lying in the planes of box faces and triangle vertices, for the scene's sun and directions with zero components
    (the slab test's 0·inf)."""
    from difffog.geometry._hits import _hit_geometry, _sun_lit

    scene = df.load_scene(name)
    lo, hi = np.asarray(scene.domain.min, float), np.asarray(scene.domain.max, float)
    n = 29
    axes = [lo[c] + (np.arange(n) + 0.5) * (hi[c] - lo[c]) / n for c in range(3)]
    grid = (axes[0][:, None, None], axes[1][None, :, None], axes[2][None, None, :])
    rng = np.random.default_rng(3)
    pts = lo + rng.uniform(size=(3000, 3)) * (hi - lo)
    boxes, tris = _hit_geometry(scene)
    faces = np.concatenate([np.stack([b_lo, b_hi]) for _, b_lo, b_hi in boxes]
                           + [tris.corners.reshape(-1, 3)])
    for c in range(3):  # a third of the points in a box face's (or a vertex's) plane
        pts[c * 1000:(c + 1) * 1000, c] = rng.choice(faces[:, c], 1000)
    seen = np.zeros(3, int)
    for s in (scene.sun.direction, (0.0, 0.6, 0.8), (0.0, 0.0, 1.0), (0.6, 0.0, -0.8)):
        s = np.asarray(s, float) / np.linalg.norm(s)
        for xs, p in ((grid, np.stack(np.broadcast_arrays(*grid), -1).reshape(-1, 3)),
                      ((pts[:, 0], pts[:, 1], pts[:, 2]), pts)):
            lit, fluid = _sun_lit(scene, xs, s, 1e-9)
            ref = first_hits(scene, p, np.broadcast_to(s, p.shape), t_min=1e-9)
            np.testing.assert_array_equal(lit.reshape(-1), np.isinf(ref.t))
            np.testing.assert_array_equal(fluid.reshape(-1), ~ref.inside)
            seen += [lit.sum(), (~lit & fluid).sum(), (~fluid).sum()]
    assert np.all(seen > 0), seen  # lit, shadowed and inside points were all tested
