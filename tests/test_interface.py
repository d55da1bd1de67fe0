"""The forward-model interface, for every model of ``helpers.MODELS``: images, render,
render_batch, the light at points, a gradient against finite differences, a short fit, and
the result codes of light solves that did not converge."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import difffog as df
from helpers import FIT_TRUTH, build_model, central_difference, small_scene


def test_registry_builds_every_model_by_name(model):
    assert isinstance(model, df.AbstractForwardModel)
    assert model.settings()["solver"] in df.SOLVERS
    assert [c.name for c in model.cameras] == ["top", "oblique"]


def test_images_have_every_camera_at_its_shape(model):
    imgs = model(model.params())
    assert set(imgs) == {"top", "oblique"}
    for img in imgs.values():
        assert img.shape == (10, 12)
        a = np.asarray(img)
        assert np.all(np.isfinite(a)) and a.min() >= 0 and a.max() > 0


def test_render_reports_light_result_and_timings(model):
    out = df.render(model)
    assert out.result == df.RESULTS.successful and out.converged
    assert isinstance(out.light, df.AbstractLight)
    assert int(out.light.result) == df.RESULTS.successful
    for img in out.images.values():
        assert img.dtype == np.float32
    for k in ("light_compile_s", "light_s", "images_compile_s", "images_s"):
        assert out.timings[k] >= 0
    # the same images as the jitted call
    direct = model(model.params())
    for k, v in out.images.items():
        np.testing.assert_allclose(v, np.asarray(direct[k]), rtol=1e-5, atol=1e-7)


def test_render_of_a_scene_builds_through_the_registry():
    out = df.render(small_scene(), solver="splat", accuracy=None, resolution=12, supersample=1)
    assert out.settings["solver"] == "splat" and out.settings["resolution"] == 12


def test_models_built_alike_share_their_compiled_programs(model):
    """A model built again from the same scene and settings (a notebook cell run twice, a fit
    level rebuilt from a new start) renders with the programs compiled for the first: nothing
    is traced or compiled (``HostInfo``, the models' host-side record, compares equal), and
    the images are the same.  The listener is shown to count: a new function compiles
    once."""
    from jax._src.dispatch import BACKEND_COMPILE_EVENT, JAXPR_TRACE_EVENT

    solver = "sweep" if isinstance(model, df.SweepModel) else "splat"
    first = np.asarray(model()["top"])
    events = []

    def listen(name, secs, **kw):
        if name in (BACKEND_COMPILE_EVENT, JAXPR_TRACE_EVENT):
            events.append(name)

    again = build_model(solver)
    assert again is not model
    jax.monitoring.register_event_duration_secs_listener(listen)
    try:
        second = np.asarray(again()["top"])
        n_again = len(events)
        jax.jit(lambda x: x * 3.0 + 1.0)(jnp.ones(3)).block_until_ready()
        n_new = len(events) - n_again
    finally:
        jax.monitoring.unregister_event_duration_listener(listen)
    assert n_again == 0, events
    assert n_new >= 1  # the listener sees a compile when there is one
    np.testing.assert_array_equal(second, first)


def _sets(model):
    p0 = model.params()
    s = model.scene
    return [df.set_param(df.set_param(p0, s, "fog.scattering", z), s, "shape.walls.albedo", a)
            for z, a in ((0.5, 0.2), (2.0, 0.5), (4.0, 0.9))]


# slow: the default suite's 12-minute budget on 2 cores (stop 56)
@pytest.mark.slow
def test_render_batch_equals_one_by_one(model):
    sets = _sets(model)
    batch = df.render_batch(model, sets)
    for i, p in enumerate(sets):
        for cam, img in model(p).items():
            np.testing.assert_allclose(np.asarray(batch[cam][i]), np.asarray(img),
                                       rtol=2e-5, atol=1e-6 * float(img.max()))
    # the batch really varies
    assert float(jnp.abs(batch["top"][0] - batch["top"][2]).max()) > 0.02 * float(
        batch["top"].max())


def test_light_at_points_is_the_light_in_the_fog(model):
    light = df.render(model).light  # render's compiled light solve (shared with the test above)
    pts = jnp.array([[0.5, 0.5, 0.95], [0.5, 0.5, 0.05], [0.2, 0.8, 0.5]])
    f = np.asarray(light.fluence_at(pts))
    assert f.shape == (3,) and np.all(np.isfinite(f)) and np.all(f >= 0)
    # under the sun (irradiance 2) the fluence near the top of the fog is of its order,
    # and the light weakens towards the floor through the fog
    assert 0.5 < f[0] < 10.0
    assert f[1] < f[0]


@pytest.mark.parametrize("solver", [
    # both in -m slow (the suite's 12-minute budget): the splat's image gradients are checked
    # against finite differences by default in test_splat.py (every parameter kind), the
    # sweep's light (test_sweep.py) and camera (test_camera.py) gradients apart; this
    # end-to-end check compiles for ~35 s each
    pytest.param("splat", marks=pytest.mark.slow),
    pytest.param("sweep", marks=pytest.mark.slow)])
def test_gradient_matches_finite_differences(solver, x64):
    scene = small_scene(size=(6, 5))
    extra = dict(tol=1e-12, max_iterations=1000, adjoint_rtol=1e-11) if solver == "sweep" else {}
    m = build_model(solver, scene, **extra)
    p0 = m.params(jnp.float64)
    # a fixed random weighting of the pixels (a quadratic misfit would need the images
    # rendered first: one more compiled program)
    rng = np.random.default_rng(3)
    weights = {c.name: jnp.asarray(rng.random((c.height, c.width))) for c in m.cameras}

    def loss(p):
        imgs = m(p)
        return sum(jnp.sum(weights[k] * imgs[k]) for k in imgs)

    # one compiled program gives the gradient and the values the differences take (a second
    # program for the loss alone would double the compile time, which dominates here)
    value_and_grad = jax.jit(jax.value_and_grad(loss))
    value, g = value_and_grad(p0)
    f = lambda p: value_and_grad(p)[0]  # noqa: E731
    for path in ("fog.scattering", "fog.absorption", "shape.ball-mid.albedo", "sun.irradiance"):
        fd = float(central_difference(f, p0, scene, path))
        got = float(df.get_param(g, scene, path))
        assert got == pytest.approx(fd, rel=1e-4, abs=1e-10 * abs(float(value))), path


# both slow (the suite's 12-minute budget; both passed when last run): test_fit.py's fits run
# the sweep's in the default suite, and the splat's gradient is checked there below
@pytest.mark.parametrize("fit_model", [
    pytest.param("splat", marks=pytest.mark.slow),
    pytest.param("sweep", marks=pytest.mark.slow)], indirect=True)
def test_short_fit_recovers_the_truth(fit_model):
    """A fit through each model (the fit tests' shared model: its compiled step is shared)."""
    targets = {k: np.asarray(v) for k, v in fit_model(fit_model.params()).items()}
    start = {p: 1.15 * v for p, v in FIT_TRUTH.items()}
    res = df.fit(fit_model.scene, targets, start, forward=fit_model, max_steps=8)
    for p, v in FIT_TRUTH.items():
        assert res.estimates[p] == pytest.approx(v, rel=0.01), p
    assert res.history and res.history[-1]["light_result"] == "successful"


# -- result codes -------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def thick():
    """A tiny, optically thick, nearly conservative scene whose light solve is capped at 3
    iterations: it cannot converge."""
    scene = small_scene("fog-balls", ["fog.scattering=60", "fog.absorption=0.001"], (8, 6))
    return build_model("sweep", scene, resolution=10, max_iterations=3, tol=1e-6)


@pytest.mark.filterwarnings("ignore::difffog.ThickStepWarning")  # checked below
def test_unconverged_light_solve_raises_with_its_error_and_iterations(thick):
    with pytest.raises(df.SolverError, match=r"max_iterations_reached \(estimated error "
                                             r"[0-9.e+-]+ after 3 iterations\)"):
        df.render(thick)
    # the scene's steps are optically thick (ζ = 60, N = 10): render says so, with the fix
    with pytest.warns(df.ThickStepWarning, match=r"σ_t·h·M = [0-9.]+ > 1 .* resolution >= "):
        out = df.render(thick, throw=False)
    assert out.result == df.RESULTS.max_iterations_reached and not out.converged
    assert int(out.light.iterations) == 3 and float(out.light.error_estimate) > 1e-6
    # the caller asked for the images regardless: they are there, finite
    assert out.images["top"].shape == (6, 8) and np.all(np.isfinite(out.images["top"]))


@pytest.mark.slow  # the suite's budget; the eager path is checked just above
def test_unconverged_light_solve_raises_inside_jit(thick):
    with pytest.raises(Exception, match="iteration cap before its tolerance"):
        jax.block_until_ready(thick(thick.params()))


@pytest.mark.slow  # the suite's 12-minute budget (passed when last run)
def test_render_batch_names_the_failed_parameter_sets(thick):
    p = thick.params()
    with pytest.raises(df.SolverError, match=r"parameter set\(s\) 0, 1 failed"):
        df.render_batch(thick, [p, p])


def _stubborn_solve(throw: bool):
    """A linear solve that cannot converge: GMRES(2) with one restart on a 6×6 system whose
    Krylov space needs all six steps, through the sweep's CheckedSolver."""
    import lineax as lx

    from difffog.forward.sweep._implicit import CheckedSolver

    a = jnp.diag(jnp.arange(1.0, 7.0)) + jnp.diag(jnp.ones(5), 1)
    solver = CheckedSolver(lx.GMRES(rtol=1e-12, atol=1e-12, restart=2, max_steps=1),
                           throw=throw)
    return lx.linear_solve(lx.MatrixLinearOperator(a), jnp.ones(6), solver).value


def test_unconverged_adjoint_solve_raises_or_warns():
    with pytest.raises(Exception, match="adjoint light solve"):
        jax.block_until_ready(jax.jit(_stubborn_solve, static_argnums=0)(True))
    with pytest.warns(df.AdjointWarning, match="did not converge"):
        x = jax.block_until_ready(jax.jit(_stubborn_solve, static_argnums=0)(False))
    assert np.all(np.isfinite(np.asarray(x)))


def test_solves_by_value_transpose_right_and_give_nan_without_a_callback():
    """``_implicit._solve_by_value`` (what the density fit's program takes): on a
    non-symmetric system its value is A⁻¹b and its gradient Aᵀ⁻¹w (the solver's own transposed
    solve, though JAX is told the operator is symmetric); a solve that cannot converge gives
    NaN, and the compiled gradient has no host callback."""
    import lineax as lx

    from difffog.forward.sweep._implicit import CheckedSolver, KrylovSolver, _solve_by_value

    a = np.diag(np.arange(1.0, 7.0)) + np.diag(np.ones(5), 1) + 0.3 * np.diag(np.ones(4), -2)
    op = lx.MatrixLinearOperator(jnp.asarray(a))
    b, w = jnp.linspace(1.0, 2.0, 6), jnp.linspace(-1.0, 1.0, 6)
    good = CheckedSolver(KrylovSolver(rtol=1e-12, restart=10, max_matvecs=60))
    bad = CheckedSolver(KrylovSolver(rtol=1e-30, restart=2, max_matvecs=2))

    def f(b, solver):
        return jnp.sum(w * _solve_by_value(op, b, solver, {}))

    x = _solve_by_value(op, b, good, {})
    np.testing.assert_allclose(np.asarray(x), np.linalg.solve(a, np.asarray(b)), rtol=1e-5)
    g = jax.jit(jax.grad(f), static_argnums=1)
    np.testing.assert_allclose(np.asarray(g(b, good)), np.linalg.solve(a.T, np.asarray(w)),
                               rtol=1e-5)  # float32
    assert not np.allclose(np.linalg.solve(a.T, np.asarray(w)), np.linalg.solve(a, np.asarray(w)),
                           rtol=1e-2)  # the transpose matters here
    assert np.all(np.isnan(np.asarray(g(b, bad))))
    assert "callback" not in g.lower(b, good).as_text().lower()


@pytest.mark.slow  # the extremes matrix (test_extremes.py) records the sweep's adjoint warnings
def test_unconverged_adjoint_of_the_sweep_warns():
    """The sweep's gradient goes through that check: an adjoint asked for the impossible
    (rtol 1e-30) warns, and the gradient stays finite."""
    m = build_model("sweep", small_scene(size=(4, 4)), resolution=10, max_iterations=40,
                    adjoint_rtol=1e-30, throw=False)
    with pytest.warns(df.AdjointWarning, match="did not converge"):
        g = jax.block_until_ready(
            jax.jit(jax.grad(lambda p: jnp.sum(m(p, throw=False)["top"])))(m.params()))
    assert np.isfinite(float(g.scattering))


def test_forward_model_refuses_settings_of_the_other_solver():
    with pytest.raises(df.DifffogError, match="sheets is not a setting of the sweep solver"):
        df.forward_model(small_scene(), "sweep", sheets=10)
    with pytest.raises(df.DifffogError, match="unknown solver 'sweeep'"):
        df.forward_model(small_scene(), "sweeep")
