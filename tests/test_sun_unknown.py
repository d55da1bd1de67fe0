"""The sun's direction as an unknown (``sun.zenith_deg``, ``sun.azimuth_deg``): the sweep model
traces it (``SweepModel.with_sun_derivatives``), its derivatives are exact for the model it
renders (the light solve's beam, the cosines and the phase follow the traced direction; the
host's shadows and paths are linearized about the model's sun), and a fit finds the sun by
rounds that rebuild the model at the estimated sun."""

import dataclasses
import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import difffog as df
from difffog import DifffogError, SceneError
from difffog.fit import _driver
from difffog.scene._params import set_param, sun_direction_of


def _slab(g=0.0, ball=False, pixels=12):
    """Fog over a ground quad (no shape between them and the sun unless ``ball``), two views."""
    shapes = [df.Quad("ground", albedo=0.5)]
    if ball:
        shapes.append(df.Sphere("ball", center=(0.5, 0.5, 0.22), radius=0.15, albedo=0.8))
    fog = dict(phase="henyey-greenstein", g=g) if g else {}
    return df.Scene(
        title="sun unknown", domain=df.Domain(min=(0, 0, -0.1), max=(1, 1, 0.6)),
        fog=df.Fog(scattering=1.5, absorption=0.1, **fog),
        sun=df.Sun(irradiance=2.0, zenith_deg=35, azimuth_deg=20), sky=df.Sky(radiance=0.2),
        shapes=shapes,
        cameras=[df.Camera("top", "orthographic", position=(0.5, 0.5, 1.5),
                           look_at=(0.5, 0.5, 0), up=(0, 1, 0), resolution=(pixels, pixels),
                           extent=(0.8, 0.8)),
                 df.Camera("side", "orthographic", position=(0.5, -1.0, 0.8),
                           look_at=(0.5, 0.5, 0.2), up=(0, 0, 1), resolution=(pixels, pixels),
                           extent=(0.8, 0.8))])


def _moved(scene, path, by):
    return scene.replace(sun=dataclasses.replace(
        scene.sun, **{path[4:]: getattr(scene.sun, path[4:]) + by}))


def test_sun_paths_read_and_set_the_direction():
    scene = _slab()
    assert {"sun.zenith_deg", "sun.azimuth_deg"} <= set(df.param_paths(scene))
    p = df.forward_model(scene, "sweep", resolution=8).params()
    assert float(df.get_param(p, scene, "sun.zenith_deg")) == 35.0  # the scene's, not traced
    assert sun_direction_of(p, scene) is None
    q = set_param(set_param(p, scene, "sun.zenith_deg", 50.0), scene, "sun.azimuth_deg", -30.0)
    want = dataclasses.replace(scene.sun, zenith_deg=50.0, azimuth_deg=-30.0).direction
    np.testing.assert_allclose(np.asarray(sun_direction_of(q, scene)), want, atol=1e-6)
    no_sun = scene.replace(sun=None)
    assert "sun.zenith_deg" not in df.param_paths(no_sun)
    with pytest.raises(SceneError, match="not a differentiable parameter"):
        set_param(p, no_sun, "sun.zenith_deg", 10.0)


# slow: the default suite's 12-minute budget on 2 cores (stop 56);
# by default the sun's paths and refusals are checked (test_sun_paths_read_and_set_the_direction,
# test_sun_unknowns_are_refused_where_they_cannot_be_traced)
@pytest.mark.slow
def test_traced_sun_renders_the_scene_at_its_own_sun():
    """At the model's own sun the traced angles change nothing (shadows included)."""
    scene = _slab(ball=True)
    model = df.forward_model(scene, "sweep", resolution=12)
    sun_model = model.with_sun_derivatives()
    p = model.params()
    q = set_param(set_param(p, scene, "sun.zenith_deg", 35.0), scene, "sun.azimuth_deg", 20.0)
    a, b = model(p), sun_model(q)
    for cam in a:
        np.testing.assert_allclose(np.asarray(b[cam]), np.asarray(a[cam]), rtol=2e-6,
                                   atol=1e-7)
    assert sun_model.settings()["sun_derivative_step_deg"] == 1.0
    with pytest.raises(SceneError, match="with_sun_derivatives"):
        model(q)  # traced angles, no derivatives: a one-line error, not a silent static sun


def _rebuilt_forms(g):
    """A model with the sun's derivatives, the same rebuilt at another sun, and their
    traced-sun forms, the second's shaped like the first's."""
    paths = ("sun.zenith_deg", "sun.azimuth_deg")
    a = df.forward_model(_slab(g=g, ball=True, pixels=8), "sweep",
                         resolution=8).with_sun_derivatives()
    b = a.at_sun(35.7, 20.6)  # the ball's shadow moves: other edge pixels, other rays
    fa = a.traced_sun_form(paths)
    return a, b, fa, b.traced_sun_form(paths, like=fa)


def test_a_model_rebuilt_at_another_sun_runs_the_first_ones_programs():
    """A fit's rounds rebuild the model at the estimated sun; their traced-sun forms
    (``SweepModel.traced_sun_form``) have the first round's structure and array shapes, the
    key of its compiled steps (stop 57: each round compiled its step anew, 45-50 s of a
    round's 75 s in test_fit_finds_the_sun_by_rounds); their values are
    test_the_rebuilt_models_form_renders_what_it_renders's."""
    from difffog.fit._stepper import _model_key

    a, b, fa, fb = _rebuilt_forms(0.0)
    assert _model_key(fb) == _model_key(fa)
    assert _model_key(b.traced_sun_form(("sun.zenith_deg", "sun.azimuth_deg"))) \
        != _model_key(fa)  # (without ``like``: b's own static sun)
    assert fb.scene.sun == a.scene.sun and b.scene.sun.zenith_deg == 35.7
    assert [int(h.weight.shape[0]) for h in fb.hits] == [int(h.weight.shape[0]) for h in fa.hits]
    assert all(int(h.weight.shape[0]) > int(k.weight.shape[0]) for h, k in zip(fa.hits, a.hits))
    for h, k in zip(fb.hits, b.hits):  # the padding: rays of weight 0
        n = int(k.weight.shape[0])
        np.testing.assert_array_equal(np.asarray(h.weight[:n]), np.asarray(k.weight))
        assert not np.asarray(h.weight[n:]).any()
    with pytest.raises(SceneError, match="no sun derivatives"):
        df.forward_model(_slab(pixels=8), "sweep", resolution=8).traced_sun_form(
            ("sun.zenith_deg",))


# slow: two render compiles of ~22 s each on 2 cores (the default suite's 12-minute budget);
# the forms' structure and padding are checked by default (test_a_model_rebuilt_at_...)
@pytest.mark.slow
@pytest.mark.parametrize("g", [0.0, 0.6])
def test_the_rebuilt_models_form_renders_what_it_renders(g):
    """The form renders what the rebuilt model renders wherever the sun is traced (its own
    shadows, paths and linearization; the first model's static sun standing in), and not
    what the first model renders (g = 0.6: the first collision's cell-averaged phase at the
    traced sun)."""
    _, b, fa, fb = _rebuilt_forms(g)

    def images(m, z, az):
        p = set_param(set_param(m.params(), m.scene, "sun.zenith_deg", z), m.scene,
                      "sun.azimuth_deg", az)
        return np.concatenate([np.asarray(v).ravel() for v in m(p).values()])

    for at in ((35.7, 20.6), (36.1, 20.2)):
        want = images(b, *at)
        np.testing.assert_allclose(images(fb, *at), want, rtol=2e-6, atol=1e-7)
        # the first model, linearized about its own sun, renders these suns otherwise: the
        # form carries the rebuilt model's arrays
        assert np.abs(images(fa, *at) - want).max() > 1e-3 * np.abs(want).max()


@pytest.mark.parametrize("g,order,rebuilt", [
    pytest.param(0.0, 0, ("sun.zenith_deg", "sun.azimuth_deg"), marks=pytest.mark.slow),
    pytest.param(0.6, 2, ("sun.azimuth_deg",), marks=pytest.mark.slow),
    # (slow: 74 s of compiling in float64, which took the default suite from 8:07 to 10:30
    # with the fit below; that fit checks the traced sun's Jacobian end to end)
    pytest.param(0.6, 2, ("sun.zenith_deg",), marks=pytest.mark.slow)])
def test_sun_gradients_match_finite_differences(x64, g, order, rebuilt):
    """Reverse mode through the traced sun equals central differences of the same model in
    float64 (the exact gradient of what it renders), and that model's change with the sun
    matches models rebuilt at the moved sun (``rebuilt``: for these angles; with the same
    step: the host's shadows and paths change in steps of its rays, so their derivative is a
    difference at some step)."""
    scene = _slab(g)
    kw = dict(resolution=10, tol=1e-9, max_iterations=3000, phase_order=order)
    step = 0.5
    model = df.forward_model(scene, "sweep", **kw).with_sun_derivatives(step)
    p0 = model.params()
    paths = ("sun.zenith_deg", "sun.azimuth_deg")
    at = jnp.asarray([float(df.get_param(p0, scene, q)) for q in paths])

    def images(angles):
        p = p0
        for q, v in zip(paths, angles):
            p = set_param(p, scene, q, v)
        return model(p)

    out, vjp = jax.vjp(images, at)
    rng = np.random.default_rng(1)
    w = {c: jnp.asarray(rng.standard_normal(out[c].shape)) for c in out}
    grad = np.asarray(vjp(w)[0])
    e = 1e-3
    for i, path in enumerate(paths):
        up, dn = (images(at.at[i].add(s)) for s in (e, -e))
        fd = sum(float(jnp.sum(w[c] * (up[c] - dn[c]))) for c in w) / (2 * e)
        assert grad[i] == pytest.approx(fd, rel=1e-5), path
        if path not in rebuilt:
            continue
        moved = {}
        for s in (step, -step):
            m = df.forward_model(_moved(scene, path, s), "sweep", **kw)
            moved[s] = m(m.params())
        lin = np.concatenate([np.ravel((up[c] - dn[c]) / (2 * e)) for c in w])
        ref = np.concatenate([np.ravel((moved[step][c] - moved[-step][c]) / (2 * step))
                              for c in w])
        assert np.linalg.norm(ref) > 1e-4  # the images do depend on the sun
        assert np.linalg.norm(lin - ref) < 0.05 * np.linalg.norm(ref), path


def _sun_targets(dz, da, pixels=16, N=12):
    truth = _moved(_moved(_slab(ball=True, pixels=pixels), "sun.zenith_deg", dz),
                   "sun.azimuth_deg", da)
    model = df.forward_model(truth, "sweep", resolution=N)
    return {k: np.asarray(v) for k, v in model(model.params()).items()}


# slow: the default suite's 12-minute budget on 2 cores (stop 56); the fit by rounds is also
# test_fit_finds_the_sun_by_rounds; by default only the sun's paths and refusals are checked
# (test_sun_paths_read_and_set_the_direction, test_sun_unknowns_are_refused_where_...)
@pytest.mark.slow
def test_fit_finds_a_sun_near_the_start():
    """A sun 0.3° off in both angles, with the ball's shadow on the ground: the fit, through the
    traced sun's Jacobian, finds it within 0.05° (the first round's model is linearized with
    ±4° steps; a second round, if any, is built at its estimate)."""
    res = df.fit(_slab(ball=True, pixels=16), _sun_targets(0.3, 0.3),
                 ["sun.zenith_deg", "sun.azimuth_deg"], resolution=12)
    assert res.converged, res.result
    assert res.estimates["sun.zenith_deg"] == pytest.approx(35.3, abs=0.05)
    assert res.estimates["sun.azimuth_deg"] == pytest.approx(20.3, abs=0.05)
    assert 1 <= len(res.sun_rounds) <= 3
    assert res.sun_rounds[0]["step_deg"] == _driver.SUN_FIRST_STEP


@pytest.mark.slow
def test_fit_finds_the_sun_by_rounds():
    """Targets rendered at zenith 37°, azimuth 22° with the ball's shadow on the ground, the
    fit started 2° off in both: every round rebuilds the model at the last estimate, and the
    last one moves the sun less than SUN_SETTLE_DEG."""
    from difffog.fit import _stepper

    targets = _sun_targets(2.0, 2.0)
    start = _slab(ball=True, pixels=16)
    before = set(_stepper._STEPPERS)
    res = df.fit(start, targets, ["sun.zenith_deg", "sun.azimuth_deg"], resolution=12)
    assert res.converged, res.result
    # every round ran the first one's compiled step (``SweepModel.traced_sun_form``)
    assert len(set(_stepper._STEPPERS) - before) <= 1
    assert res.estimates["sun.zenith_deg"] == pytest.approx(37.0, abs=0.1)
    assert res.estimates["sun.azimuth_deg"] == pytest.approx(22.0, abs=0.1)
    rounds = res.sun_rounds
    assert len(rounds) >= 2 and rounds[0]["sun"] == {"sun.zenith_deg": 35.0,
                                                      "sun.azimuth_deg": 20.0}
    last = rounds[-1]
    assert max(abs(last["estimates"][p] - last["sun"][p]) for p in last["sun"]) \
        <= _driver.SUN_SETTLE_DEG
    assert res.initial["sun.zenith_deg"] == 35.0
    assert res.iterations == sum(r["iterations"] for r in rounds)
    assert res.to_json()["sun_rounds"] == rounds
    text = res.summary(truth={"sun.zenith_deg": 37.0, "sun.azimuth_deg": 22.0})
    assert f"{len(rounds)} rounds" in text and "°" in text


def test_sun_unknowns_are_refused_where_they_cannot_be_traced():
    scene = _slab(pixels=8)
    tg = {"top": np.ones((8, 8))}
    with pytest.raises(DifffogError, match="splat forward model takes the sun's direction"):
        df.fit(scene, tg, ["sun.zenith_deg"], forward="splat")
    with pytest.raises(DifffogError, match="fit_batch: the sun's angles"):
        df.fit_batch(scene, [tg], ["sun.azimuth_deg"])
    with pytest.raises(DifffogError, match="not supported with a ladder"):
        df.fit(scene, tg, ["sun.zenith_deg"], ladder=(8, 12))
    with pytest.raises(DifffogError, match="resume: not supported with the sun"):
        df.fit(scene, tg, ["sun.zenith_deg"], checkpoint="x.npz", resume=True)
    with pytest.raises(DifffogError, match="bounds"):
        df.fit(scene, tg, {"sun.zenith_deg": (30.0, 0.0, 120.0)})
    model = df.forward_model(scene, "splat", resolution=8)
    p = set_param(model.params(), scene, "sun.zenith_deg", 30.0)
    with pytest.raises(SceneError, match="splat solver takes the sun's direction as fixed"):
        model(p)
    grid = scene.replace(fog=dataclasses.replace(scene.fog, density=np.ones((4, 4, 4))))
    m = df.forward_model(grid, "sweep", resolution=8).with_sun_derivatives()
    q = df.with_density(set_param(m.params(), grid, "sun.zenith_deg", 30.0), np.ones((4, 4, 4)))
    with pytest.raises(SceneError, match="cannot be traced together"):
        m(q)
    with pytest.raises(SceneError, match="no \\[sun\\]"):
        df.forward_model(scene.replace(sun=None), "sweep", resolution=8).with_sun_derivatives()
    assert math.isfinite(_driver.SUN_FIRST_STEP)


@pytest.mark.slow
def test_fit_of_a_given_model_rebuilds_it_at_the_sun_and_refines_there():
    """forward=a SweepModel: each round rebuilds that model at the estimated sun
    (``SweepModel.at_sun``), and ``model_error="refine"`` renders its finer checks at the
    last round's sun, with the last round's move as a part of the model error."""
    targets = _sun_targets(1.5, -1.5)
    start = _slab(ball=True, pixels=16)
    model = df.forward_model(start, "sweep", resolution=12)
    res = df.fit(start, targets, ["sun.zenith_deg", "sun.azimuth_deg"], forward=model,
                 model_error="refine")
    assert res.converged, res.result
    assert len(res.sun_rounds) >= 2
    for p, want in (("sun.zenith_deg", 36.5), ("sun.azimuth_deg", 18.5)):
        assert res.fitted[p] == pytest.approx(want, abs=0.1)
        assert "sun_rounds" in res.model_error_parts[p]
        # the correction moves towards the finer lattice's reading of targets rendered at
        # N = 12 themselves (on so coarse a lattice the zenith by ~2°): the model error, which
        # the truth is judged by, covers that move
        assert res.model_error[p] >= abs(res.estimates[p] - res.fitted[p])
    final = res.sun_rounds[-1]["sun"]  # the refine's models were built at the last round's sun
    assert final != res.sun_rounds[0]["sun"]
