"""The fog's density grid as an unknown (``Params.density``): the lattice's linear maps of the
grid, the traced forward model against the host's, and its gradient for every cell against
finite differences in float64."""

from __future__ import annotations

import dataclasses
import json

import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import difffog as df
from difffog.geometry._lattice import voxelize
from helpers import small_scene


def tiny_cloud(grid: int = 8, size=(16, 16), cameras=("top", "view0")):
    """cloud-tomo with its 32³ cloud averaged down to ``grid``³ cells and ``cameras`` at
    ``size`` pixels."""
    scene = df.load_scene("cloud-tomo")
    g = np.asarray(scene.fog.density, np.float64)
    k = g.shape[0] // grid
    g = g.reshape(grid, k, grid, k, grid, k).mean(axis=(1, 3, 5))
    cams = tuple(dataclasses.replace(scene.camera(c), resolution=size) for c in cameras)
    return scene.replace(fog=dataclasses.replace(scene.fog, density=g), cameras=cams)


#: the tiny cloud's lattice steps are optically thick (σ_t·h·M up to 6.6): "auto" would pick the
#: linear scheme, which these tests of the density's plumbing do not need (and it compiles
#: longer)
TINY = dict(scheme="step")


def with_grid(scene, g):
    return scene.replace(fog=dataclasses.replace(scene.fog, density=np.asarray(g)))


@pytest.mark.parametrize("name", ["cloud-tomo", "fog-balls"])
def test_density_map_gives_the_lattices_fog(name):
    """The grid's linear map reproduces what voxelize computes on the host (the fog's own
    density and each cell's fog volume, with SOLID cells' fog moved beside fog-balls' walls
    and balls), to float32 rounding, and is linear (a sum of grids maps to the sum)."""
    scene = df.load_scene(name)
    rng = np.random.default_rng(0)
    if name == "fog-balls":  # a uniform fog: give it a positive random grid
        scene = with_grid(scene, rng.uniform(0.2, 1.5, (6, 5, 7)))
    lat = voxelize(scene, 20, 3, margin=4)
    m = lat.density_map
    g = np.asarray(scene.fog.density, np.float64)
    fog, dens = m.apply(g)
    assert np.abs(fog - lat.fog_density).max() <= 2e-7 * lat.fog_density.max()
    assert np.abs(dens - lat.density).max() <= 2e-7 * lat.density.max()
    if name == "fog-balls":
        assert len(m.src) > 0  # the walls' and balls' cells moved fog: the map has those too
    other = rng.uniform(0.0, 1.0, g.shape) * (g > 0)
    f2, d2 = m.apply(other)
    f3, d3 = m.apply(g + other)
    np.testing.assert_allclose(f3, fog + f2, atol=1e-12)
    np.testing.assert_allclose(d3, dens + d2, atol=1e-12)


def test_traced_density_gives_the_hosts_fields_at_the_scene_grid():
    """``with_density(params, scene's grid)`` gives every field the model derives from the
    density as the host computed it for the fixed grid: the solver's cell fog, the cameras'
    density and sun path, and each exact hit's depth towards the sun (the same midpoint
    samples); twice the grid doubles the hits' depths (linear); a uniform fog and a grid of
    another shape are refused with one line each."""
    scene = tiny_cloud()
    model = df.forward_model(scene, "sweep", resolution=12, M=2, supersample=1, accuracy=None,
                             **TINY)
    p = model.params()
    g = np.asarray(scene.fog.density)
    host = model._with_density(p)
    traced = jax.jit(lambda q: model._with_density(q)[1:])  # the solver's: the same map
    geom, cam, dens, hits = model._with_density(df.with_density(p, g))
    cam2, _, hits2 = traced(df.with_density(p, 2 * g))
    close = lambda a, b: np.testing.assert_allclose(  # noqa: E731
        np.asarray(a), np.asarray(b), rtol=0, atol=2e-6 * float(np.abs(np.asarray(b)).max()))
    close(geom.density, host[0].density)
    close(dens, host[2])
    close(cam.fog_density, host[1].fog_density)
    close(cam.sun_path, host[1].sun_path)
    lit = 0
    for h, h0, h2 in zip(hits, host[3], hits2):
        close(h.sun_depth, h0.sun_depth)
        close(h2.sun_depth, 2 * np.asarray(h0.sun_depth))
        lit += int(np.sum(np.asarray(h0.sun_depth) > 0.01))
    assert lit > 50  # the cloud's shadow falls on ground the cameras see
    m2 = df.forward_model(small_scene(), "sweep", resolution=12, M=2, supersample=1,
                          accuracy=None)
    with pytest.raises(df.SceneError, match="uniform fog"):
        m2.images(df.with_density(m2.params(), np.ones((4, 4, 4))))
    with pytest.raises(df.SceneError, match="shape"):
        model.images(df.with_density(p, np.ones((4, 4, 4))))


def test_the_priors_are_the_documented_sums_and_a_bad_one_is_refused():
    """``roughness``: "tv" is Σ sqrt(|∇g|² + ε²) − ε and "smooth" Σ|∇g|² over the cells, with
    forward differences that are 0 past the grid, "shape" the latter at a fixed mass (a scaled
    grid's is unchanged, where "smooth" scales with the square); fit_density refuses an unknown prior and
    a negative weight with one line each."""
    from difffog.fit._density import roughness

    g = np.random.default_rng(1).random((4, 5, 3))
    d = [np.diff(g, axis=a, append=np.take(g, [-1], axis=a)) for a in range(3)]
    sq = d[0] ** 2 + d[1] ** 2 + d[2] ** 2
    assert float(roughness(jnp.asarray(g), "smooth", 0.0)) == pytest.approx(sq.sum(), rel=1e-6)
    eps = 0.01
    tv = np.sum(np.sqrt(sq + eps ** 2) - eps)
    assert float(roughness(jnp.asarray(g), "tv", eps)) == pytest.approx(tv, rel=1e-6)
    # "shape": "smooth" at the start's mass, the same for the grid scaled by any factor
    m0 = float(g.sum())
    for k in (1.0, 0.5, 3.0):
        assert float(roughness(jnp.asarray(k * g), "shape", 0.0, m0)) == pytest.approx(
            sq.sum(), rel=1e-6)
    assert float(roughness(jnp.asarray(0.5 * g), "smooth", 0.0)) == pytest.approx(
        0.25 * sq.sum(), rel=1e-6)
    scene = tiny_cloud()
    t = {c.name: np.ones((c.height, c.width)) for c in scene.cameras}
    with pytest.raises(df.DifffogError, match="prior: 'l1' is not one of tv, smooth"):
        df.fit_density(scene, t, prior="l1")
    with pytest.raises(df.DifffogError, match="prior_weight: a finite weight >= 0"):
        df.fit_density(scene, t, prior="smooth", prior_weight=-1.0)


def test_carving_needs_two_views_and_a_coarse_cell_all_of_its_fine_cells():
    """Space carving (``_carved``): where every pixel of both views is clear, the cells both
    views' rays cross are carved with ``views=2`` and none with one camera (fog as bright as
    the ground behind it leaves one view unchanged); a cell is marked only by a ray through its
    central part, so a ray along a cell face marks neither neighbour; and a coarse cell is
    carved only when all of its fine cells are (``coarsen_carved``)."""
    from difffog.fit._density import _carved, coarsen_carved

    scene = tiny_cloud(grid=8, size=(8, 8))
    cams = scene.cameras[:2]
    img = {c.name: np.ones((c.height, c.width)) for c in cams}
    one = _carved(scene, cams[:1], img, img, (8, 8, 8), 0.02, views=1)
    both = _carved(scene, cams, img, img, (8, 8, 8), 0.02, views=2)
    alone = _carved(scene, cams[:1], img, img, (8, 8, 8), 0.02, views=2)
    other = _carved(scene, cams[1:], img, img, (8, 8, 8), 0.02, views=1)
    assert one.any() and not alone.any()
    np.testing.assert_array_equal(both, one & other)
    assert 0 < both.sum() < one.sum()
    # the top view is orthographic, straight down: its 8x8 pixel-centre rays pass through
    # the centres of an 8-cell grid's columns (marked) and along the faces of a 16-cell
    # grid's cells (not marked), whose 2x2 sub-pixel rays pass through cell centres again
    top = [c for c in cams if c.name == "top"]
    assert _carved(scene, top, img, img, (8, 8, 8), 0.02)[:, :, 4].all()
    assert not _carved(scene, top, img, img, (16, 16, 16), 0.02).any()
    assert _carved(scene, top, img, img, (16, 16, 16), 0.02, rays=2)[:, :, 8].all()

    rng = np.random.default_rng(3)
    fine = rng.random((8, 6, 4)) < 0.8
    fine[:2, :3, :2] = True
    coarse = coarsen_carved(fine, (4, 3, 2))
    want = fine.reshape(4, 2, 3, 2, 2, 2).all(axis=(1, 3, 5))
    np.testing.assert_array_equal(coarse, want)
    assert coarse[0, 0, 0] and not coarse.all()


def test_a_density_fit_takes_the_substep_scheme_and_the_shape_prior_unless_told():
    """The density fit's levels use the sub-stepped scheme (``DENSITY_SCHEME``: the closest to
    Mitsuba on the clouds' skins) and the "shape" prior (``DEFAULT_PRIOR``: blind to the
    total mass), the pair that came closest to the truth on four clouds (docs/tomography.md);
    settings that name a scheme win, and "auto" still resolves to linear for the tiny cloud
    (step depth 6.6)."""
    import inspect

    from difffog.fit._density import DEFAULT_PRIOR, DENSITY_SCHEME, level_loss

    scene = tiny_cloud()
    g = np.asarray(scene.fog.density)
    t = {c.name: np.ones((c.height, c.width)) for c in scene.cameras}
    loss, _, model, lev = level_loss(scene, t, g, 10, 1, 1e-3, 2, 1)
    assert DENSITY_SCHEME == "substep" and model.solver.scheme == "substep"
    assert DEFAULT_PRIOR == "shape" and loss.prior == "shape"
    assert inspect.signature(df.fit_density).parameters["prior"].default == "shape"
    _, _, model, _ = level_loss(scene, t, g, 10, 1, 1e-3, 2, 1, {"scheme": "step"})
    assert model.solver.scheme == "step"
    _, _, model, lev = level_loss(scene, t, g, 10, 1, 1e-3, 2, 1, {"scheme": "auto"})
    assert model.solver.resolved_scheme(lev, model.lattice) == "linear"


def test_a_density_fits_final_level_takes_two_pixels_per_lattice_node():
    """The default image reduction per level: one pixel per lattice node on the coarser
    levels, two on the final one (``FINAL_PIXELS_PER_NODE``: cloud-tomo's 64² views at full
    size on its 32-node lattice), a divisor of every camera's sides, never below 1."""
    from difffog.fit._density import FINAL_PIXELS_PER_NODE, level_downsample

    assert FINAL_PIXELS_PER_NODE == 2
    scene = df.load_scene("cloud-tomo-start")
    names = {c.name for c in scene.cameras}
    assert level_downsample(scene, names, [16, 24, 32]) == [4, 2, 1]
    assert level_downsample(scene, names, [48, 64]) == [1, 1]
    big = scene.replace(cameras=tuple(dataclasses.replace(c, resolution=(480, 360))
                                      for c in scene.cameras))
    # 480 // 16 = 30, 480 // 24 = 20, 480 // 64 = 7 -> 6 (7 does not divide 360)
    assert level_downsample(big, names, [16, 24, 32]) == [30, 20, 6]


def test_the_shape_prior_starts_where_smooth_does_and_ignores_the_mass():
    """A level's "shape" prior is "smooth" of its start at the start (the level keeps the
    start's mass), and the same for the grid at twice the density, where "smooth" is 4×."""
    from difffog.fit._density import level_loss, roughness

    scene = tiny_cloud()
    g = np.asarray(scene.fog.density)
    t = {c.name: np.ones((c.height, c.width)) for c in scene.cameras}
    sm, x0, _, _ = level_loss(scene, t, g, 10, 1, 1e-3, 2, 1, prior="smooth")
    sh, x1, _, _ = level_loss(scene, t, g, 10, 1, 1e-3, 2, 1, prior="shape")
    assert float(sh.mass0) == pytest.approx(float(g[g > 0].sum()), rel=1e-6)
    for k in (1.0, 2.0):
        a = float(roughness(sm.grid(x0 + np.log(k)), "smooth", sm.eps))
        b = float(roughness(sh.grid(x1 + np.log(k)), "shape", sh.eps, sh.mass0))
        assert b == pytest.approx(a / k ** 2, rel=1e-5) and a > 0


def test_a_density_fit_samples_two_rays_per_target_pixel_side_unless_told():
    """Each level's cameras cast two rays per side of a *target* pixel by default (a level's
    images reduced k times get min(4, 2k) per reduced pixel side, at least 2), so that they
    sample the targets' box filter as the targets' pixels do (docs/tomography.md: with one
    ray per target pixel the truth's own misfit to cloud-tomo's Mitsuba images was 3.44e-4 at
    the final level, with two per side 2.01e-4); a per-level list of the wrong length is
    refused with one line."""
    from difffog.fit._density import rays_per_pixel_side

    assert [rays_per_pixel_side(k) for k in (1, 2, 3, 4, 8)] == [2, 4, 4, 4, 4]
    scene = tiny_cloud()
    t = {c.name: np.ones((c.height, c.width)) for c in scene.cameras}
    with pytest.raises(df.DifffogError, match="supersample need one value per level"):
        df.fit_density(scene, t, grids=(4,), supersample=[2, 2, 2], progress=False)


@pytest.fixture(scope="module")
def tiny_fit_case():
    """float64 (restored after the module): the tiny cloud, its two views, and a start: a
    uniform box one cell around the cloud.  The views are the fit level's own images of the
    truth (``LEVEL``: N = 10, M = 2, full images), rendered by the very program the fit and the
    gradient check run (models built alike share their compiled programs): this test checks
    the machinery; the benchmark (benchmarks/tomography.py) fits independent Mitsuba images."""
    from difffog.fit._density import _value_and_grad, level_loss

    old = jax.config.jax_enable_x64
    jax.config.update("jax_enable_x64", True)
    scene = tiny_cloud()
    truth = np.asarray(scene.fog.density, np.float64)
    box = np.zeros_like(truth)
    nz = np.argwhere(truth > 0)
    lo, hi = np.maximum(nz.min(0) - 1, 0), np.minimum(nz.max(0) + 2, truth.shape)
    box[lo[0]:hi[0], lo[1]:hi[1], lo[2]:hi[2]] = truth[truth > 0].mean()
    blank = {c.name: np.ones((c.height, c.width)) for c in scene.cameras}
    loss, _, _, _ = level_loss(scene, blank, box, LEVEL["resolutions"][0],
                               LEVEL["downsample"][0], 1e-3, LEVEL["M"], 1, LEVEL["settings"])
    # the truth on the box's cells (its zeros as e^-80: 0 to float64's resolution)
    x_true = np.log(np.maximum(truth.reshape(-1)[np.asarray(loss.support)], 1e-35))
    (_, (_, _, code, imgs)), _ = _value_and_grad(jax.numpy.asarray(x_true), loss)
    assert int(code) == 0
    targets = {c: np.asarray(v) for c, v in imgs.items()}
    yield scene, targets, truth, box
    jax.config.update("jax_enable_x64", old)


#: the tiny fit's level: lattice, image reduction, solver settings (tight tolerances: the
#: gradient check)
LEVEL = dict(resolutions=(10,), downsample=(1,), M=2, supersample=1,
             settings=dict(TINY, tol=1e-10, adjoint_rtol=1e-10, max_iterations=400))


def test_fit_density_recovers_a_tiny_cloud_and_its_gradient_is_exact(tiny_fit_case, tmp_path):
    """End to end at a tiny size (one grid level, 8 evaluations, float64): the loss falls, the
    error to the truth falls well below the start's, the carving removes cells the views see
    through, the cells outside the start's support stay 0, and density.npz / fit.json are
    written.  Then the fit's gradient at its estimate (the images' relative misfit + the
    prior, in the log of every support cell; reverse mode through the implicit light solve:
    one adjoint solve for all the cells) against central differences on the densest, a
    middling and the thinnest cell (the fit's own compiled program).  A fixed weight
    (balance=False): the balancing test is its own."""
    from difffog.fit._density import _value_and_grad

    scene, targets, truth, box = tiny_fit_case
    res = df.fit_density(scene, targets, start=box, grids=None, max_steps=8, progress=False,
                         balance=False, **LEVEL)
    start_err = np.linalg.norm(box - truth) / np.linalg.norm(truth)
    assert res.density.shape == truth.shape
    assert res.relative_error(truth) < 0.5 * start_err
    losses = [h["loss"] for h in res.history if "loss" in h]
    assert len(losses) <= 8 and min(losses) < 0.2 * losses[0]
    assert res.levels[0]["carved_cells"] > 0
    # the carving emptied no cell where the truth has fog
    assert truth[(res.density == 0) & (box > 0)].sum() == 0
    assert np.all(res.density[box == 0] == 0)
    res.save(tmp_path / "out")
    with np.load(tmp_path / "out" / "density.npz") as z:
        np.testing.assert_array_equal(z["density"], res.density)
    report = json.loads((tmp_path / "out" / "fit.json").read_text())
    assert report["grid"] == list(truth.shape) and report["levels"][0]["steps"] == len(losses)
    # the estimate's images: their misfit is the best evaluation's data term
    imgs, tg = res.images()
    assert set(imgs) == set(targets) and all(imgs[c].shape == targets[c].shape for c in imgs)
    t_all = np.concatenate([tg[c].ravel() for c in tg])
    misfit = 0.5 * sum(np.sum((imgs[c] - tg[c]) ** 2) for c in imgs) / (
        t_all.size * np.mean(t_all ** 2))
    best = min((h for h in res.history if "loss" in h), key=lambda h: h["loss"])
    assert misfit == pytest.approx(best["data"], rel=1e-9)

    loss, x = res.final_level
    (_, (_, _, code, _)), grad = _value_and_grad(x, loss)
    assert int(code) == 0
    # no host callback in the fit's program (an unconverged adjoint is a NaN gradient), so
    # XLA's persistent cache keeps it for the next process
    assert "callback" not in _value_and_grad.lower(x, loss).as_text().lower()
    grad = np.asarray(grad)
    keep = np.flatnonzero(np.asarray(loss.keep) > 0)
    dens = np.exp(np.asarray(x))[keep]
    order = keep[np.argsort(dens)]
    # the same gradient per unit density on the grid (DensityFit.gradient), 0 off the support
    val, dg = res.gradient()
    flat = dg.reshape(-1)[np.asarray(loss.support)]
    np.testing.assert_allclose(flat[keep] * dens, grad[keep], rtol=1e-10,
                               atol=1e-12 * np.abs(grad).max())
    assert np.all(dg[box == 0] == 0) and val == pytest.approx(min(losses), rel=1e-12)
    for i in (order[-1], order[len(order) // 2], order[0]):
        eps = 1e-4
        f = [float(_value_and_grad(x.at[i].add(s * eps), loss)[0][0]) for s in (1, -1)]
        fd = (f[0] - f[1]) / (2 * eps)
        assert abs(fd) > 1e-10, i  # the cell reaches the loss
        assert grad[i] == pytest.approx(fd, rel=1e-5, abs=1e-6 * np.abs(grad).max()), i


def test_a_density_fit_resumes_from_its_checkpoint(tiny_fit_case, tmp_path):
    """A fit stopped after 3 evaluations (max_steps) leaves a checkpoint; resumed with 6 it
    goes on from its best point (its first evaluation there gives that point's loss again,
    the same program) and spends at most the 3 it has left (fewer when an iteration gains
    less than rtol); a checkpoint of another fit (another prior weight) is refused with one
    line."""
    scene, targets, truth, box = tiny_fit_case
    ck = tmp_path / "density-checkpoint.npz"
    kw = dict(start=box, grids=None, progress=False, checkpoint=ck, balance=False, **LEVEL)
    part = df.fit_density(scene, targets, max_steps=3, **kw)
    assert part.result == "max_steps" and ck.exists()
    before = [h["loss"] for h in part.history if "loss" in h]
    assert len(before) == 3
    with pytest.raises(df.DifffogError, match="different fit"):
        df.fit_density(scene, targets, max_steps=6, resume=True, prior_weight=2e-3,
                       **{**kw, "balance": 0.8})
    full = df.fit_density(scene, targets, max_steps=6, resume=True, **kw)
    losses = [h["loss"] for h in full.history if "loss" in h]
    assert losses[:3] == before and 5 <= len(losses) <= 6
    assert losses[3] == pytest.approx(min(before), rel=1e-12)
    assert min(losses[3:]) < min(before)
    assert full.levels[-1]["steps"] == len(losses)
    assert full.relative_error(truth) < part.relative_error(truth)


def test_the_balancing_rule_moves_the_weight_by_the_measured_power():
    """The balancing principle's next weight: unchanged (None) within BALANCE_TOL of the
    aimed share, else W · (aim / share)^(1 / BALANCE_POWER), by at most 10 either way; a
    share that is not a finite positive number leaves the weight alone."""
    from difffog.fit._density import BALANCE_POWER, BALANCE_TOL, balanced_weight

    assert balanced_weight(3e-5, 0.8 * BALANCE_TOL * 0.999, 0.8) is None
    assert balanced_weight(3e-5, 0.8 / BALANCE_TOL * 1.001, 0.8) is None
    w = balanced_weight(3e-5, 1.10, 0.8)  # cloud-tomo-b's share at the default weight
    assert w == pytest.approx(3e-5 * (0.8 / 1.10) ** (1 / BALANCE_POWER), rel=1e-12)
    assert 1.5e-5 < w < 1.8e-5  # the weight the hand check gave (docs/tomography.md)
    assert balanced_weight(1e-5, 0.01, 0.8) == pytest.approx(1e-4, rel=1e-12)
    assert balanced_weight(1e-5, 100.0, 0.8) == pytest.approx(1e-6, rel=1e-12)
    assert balanced_weight(1e-5, 0.0, 0.8) is None and balanced_weight(1e-5, np.inf, 0.8) is None


# slow: the default suite's 12-minute budget on 2 cores (stop 56); by default the tiny cloud's
# end-to-end fit (test_fit_density_recovers_a_tiny_cloud_and_its_gradient_is_exact)
@pytest.mark.slow
def test_a_balanced_density_fit_moves_its_share_toward_the_aim_and_resumes(tiny_fit_case,
                                                                          tmp_path):
    """balance=0.8 on the tiny cloud (its own images: the prior's share after the first pass
    is far below 0.8): the final level runs a second pass at the rule's weight, from the first
    pass's estimate, and its share ends closer to 0.8; each pass's estimate is kept, the last
    is the result, and the record (weights, shares, history) says what happened.  A fit
    stopped in its second pass resumes there at the second weight (its first evaluation
    gives the pass's best loss again).  Balancing is on by default and off when a weight is
    given; bad balance settings are refused with one line."""
    from difffog.fit._density import balanced_weight

    scene, targets, truth, box = tiny_fit_case
    kw = dict(start=box, grids=None, progress=False, **LEVEL)
    res = df.fit_density(scene, targets, max_steps=6, balance=0.8, **kw)
    bal = res.levels[-1]["balance"]
    assert bal["target"] == 0.8 and len(bal["prior_weights"]) == len(bal["shares"]) == 2
    w0, w1 = bal["prior_weights"]
    assert w1 == pytest.approx(balanced_weight(w0, bal["shares"][0], 0.8), rel=1e-12) and w1 > w0
    assert abs(np.log(bal["shares"][1] / 0.8)) < abs(np.log(bal["shares"][0] / 0.8))
    evals = [h for h in res.history if "loss" in h]
    assert [h.get("pass", 0) for h in evals] == [0] * 6 + [1] * 6
    assert res.levels[-1]["steps"] == 12
    # the second pass starts where the first ended: the same cells, the weight alone differs
    second, best0 = evals[6], min(evals[:6], key=lambda h: h["loss"])
    assert second["data"] == pytest.approx(best0["data"], rel=1e-9)
    assert second["prior"] == pytest.approx(best0["prior"] * w1 / w0, rel=1e-9)
    assert len(res.passes) == 2 and np.array_equal(res.passes[-1], res.density)
    assert not np.array_equal(res.passes[0], res.passes[1])
    # stopped in the second pass, resumed there
    ck = tmp_path / "ck.npz"
    part = df.fit_density(scene, targets, max_steps=3, balance=0.8, checkpoint=ck, **kw)
    pw = part.levels[-1]["balance"]["prior_weights"]
    assert part.result == "max_steps" and len(pw) == 2
    p_evals = [h for h in part.history if "loss" in h]
    best1 = min(p_evals[3:], key=lambda h: h["loss"])
    full = df.fit_density(scene, targets, max_steps=5, balance=0.8, checkpoint=ck, resume=True,
                          **kw)
    f_evals = [h for h in full.history if "loss" in h]
    assert full.levels[-1]["balance"]["prior_weights"] == pw
    assert f_evals[6].get("pass") == 1 and f_evals[6]["loss"] == pytest.approx(best1["loss"],
                                                                             rel=1e-12)
    assert len(f_evals) == 3 + 5  # the second pass spends the 2 evaluations it has left
    # on by default, off when the weight is given
    assert df.fit_density(scene, targets, max_steps=1, **kw).settings["balance"] == 0.8
    fixed = df.fit_density(scene, targets, max_steps=1, prior_weight=1e-3, **kw)
    assert fixed.settings["balance"] is None and "balance" not in fixed.levels[-1]
    for bad, match in ((dict(balance=-1.0), "balance: a share > 0"),
                       (dict(balance="x"), "balance: a share > 0"),
                       (dict(balance=True, prior="tv"), "has no default share"),
                       (dict(balance=0.8, prior_weight=0.0), "0 cannot be balanced"),
                       (dict(balance_rounds=-1), "balance_rounds")):
        with pytest.raises(df.DifffogError, match=match):
            df.fit_density(scene, targets, max_steps=1, **{**kw, **bad})


def test_a_density_fit_stops_at_its_best_point_when_an_adjoint_solve_fails(tiny_fit_case,
                                                                           tmp_path,
                                                                           monkeypatch):
    """An evaluation whose gradient's adjoint light solve does not converge (a NaN gradient
    from the compiled program, ``solves_by_value``; a thick cloud's fit once failed so at its
    29th final evaluation) ends the level at its best point so far: an AdjointWarning of one
    line, the result "adjoint_failed" (not "successful"), the failure in the history, no
    traceback, and the checkpoint kept, from which a resume goes on at that best point."""
    from difffog.fit import _density as dens

    scene, targets, truth, box = tiny_fit_case
    real, calls = dens._value_and_grad, [0]

    def flaky(x, loss):  # the carving's call, 3 evaluations, then the adjoint fails
        calls[0] += 1
        (val, aux), grad = real(x, loss)
        return (val, aux), (grad * jnp.nan if calls[0] == 5 else grad)

    monkeypatch.setattr(dens, "_value_and_grad", flaky)
    ck = tmp_path / "ck.npz"
    kw = dict(start=box, grids=None, progress=False, balance=False, checkpoint=ck, **LEVEL)
    with pytest.warns(df.AdjointWarning, match="did not converge at evaluation 4 of level 0"):
        res = df.fit_density(scene, targets, max_steps=8, **kw)
    assert res.result == "adjoint_failed" and ck.exists()
    losses = [h["loss"] for h in res.history if "loss" in h]
    assert len(losses) == 3 and res.history[-1]["what"] == "adjoint_failed"
    assert res.levels[0]["loss"] == min(losses) and res.levels[0]["steps"] == 4
    monkeypatch.setattr(dens, "_value_and_grad", real)
    full = df.fit_density(scene, targets, max_steps=8, resume=True, **kw)
    after = [h["loss"] for h in full.history if "loss" in h]
    assert after[3] == pytest.approx(min(losses), rel=1e-12) and full.result != "adjoint_failed"


def test_a_density_fits_line_search_never_tries_a_cell_thicker_than_the_cap(tiny_fit_case,
                                                                            monkeypatch):
    """L-BFGS-B's trial points stay at log-densities below ``log_density_cap``: 100 mean free
    paths per cell (a cold fit of cloud-tomo-c once tried log-densities of 105, an infinite
    density whose NaN light ended the level).  A loss that always rewards more fog runs into
    the cap and stops there."""
    from difffog.fit import _density as dens

    scene, targets, truth, box = tiny_fit_case
    seen = []

    def runaway(x, loss):  # −Σx: unbounded below, every cell wants more fog
        seen.append(np.asarray(x))
        val = -jnp.sum(x)
        return (val, (val, 0.0 * val, jnp.asarray(0), {})), -jnp.ones_like(x)

    monkeypatch.setattr(dens, "_value_and_grad", runaway)
    res = df.fit_density(scene, targets, start=box, grids=None, progress=False, balance=False,
                         carve=False, max_steps=40, **LEVEL)
    size = np.asarray(scene.domain.max) - np.asarray(scene.domain.min)
    width = float(np.min(size / np.asarray(box.shape)))
    cap = math.log(dens.MAX_CELL_DEPTH / ((scene.fog.scattering + scene.fog.absorption) * width))
    assert dens.log_density_cap(scene, box.shape, np.log(box[box > 0])) == pytest.approx(cap)
    assert cap > np.log(box.max()) + math.log(10)  # the start is well inside
    top = max(float(x.max()) for x in seen)
    assert top <= cap + 1e-9 and top == pytest.approx(cap)
    assert float(np.max(res.density)) == pytest.approx(math.exp(cap))
    # a start denser than the cap keeps 10× headroom above its densest cell
    assert dens.log_density_cap(scene, box.shape, np.array([cap + 1.0])) == pytest.approx(
        cap + 1.0 + math.log(10))
