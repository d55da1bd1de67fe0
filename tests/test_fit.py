"""Fitting: the Jacobian against finite differences, recovery of known parameters, starts far
from the truth, robust losses, identifiability warnings, checkpoint/resume, input errors.

The sweep fits run on a small lattice (N = 12, M = 2, images of 16×16 and 20×15 pixels); the
cheap analytic toy forward model checks the optimiser plumbing without a light solve.  The
recovery study at realistic sizes is ``benchmarks/recovery_study.py`` (and the slow tests at
the end)."""

import dataclasses
import json
import math
import warnings
from pathlib import Path

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import difffog as df
from difffog import DifffogError, IdentifiabilityWarning, SweepModel, SweepSolver
from difffog.fit._driver import make_model
from difffog.fit._residuals import FitProblem
from difffog.fit._result import statistics
from difffog.fit._unknowns import Coordinate

from helpers import ToyLight

ROOT = Path(__file__).resolve().parents[1]


def _small_scene():
    return df.load_scene("fog-balls", ["shape.walls.thickness=0.1"])  # > one voxel at N = 12


TRUTH = {"fog.scattering": 2.0, "fog.absorption": 0.5, "shape.walls.albedo": 0.7}


@pytest.fixture
def small_forward(sweep_fit_model):
    """The session's sweep fit model (conftest), shared with test_interface's fit (one
    compiled fit step)."""
    return sweep_fit_model


@pytest.fixture
def small_targets(small_forward):
    return {k: np.asarray(v) for k, v in small_forward(small_forward.params()).items()}


# ------------------------------------------------------------------ a cheap analytic forward
class Toy(df.AbstractForwardModel):
    """A forward model with the models' interface and no light solve: the 'top' image is
    ζ·F·a(x) + γ·b(x) + ρ_walls·c(x) (F the sun irradiance)."""

    scene: df.Scene = eqx.field(static=True)
    cameras: tuple = eqx.field(static=True)
    a: jax.Array
    b: jax.Array
    c: jax.Array

    def __init__(self, scene=None, shape=(8, 10)):
        scene = scene or _small_scene()
        cams = tuple(dataclasses.replace(c, resolution=(shape[1], shape[0]))
                     for c in scene.cameras if c.name == "top")
        self.scene = scene.replace(cameras=cams)
        self.cameras = cams
        y, x = np.mgrid[0:shape[0], 0:shape[1]] / 7.0
        self.a, self.b, self.c = (jnp.asarray(v, jnp.float32)
                                  for v in (np.exp(-x), 1.0 + np.sin(3 * y), x * y))

    def light(self, params):
        return ToyLight(result=jnp.asarray(df.RESULTS.successful, jnp.int32),
                        iterations=jnp.asarray(1, jnp.int32),
                        error_estimate=jnp.asarray(0.0, params.scattering.dtype))

    def images_from(self, light, p):
        walls = p.albedo[0]
        return {"top": p.scattering * p.sun_irradiance * self.a + p.absorption * self.b
                + walls * self.c}

    def check(self, params):
        return None

    def settings(self):
        return {"solver": "toy", "resolution": 0}


def _toy_target(toy, **values):
    p = toy.params()
    for k, v in values.items():
        p = df.set_param(p, toy.scene, k, v)
    return {"top": np.asarray(toy(p)["top"])}


# ------------------------------------------------------------------ coordinates
@pytest.mark.parametrize("coord,v", [
    (Coordinate("fog.scattering", 0.0, math.inf), 2.5),
    (Coordinate("fog.scattering", 0.5, math.inf), 2.5),
    (Coordinate("shape.walls.albedo", 0.0, 1.0), 0.7),
    (Coordinate("fog.g", -0.99, 0.99), 0.85),
    (Coordinate("fog.scattering", 0.1, 100.0), 60.0),
])
def test_coordinates_round_trip_and_derivative(coord, v):
    u = coord.to_u(v)
    assert float(coord.to_v(jnp.float32(u))) == pytest.approx(v, rel=1e-6)
    eps = 1e-2  # float32: rounding 1e-7/eps, truncation eps²
    fd = (float(coord.to_v(u + eps)) - float(coord.to_v(u - eps))) / (2 * eps)
    assert coord.dv_du(u) == pytest.approx(fd, rel=1e-3)


# ------------------------------------------------------------------ Jacobian vs FD (float64)
KINDS = {
    "fog.scattering": 2.0,
    "fog.absorption": 0.5,
    "fog.g": 0.3,
    "shape.walls.albedo": 0.7,
    "shape.ball-mid.emission": 0.2,
    "sun.irradiance": 3.0,
    "sky.radiance": 0.1,
}


@pytest.mark.slow  # ~75 s of compiling in float64; by default the sweep fits below check the
# Jacobian of their three unknowns (they converge to 1e-3 in a few LM steps) and
# test_interface.py the reverse-mode gradient against finite differences
def test_fit_jacobian_matches_finite_differences_for_every_unknown_kind(x64):
    scene = _small_scene()
    small = scene.replace(cameras=tuple(dataclasses.replace(c, resolution=(8, 6))
                                        for c in scene.cameras))
    fwd = SweepModel(small, resolution=12, supersample=1,
                     solver=SweepSolver(M=2, max_iterations=2000, tol=1e-13, adjoint_rtol=1e-12))
    coords = tuple(Coordinate(p, *({"fog.g": (-0.99, 0.99), "shape.walls.albedo": (0.0, 1.0)}
                               .get(p, (0.0, math.inf)))) for p in KINDS)
    pb = FitProblem(fwd.scene, coords, ("top", "oblique"), "linear")
    base = fwd.params(jnp.float64)
    u = jnp.asarray([c.to_u(v) for c, v in zip(coords, KINDS.values())], jnp.float64)
    y, J, code = eqx.filter_jit(pb.model_and_jacobian)(fwd, u, base)
    assert int(code) == df.RESULTS.successful
    J = np.asarray(J)
    f = eqx.filter_jit(pb.model)
    model = lambda u, base: f(fwd, u, base)[0]  # noqa: E731
    assert J.shape == (2 * 48, len(KINDS))
    for i, path in enumerate(KINDS):
        eps = 1e-5
        du = np.zeros(len(KINDS))
        du[i] = eps
        fd = (np.asarray(model(u + du, base)) - np.asarray(model(u - du, base))) / (2 * eps)
        scale = np.abs(fd).max()
        assert scale > 0, path
        assert np.abs(J[:, i] - fd).max() <= 1e-6 * scale, path


@pytest.mark.slow  # ~2 min of float64 compiles; test_sweep.py checks the matrix-free tangent
# against the linearised one and differences on a slab by default
def test_fit_jacobian_tangents_matrix_free_equal_the_linearised_and_differences(x64):
    """The fit's Jacobian takes the light field's tangents by forward mode with the tangent
    solves' products applied matrix-free (``SweepSolver(tangents="matrix-free")``: (I − K)v by
    one sourceless Jacobi step, no linearised sweeps kept): the same columns as with the
    products linearised, and central differences, in float64."""
    scene = _small_scene()
    small = scene.replace(cameras=tuple(dataclasses.replace(c, resolution=(8, 6))
                                        for c in scene.cameras))
    solver = SweepSolver(M=2, max_iterations=2000, tol=1e-12, adjoint_rtol=1e-12)
    fwd = SweepModel(small, resolution=10, supersample=1, solver=solver)
    lin = eqx.tree_at(lambda m: m.solver, fwd, dataclasses.replace(solver, tangents="linearised"))
    coords = (Coordinate("fog.scattering", 0.0, math.inf), Coordinate("fog.absorption", 0.0,
              math.inf), Coordinate("shape.walls.albedo", 0.0, 1.0))
    pb = FitProblem(fwd.scene, coords, ("top", "oblique"), "linear")
    base = fwd.params(jnp.float64)
    u = jnp.asarray([c.to_u(v) for c, v in zip(coords, TRUTH.values())], jnp.float64)
    jac = eqx.filter_jit(pb.model_and_jacobian)
    y, J, code = jac(fwd, u, base)
    _, J_lin, _ = jac(lin, u, base)
    assert int(code) == df.RESULTS.successful
    J, J_lin = np.asarray(J), np.asarray(J_lin)
    assert np.abs(J).min(axis=0).max() > 0 and np.abs(J - J_lin).max() <= 1e-10 * np.abs(J).max()
    f = eqx.filter_jit(pb.model)
    for i in range(len(coords)):
        du = np.zeros(len(coords))
        du[i] = 1e-5
        fd = (np.asarray(f(fwd, u + du, base)[0]) - np.asarray(f(fwd, u - du, base)[0])) / 2e-5
        assert np.abs(J[:, i] - fd).max() <= 1e-6 * np.abs(fd).max(), coords[i].path
    with pytest.raises(df.DifffogError, match="tangents"):
        SweepSolver(tangents="dense")


def test_jacobian_tangent_solves_start_from_the_given_tangents():
    """``FitProblem.jacobian_and_tangents(..., guess)``: the tangent solves start from
    ``guess`` (a fit's last step's tangents) and return the light state's tangents (and the
    light state at u, where the model error's finer renders start).  With a
    loose tangent tolerance, each Jacobian started from the last one's tangents at the same
    point is closer to the converged one: from zero twice gives the same J to the bit (the
    guess would be ignored), from the tangents it moves, by less each time.  So with one
    GMRES per unknown (``block_tangents=False``); the block solve (the default) reaches the
    converged J to float32 rounding from zero already at this tolerance, so it can only be
    seen to move, within the tolerance."""
    for block in (False, True):
        _start_from_tangents(block)
    with pytest.raises(df.DifffogError, match="block_tangents"):
        SweepSolver(block_tangents="yes")


def _start_from_tangents(block):
    scene = _small_scene()
    small = scene.replace(cameras=tuple(dataclasses.replace(c, resolution=(8, 6))
                                        for c in scene.cameras))
    fwd = SweepModel(small, resolution=10, supersample=1,
                     solver=SweepSolver(M=2, max_iterations=500, tol=1e-6, adjoint_rtol=3e-2,
                                        block_tangents=block))
    coords = (Coordinate("fog.scattering", 0.0, math.inf),
              Coordinate("shape.walls.albedo", 0.0, 1.0))
    pb = FitProblem(fwd.scene, coords, ("top", "oblique"), "linear")
    base = fwd.params(jnp.float32)
    u = jnp.asarray([c.to_u(TRUTH[c.path]) for c in coords], jnp.float32)
    jac = eqx.filter_jit(pb.jacobian_and_tangents)
    _, J0, code, T0, _ = jac(fwd, u, base, None)
    _, J0b, _, _, _ = jac(fwd, u, base, None)
    _, J1, _, T1, _ = jac(fwd, u, base, T0)
    _, J2, _, _, state = jac(fwd, u, base, T1)
    assert int(code) == df.RESULTS.successful
    assert jax.tree.structure(T0) == jax.tree.structure(fwd.zero_light_state(jnp.float32))
    assert all(a.shape[0] == len(coords) for a in jax.tree.leaves(T0))
    light = eqx.filter_jit(lambda m, p: m.light(p))(fwd, pb.params(u, base))
    assert all(np.allclose(a, b, rtol=1e-4, atol=1e-6 * float(jnp.max(b)))
               for a, b in zip(state, light.state))  # and the light state at u
    J0, J0b, J1, J2 = (np.asarray(a, np.float64) for a in (J0, J0b, J1, J2))
    assert np.array_equal(J0, J0b)
    first, second = np.abs(J1 - J0).max(), np.abs(J2 - J1).max()
    if block:
        assert 0 < first <= 0.05 * np.abs(J0).max() and 0 < second <= 0.05 * np.abs(J0).max()
    else:
        assert 0 < second < 0.5 * first <= 0.05 * np.abs(J0).max()


# slow since stop 80 (the default suite's 12-minute budget on 2 cores: ~40 s there, two tangent
# programs to compile); by default the block solve runs in every fit's Jacobian, is checked
# against dense solves in test_sweep.py's block GMRES test and, started from given tangents,
# in the test above
@pytest.mark.slow
def test_block_tangent_solves_give_the_tangents_of_one_solve_per_unknown():
    """The fit's tangent solves, one per unknown (the light state's tangents, ``jax.vmap``
    of ``jax.jvp`` inside ``forward_mode()``, as ``FitProblem.jacobian_and_tangents`` takes
    them), run as one block GMRES (``SweepSolver(block_tangents=True)``, the default) or one
    GMRES each in lockstep (False): the same tangents to the solves' tolerance, but not the
    same rounding (the block solve is the one that ran).  (The light alone: the cameras'
    columns do not depend on it; from the last Jacobian's tangents: the next test.)"""
    from difffog.forward.sweep._march import forward_mode

    scene = _small_scene()
    solver = SweepSolver(M=2, max_iterations=500, tol=1e-6, adjoint_rtol=1e-5)
    fwd = SweepModel(scene, resolution=10, supersample=1, solver=solver)
    each = eqx.tree_at(lambda m: m.solver, fwd,
                       dataclasses.replace(solver, block_tangents=False))
    coords = tuple(Coordinate(p, 0.0, 1.0 if "albedo" in p else math.inf) for p in TRUTH)
    pb = FitProblem(fwd.scene, coords, ("top",), "linear")
    base = fwd.params(jnp.float32)
    u = jnp.asarray([c.to_u(v) for c, v in zip(coords, TRUTH.values())], jnp.float32)

    @eqx.filter_jit
    def tangents(model, u):
        def state(x):
            return model.light(pb.params(x, base)).state

        with forward_mode():
            return jax.vmap(lambda e: jax.jvp(state, (u,), (e,))[1])(jnp.eye(len(u)))

    for a, b in zip(tangents(fwd, u), tangents(each, u)):
        a, b = np.asarray(a, np.float64), np.asarray(b, np.float64)
        scale = np.abs(b).reshape(len(coords), -1).max(axis=1)
        assert scale.min() > 0 and np.isfinite(a).all() and not np.array_equal(a, b)
        assert np.abs(a - b).reshape(len(coords), -1).max(axis=1).max() <= 1e-3 * scale.min()


def test_an_unconverged_tangent_solve_is_a_result_code_and_the_step_has_no_callback():
    """The fit's Jacobian reports a tangent solve that did not converge (asked for rtol
    1e-30) by its result code, ``tangent_unconverged``, with a finite Jacobian (zeros where
    the solve gave up), and a fit on it ends "light_solve_failed" with that message; the
    Jacobian compiles without a host callback, which XLA's persistent cache would not store
    (the fit's step compiled again in every new process, stop 62)."""
    scene = _small_scene()
    small = scene.replace(cameras=tuple(dataclasses.replace(c, resolution=(8, 6))
                                        for c in scene.cameras[:1]))
    coords = (Coordinate("fog.scattering", 0.0, math.inf),)
    for rtol, want in ((1e-30, df.RESULTS.tangent_unconverged), (1e-3, df.RESULTS.successful)):
        fwd = SweepModel(small, resolution=10, supersample=1,
                         solver=SweepSolver(M=2, max_iterations=30, tol=1e-5,
                                            adjoint_rtol=rtol))
        pb = FitProblem(fwd.scene, coords, ("top",), "linear")
        base = fwd.params(jnp.float32)
        u = jnp.asarray([coords[0].to_u(2.0)], jnp.float32)
        jac = eqx.filter_jit(pb.model_and_jacobian)
        _, J, code = jac(fwd, u, base)
        assert int(code) == want, (rtol, df.RESULTS(int(code)).name)
        assert np.all(np.isfinite(np.asarray(J)))
        if want == df.RESULTS.successful:
            assert np.abs(np.asarray(J)).max() > 0
            text = jac.lower(fwd, u, base).as_text()
            assert "callback" not in text.lower()
        else:  # a fit on it says so: result, message, history and one warning
            target = {"top": np.asarray(fwd(df.set_param(base, small, "fog.scattering",
                                                         2.0))["top"])}
            with warnings.catch_warnings():
                warnings.simplefilter("error", IdentifiabilityWarning)  # J says nothing here
                res = df.fit(small, target, {"fog.scattering": 1.5}, forward=fwd,
                             max_steps=2, model_error=None)
            assert res.result == "light_solve_failed" and "adjoint_rtol" in res.message
            assert {h["light_result"] for h in res.history} == {"tangent_unconverged"}
            assert [w for w in res.warnings if "tangent light solve" in w], res.warnings


# ------------------------------------------------------------------ sweep fits
@pytest.mark.slow  # 75-88 s (the suite's 12-minute budget): the default suite recovers the
# same unknowns from noisy images (test_noisy_fit_standard_errors_cover_the_truth)
def test_fit_recovers_parameters_of_its_own_images(small_forward, small_targets):
    """The inverse crime (targets from the very same model): a check of the machinery, exact
    up to float32 and the light solve's tolerance."""
    res = df.fit(_small_scene(), small_targets,
                 {"fog.scattering": 1.0, "fog.absorption": 1.0, "shape.walls.albedo": 0.5},
                 forward=small_forward)
    assert res.converged, res.message
    for p, v in TRUTH.items():
        assert res.estimates[p] == pytest.approx(v, rel=1e-3), p
    assert res.residual_rms < 1e-4 * np.mean(small_targets["top"])
    assert 2 <= res.iterations <= 20
    assert set(res.images) == {"top", "oblique"}
    assert res.images["top"].shape == (16, 16) and res.images["oblique"].shape == (15, 20)
    assert res.correlation.shape == (3, 3)
    np.testing.assert_allclose(np.diag(res.correlation), 1.0)
    assert [h["step"] for h in res.history] == list(range(1, res.iterations + 1))
    assert res.history[-1]["loss"] < 1e-6 * res.history[0]["loss"]
    assert "fog.scattering" in str(res) and "successful" in str(res)


# slow, both (the suite's 12-minute budget; both passed when last run): the default suite's
# fit starts 2-3x from the truth in test_noisy_fit_standard_errors_cover_the_truth
@pytest.mark.parametrize("factor", [pytest.param(0.2, marks=pytest.mark.slow),
                                    pytest.param(5.0, marks=pytest.mark.slow)])
def test_fit_converges_from_far_starts_or_says_it_did_not(small_forward, small_targets, factor):
    init = {p: (v * factor if not p.endswith("albedo") else min(0.95, v * factor / 5 + 0.1))
            for p, v in TRUTH.items()}
    res = df.fit(_small_scene(), small_targets, init, forward=small_forward)
    if res.converged:
        for p, v in TRUTH.items():
            assert res.estimates[p] == pytest.approx(v, rel=1e-3), (factor, p)
    else:  # the result says so, with a message naming the reason
        assert res.message and res.result != "successful"
        pytest.fail(f"×{factor}: {res.result}: {res.message}")


# slow: the default suite's 12-minute budget on 2 cores (stop 56); by default
# test_standard_errors_match_the_linear_least_squares_formula checks the standard errors' formula
@pytest.mark.slow
def test_noisy_fit_standard_errors_cover_the_truth(small_forward, small_targets):
    """5% Gaussian noise on the model's own images, a start 2-3× from the truth: the truth lies
    within 3 stated standard errors of every estimate, and the standard errors are not
    vacuous."""
    rng = np.random.default_rng(7)
    noisy = {k: v + rng.normal(0, 0.05 * v.mean(), v.shape) for k, v in small_targets.items()}
    res = df.fit(_small_scene(), noisy,
                 {"fog.scattering": 1.0, "fog.absorption": 1.0, "shape.walls.albedo": 0.5},
                 forward=small_forward)
    assert res.converged
    for p, v in TRUTH.items():
        se = res.stderr[p]
        assert 0 < se < 0.2 * v, p
        assert abs(res.estimates[p] - v) < 3 * se, (p, res.estimates[p], se)
    # the residual is the noise: RMS ≈ σ (the mean over both views)
    sigma = np.sqrt(np.mean([(0.05 * v.mean()) ** 2 for v in small_targets.values()]))
    assert res.residual_rms == pytest.approx(sigma, rel=0.25)


def test_a_fit_model_built_again_steps_with_the_compiled_stepper():
    """Fitting with a model built anew from the same scene and settings (``fit(scene, ...)``
    twice: each builds its model) reuses the first fit's stepper and so its compiled step; a
    model of another shape, or other unknowns, gets its own."""
    from difffog.fit._stepper import stepper_for
    from helpers import build_fit_model

    from difffog.fit import _driver

    coords = tuple(Coordinate(p, 0.0, math.inf) for p in ("fog.scattering", "fog.absorption"))
    a = build_fit_model("sweep")
    _driver._MODELS.clear()  # built anew, not the model cache's
    b = build_fit_model("sweep")
    assert a is not b
    first = stepper_for(a, coords, ("top", "oblique"), "linear", "lm")
    assert stepper_for(b, coords, ("top", "oblique"), "linear", "lm") is first
    assert stepper_for(b, coords[:1], ("top", "oblique"), "linear", "lm") is not first
    other = make_model(_small_scene(), "sweep", cameras=["top", "oblique"], resolution=10,
                       downsample=8, model_settings={"M": 2, "tol": 1e-6})
    assert stepper_for(other, coords, ("top", "oblique"), "linear", "lm") is not first


def test_fit_models_are_kept_for_the_next_fit_when_small(monkeypatch):
    """``make_model`` keeps the last few models it built (the same fit again in a process does
    not prepare them again): the same scene and settings give the same model, other settings
    another (and so does the float64 switch); a lattice above ``MODEL_CACHE_NODES`` is not
    kept."""
    from difffog.fit import _driver

    kw = dict(cameras=["top", "oblique"], downsample=8, model_settings={"M": 2, "tol": 1e-6})
    a = make_model(_small_scene(), "sweep", resolution=10, **kw)
    assert make_model(_small_scene(), "sweep", resolution=10, **kw) is a
    b = make_model(_small_scene(), "sweep", resolution=11, **kw)
    assert b is not a and make_model(_small_scene(), "sweep", resolution=11, **kw) is b
    assert make_model(_small_scene(), "sweep", resolution=10, **kw) is a
    key = _driver._model_key(_small_scene(), "sweep", kw["cameras"], 8, {}, False)
    old = jax.config.jax_enable_x64
    jax.config.update("jax_enable_x64", not old)  # the key only: no array is built
    try:
        assert _driver._model_key(_small_scene(), "sweep", kw["cameras"], 8, {}, False) != key
    finally:
        jax.config.update("jax_enable_x64", old)
    _driver._MODELS.clear()
    monkeypatch.setattr(_driver, "MODEL_CACHE_NODES", 10 ** 3)  # below these lattices
    c = make_model(_small_scene(), "sweep", resolution=10, **kw)
    assert c is not a and make_model(_small_scene(), "sweep", resolution=10, **kw) is not c
    assert not _driver._MODELS


# slow: the default suite's 12-minute budget on 2 cores (stop 56);
# by default test_edge_weight_without_known_edges_warns_and_changes_nothing
@pytest.mark.slow
def test_edge_weight_leaves_out_the_pixels_that_straddle_an_edge(small_forward, small_targets):
    """edge_weight=0: pixels the model's exact geometry says straddle an edge (a silhouette, a
    rim, a shadow's edge) do not count, so corrupting exactly those pixels leaves the estimate
    at the truth; fit.json's settings say which share of each view was down-weighted.
    (Right after the noisy fit: the same model and unknowns, so it reuses that fit's compiled
    step before the toy fits below push it out of the steppers' cache: 27 s, not 103.)"""
    edges = small_forward.edge_pixels()
    assert set(edges) == set(small_targets)
    for n, e in edges.items():
        assert e.shape == small_targets[n].shape and 0.02 < e.mean() < 0.6, (n, e.mean())
    bad = {n: np.where(edges[n], 1.5 * t + 0.1, t) for n, t in small_targets.items()}
    start = {p: 1.1 * v for p, v in TRUTH.items()}
    res = df.fit(_small_scene(), bad, start, forward=small_forward, edge_weight=0.0)
    assert res.converged, res.message
    for p, v in TRUTH.items():
        assert res.estimates[p] == pytest.approx(v, rel=2e-3), p
    assert res.settings["edge_weight"] == 0.0
    assert res.settings["edge_pixels"] == {n: pytest.approx(float(e.mean()), abs=1e-4)
                                           for n, e in edges.items()}


def test_fit_batch_equals_fitting_one_by_one():
    """fit_batch steps all fits together (vmap) and freezes each when it is done: every result
    is the one fit() gives for that target set (same steps and estimates).  The analytic toy
    keeps this cheap; the sweep under vmap is covered by the two-device test in
    test_batch.py (slow) and by render_batch."""
    toy = Toy()
    rng = np.random.default_rng(3)
    clean = _toy_target(toy, **{"fog.scattering": 2.0, "fog.absorption": 0.5})
    sets = [clean] + [{"top": clean["top"] + rng.normal(0, 0.02, clean["top"].shape)}
                      for _ in range(2)]
    start = {"fog.scattering": 1.0, "fog.absorption": 1.5, "shape.walls.albedo": 0.3}
    batch = df.fit_batch(toy.scene, sets, start, forward=toy)
    assert len(batch) == 3
    for i, (t, b) in enumerate(zip(sets, batch)):
        one = df.fit(toy.scene, t, start, forward=toy)
        assert b.converged and b.iterations == one.iterations, (b.result, one.result)
        assert b.estimates == pytest.approx(one.estimates, rel=1e-6)
        for hb, ho in zip(b.history, one.history):
            assert hb["values"] == pytest.approx(ho["values"], rel=1e-6)
        # Standard errors: relative to the estimate.  The noise-free set's are float32 noise
        # (~1e-8 of the estimate, any two roundings differ by tens of percent), so they are
        # only required to be negligible in both; the noisy sets' are ~1e-3 of the estimate,
        # far above float noise, and must agree closely.
        for p, v in one.estimates.items():
            if i == 0:
                assert b.stderr[p] < 1e-5 * abs(v) and one.stderr[p] < 1e-5 * abs(v), p
            else:
                assert one.stderr[p] > 1e-4 * abs(v), p  # the comparison below means something
                assert b.stderr[p] == pytest.approx(one.stderr[p], rel=1e-3), p
    # the noise-free set recovers the truth; the noisy ones differ from it and each other
    assert batch[0].estimates["fog.scattering"] == pytest.approx(2.0, rel=1e-4)
    assert batch[1].estimates != batch[2].estimates


def test_fit_batch_rejects_mixed_cameras_and_checkpoints(small_forward, small_targets):
    with pytest.raises(DifffogError, match="same cameras"):
        df.fit_batch(_small_scene(), [small_targets, {"top": small_targets["top"]}],
                     ["fog.scattering"], forward=small_forward)
    with pytest.raises(DifffogError, match="checkpoint is not supported"):
        df.fit_batch(_small_scene(), [small_targets], ["fog.scattering"],
                     forward=small_forward, checkpoint="x.npz")


@pytest.mark.slow  # the suite's 12-minute budget (passed when last run)
def test_fit_downsamples_full_resolution_targets_by_box_averaging(small_forward, small_targets):
    """Targets at the scene camera's resolution (128×128, 160×120) are box-averaged to the
    model's (16×16, 20×15).  (The same unknowns as above: the compiled step is reused.)"""
    big = {k: np.kron(v, np.ones((8, 8))) for k, v in small_targets.items()}
    assert big["top"].shape == (128, 128) and big["oblique"].shape == (120, 160)
    res = df.fit(_small_scene(), big, {"fog.scattering": 1.5, "fog.absorption": 0.6,
                                       "shape.walls.albedo": 0.6},
                 forward=small_forward, downsample=8)
    for k in small_targets:
        np.testing.assert_allclose(res.targets[k], small_targets[k], rtol=1e-6)
    assert res.estimates["fog.scattering"] == pytest.approx(2.0, rel=1e-3)


# ------------------------------------------------------------------ solvers, losses (toy)
@pytest.mark.parametrize("optimizer", ["lm", "gauss-newton", "bfgs"])
def test_each_optimizer_recovers_the_toy_truth(optimizer):
    toy = Toy()
    truth = {"fog.scattering": 1.5, "fog.absorption": 0.3, "shape.walls.albedo": 0.6}
    res = df.fit(toy.scene, _toy_target(toy, **truth),
                 {"fog.scattering": 0.5, "fog.absorption": 1.0, "shape.walls.albedo": 0.3},
                 forward=toy, optimizer=optimizer, max_steps=200, rtol=1e-7, atol=1e-7)
    assert res.converged, (optimizer, res.message)
    for p, v in truth.items():
        assert res.estimates[p] == pytest.approx(v, rel=1e-3), (optimizer, p)


def test_robust_loss_ignores_outliers_that_bias_least_squares():
    toy = Toy(shape=(16, 16))
    truth = {"fog.scattering": 1.5, "fog.absorption": 0.3}
    tgt = _toy_target(toy, **truth)
    bad = tgt["top"].copy()
    bad.flat[::17] += 5.0 * bad.mean()  # 6% of pixels are hot
    init = {"fog.scattering": 1.0, "fog.absorption": 0.5}
    ls = df.fit(toy.scene, {"top": bad}, init, forward=toy)
    rob = df.fit(toy.scene, {"top": bad}, init, forward=toy, loss="cauchy", loss_scale=0.05)
    err = lambda r: max(abs(r.estimates[p] / v - 1) for p, v in truth.items())  # noqa: E731
    assert err(ls) > 0.1
    assert err(rob) < 0.01


def test_weights_mask_out_bad_pixels():
    toy = Toy(shape=(16, 16))
    truth = {"fog.scattering": 1.5, "fog.absorption": 0.3}
    tgt = _toy_target(toy, **truth)["top"]
    bad = tgt.copy()
    bad[:4] = np.nan  # unusable rows, masked out
    res = df.fit(toy.scene, {"top": bad}, {"fog.scattering": 1.0, "fog.absorption": 0.5},
                 forward=toy, weights={"top": ~np.isnan(bad)})
    for p, v in truth.items():
        assert res.estimates[p] == pytest.approx(v, rel=1e-4)


def test_edge_weight_without_known_edges_warns_and_changes_nothing():
    toy = Toy(shape=(16, 16))
    truth = {"fog.scattering": 1.5, "fog.absorption": 0.3}
    tgt = _toy_target(toy, **truth)
    start = {"fog.scattering": 1.0, "fog.absorption": 0.5}
    plain = df.fit(toy.scene, tgt, start, forward=toy)
    with pytest.warns(UserWarning, match="does not know which pixels straddle an edge"):
        res = df.fit(toy.scene, tgt, start, forward=toy, edge_weight=0.5)
    assert res.estimates == plain.estimates and res.settings["edge_pixels"] is None


def test_unidentifiable_unknowns_warn_and_report_the_correlation():
    """ζ and the sun's irradiance enter the toy image only as their product."""
    toy = Toy()
    tgt = _toy_target(toy, **{"fog.scattering": 1.5})
    with pytest.warns(IdentifiabilityWarning, match="near-singular|correlated"):
        res = df.fit(toy.scene, tgt, {"fog.scattering": 1.0, "sun.irradiance": 2.0},
                     forward=toy)
    assert res.warnings
    # and the product, which the image does determine, is right
    prod = res.estimates["fog.scattering"] * res.estimates["sun.irradiance"]
    assert prod == pytest.approx(1.5 * 3.0, rel=1e-4)


def test_statistics_flag_collinear_and_dead_columns():
    coords = [Coordinate("fog.scattering", 0, math.inf), Coordinate("fog.absorption", 0, math.inf),
              Coordinate("sky.radiance", 0, math.inf)]
    rng = np.random.default_rng(0)
    a = rng.normal(size=50)
    J = np.stack([a, 2 * a + 1e-6 * rng.normal(size=50), rng.normal(size=50)], 1)
    se, corr, cond, msgs, _ = statistics(rng.normal(size=50), J, 50, coords, np.zeros(3))
    assert cond > 1e4 and any("near-singular" in m for m in msgs)
    J[:, 2] = 0
    *_, msgs = statistics(rng.normal(size=50), J, 50, coords, np.zeros(3))[:4]
    assert any("sky.radiance" in m and "zero Jacobian" in m for m in msgs)


def test_standard_errors_match_the_linear_least_squares_formula():
    """For a model linear in the (log-)unknowns' physical values the GN covariance is exact:
    compare with numpy's ordinary least squares on the same data."""
    toy = Toy(shape=(12, 12))
    rng = np.random.default_rng(3)
    tgt = _toy_target(toy, **{"fog.scattering": 1.5, "fog.absorption": 0.3})["top"]
    noisy = tgt + rng.normal(0, 0.02, tgt.shape)
    res = df.fit(toy.scene, {"top": noisy}, {"fog.scattering": 1.0, "fog.absorption": 0.5},
                 forward=toy, rtol=1e-8, atol=1e-8)
    a, b, c = (np.asarray(v, np.float64) for v in (toy.a, toy.b, toy.c))
    A = np.stack([3.0 * a.ravel(), b.ravel()], 1)  # sun irradiance 3
    y = noisy.ravel() - 0.7 * c.ravel()  # walls albedo 0.7
    coef, rss, *_ = np.linalg.lstsq(A, y, rcond=None)
    s2 = rss[0] / (y.size - 2)
    se = np.sqrt(np.diag(s2 * np.linalg.inv(A.T @ A)))
    assert res.estimates["fog.scattering"] == pytest.approx(coef[0], rel=1e-4)
    assert res.estimates["fog.absorption"] == pytest.approx(coef[1], rel=1e-4)
    assert res.stderr["fog.scattering"] == pytest.approx(se[0], rel=1e-3)
    assert res.stderr["fog.absorption"] == pytest.approx(se[1], rel=1e-3)


# ------------------------------------------------------------------ checkpoint / resume
class _Kill(Exception):
    pass


@pytest.mark.parametrize("optimizer", ["lm", "bfgs"])
def test_resume_after_a_kill_reaches_the_same_answer(tmp_path, optimizer):
    toy = Toy()
    tgt = _toy_target(toy, **{"fog.scattering": 1.5, "fog.absorption": 0.3})
    init = {"fog.scattering": 0.4, "fog.absorption": 1.2}
    kw = dict(forward=toy, optimizer=optimizer, max_steps=200)
    full = df.fit(toy.scene, tgt, init, **kw)
    ck = tmp_path / "fit.ckpt"

    def kill(entry):
        if entry["step"] == 3:
            raise _Kill

    with pytest.raises(_Kill):
        df.fit(toy.scene, tgt, init, checkpoint=ck, callback=kill, **kw)
    assert ck.exists()
    res = df.fit(toy.scene, tgt, init, checkpoint=ck, resume=True, **kw)
    assert res.iterations == full.iterations
    assert res.estimates == full.estimates  # bit for bit
    assert [h["values"] for h in res.history] == [h["values"] for h in full.history]
    # a fit stopped by max_steps resumes with a larger max_steps (what `difffog fit` advises)
    ck2 = tmp_path / "stopped.ckpt"
    stopped = df.fit(toy.scene, tgt, init, checkpoint=ck2, **dict(kw, max_steps=3))
    assert stopped.result == "nonlinear_max_steps_reached" and stopped.iterations == 3
    res = df.fit(toy.scene, tgt, init, checkpoint=ck2, resume=True, **kw)
    assert res.iterations == full.iterations and res.estimates == full.estimates
    # a checkpoint of another fit is refused
    with pytest.raises(DifffogError, match="different fit"):
        df.fit(toy.scene, tgt, {"fog.scattering": 0.5, "fog.absorption": 1.2},
               checkpoint=ck, resume=True, **kw)
    # one whose state has other leaves (an older difffog's) in one line, not a KeyError
    with np.load(ck) as z:
        kept = {k: z[k] for k in z.files if k != max(f for f in z.files if f.startswith("leaf"))}
    np.savez(tmp_path / "short.npz", **kept)
    with pytest.raises(DifffogError, match="does not match this fit's solver state"):
        df.fit(toy.scene, tgt, init, checkpoint=tmp_path / "short.npz", resume=True, **kw)


def test_resume_without_a_checkpoint_is_an_error(tmp_path):
    toy = Toy()
    with pytest.raises(DifffogError, match="no checkpoint"):
        df.fit(toy.scene, _toy_target(toy), ["fog.scattering"], forward=toy,
               checkpoint=tmp_path / "none.ckpt", resume=True)


# ------------------------------------------------------------------ input errors
@pytest.mark.parametrize("targets,unknowns,kw,match", [
    ({"top": np.ones((8, 10))}, ["fog.scatter"], {}, "fog.scatter.*Did you mean 'fog.scattering'"),
    ({"top": np.ones((8, 10))}, {"fog.scattering": (5.0, 0.1, 2.0)}, {}, "outside"),
    ({"top": np.ones((8, 10))}, {"shape.walls.albedo": 1.5}, {}, "outside"),
    ({"top": np.ones((8, 10))}, {"shape.walls.albedo": (0.5, 0.0, 2.0)}, {}, "bounds"),
    ({"top": np.ones((8, 10))}, {"shape.ball-mid.emission": None}, {}, "outside"),
    ({"top": np.ones((9, 10))}, ["fog.scattering"], {}, r"expected \(height, width\) = \(8, 10\)"),
    ({"side": np.ones((8, 10))}, ["fog.scattering"], {}, "no camera 'side'.*top"),
    ({"top": np.full((8, 10), np.nan)}, ["fog.scattering"], {}, "NaN"),
    ({}, ["fog.scattering"], {}, "at least one"),
    ({"top": np.ones((8, 10))}, [], {}, "no unknowns"),
    ({"top": np.ones((8, 10))}, ["fog.scattering"], {"optimizer": "adam"}, "optimizer 'adam'"),
    ({"top": np.ones((8, 10))}, ["fog.scattering"], {"loss": "l1"}, "loss 'l1'"),
    ({"top": np.ones((8, 10))}, ["fog.scattering"], {"weights": {"top": np.zeros((8, 10))}},
     "zero weight"),
    ({"top": np.ones((8, 10))}, ["fog.scattering"], {"edge_weight": 1.5}, r"edge_weight.*\[0, 1\]"),
    ({"top": np.ones((8, 10))}, ["fog.scattering"], {"edge_weight": "half"}, "edge_weight"),
])
def test_bad_input_gets_one_line_errors(targets, unknowns, kw, match):
    toy = Toy()
    with pytest.raises(DifffogError, match=match) as e:
        df.fit(toy.scene, targets, unknowns, forward=toy, **kw)
    assert "\n" not in str(e.value)


@pytest.mark.slow  # test_interface.py's short fit runs the splat's Jacobian by default
def test_fit_with_the_splat_forward_recovers_its_own_images():
    """forward="splat": the cloud's ζ and the ground's albedo from a splat image (the inverse
    crime, as a check that the splat's forward-mode Jacobian drives the fit)."""
    scene = df.load_scene("cloud-plane")
    fwd = make_model(scene, "splat", cameras=["top"], resolution=12, downsample=8)
    targets = {k: np.asarray(v) for k, v in fwd(fwd.params()).items()}
    res = df.fit(scene, targets, {"fog.scattering": 40.0, "shape.ground.albedo": 0.45},
                 forward=fwd)
    assert res.converged, res.message
    assert res.estimates["fog.scattering"] == pytest.approx(scene.fog.scattering, rel=1e-3)
    assert res.estimates["shape.ground.albedo"] == pytest.approx(0.6, rel=1e-3)


def test_downsample_must_divide_the_camera(small_forward):
    with pytest.raises(DifffogError, match="divisible by 7"):
        make_model(_small_scene(), "sweep", cameras=["top"], resolution=12, downsample=7)


@pytest.mark.slow
def test_fit_result_json_round_trips(small_forward, small_targets, tmp_path):
    res = df.fit(_small_scene(), small_targets, {"fog.scattering": 1.8, "fog.absorption": 0.5,
                                                 "shape.walls.albedo": 0.7},
                 forward=small_forward)
    d = json.loads(json.dumps(res.to_json()))
    assert d["estimates"]["fog.scattering"] == pytest.approx(2.0, rel=1e-3)
    assert d["converged"] and len(d["history"]) == res.iterations
    assert d["settings"]["cameras"] == ["oblique", "top"] and len(d["correlation"]) == 3


# ------------------------------------------------------------------ recovery (slow)
DATA = ROOT / "data_synthetic"


def _recover(scene_name, case, N=24, **fit_kw):
    """(result, truth) of a fit from ζ × 0.6, γ × 1.6, albedo − 0.15, both views at 1/4, to
    set 0's synthetic targets ("hires", "noise01", ...) or the Mitsuba images ("mc", whose
    truth is the scene's own values); N None: the fit's default."""
    from difffog.study.references import reference

    scene = df.load_scene(scene_name)
    truth = json.loads((DATA / "truth.json").read_text())[scene_name]["sets"][0]["params"]
    if case == "mc":
        targets = {c: reference(scene_name, c)[0] for c in ("top", "oblique")}
        truth = {p: float(df.get_param(df.Params.from_scene(scene), scene, p)) for p in truth}
    else:
        suffix = "" if case == "hires" else f"_{case}"
        targets = {c: np.load(DATA / scene_name / "set0" / f"{c}{suffix}.npy")
                   for c in ("top", "oblique")}
    start = {p: (0.6 * v if p == "fog.scattering" else 1.6 * v if p == "fog.absorption"
                 else v - 0.15) for p, v in truth.items()}
    res = df.fit(scene, targets, start, resolution=N, downsample=4, **fit_kw)
    return res, truth


# slow: a full-size render at N = 96, M = 5 per scene (0.5 / 0.5 / 4-5 min on 2 cores)
@pytest.mark.slow
@pytest.mark.parametrize("scene_name", ["fog-balls", "translucent-cube", "cloud-plane"])
def test_the_synthetic_targets_are_todays_model(scene_name):
    """The finer targets of data_synthetic/ are what today's model renders at their recorded
    settings (set 0): a fit against them measures its own lattice error, not also a drift of
    the model since they were made (cloud-plane's were 0.82% RMS off in the oblique view until
    stop 57, which γ took as +10%).  After a change to the forward model, regenerate them
    (``data_synthetic/make.py``) and the recovery studies that use them."""
    info = json.loads((DATA / "truth.json").read_text())[scene_name]
    r = info["render"]
    scene = df.load_scene(scene_name)
    model = df.forward_model(scene, "sweep", accuracy=None, resolution=r["resolution"],
                             M=r["directions"], supersample=r["supersample"], tol=r["tol"],
                             max_iterations=2000)
    p = model.params()
    for path, v in info["sets"][0]["params"].items():
        p = df.set_param(p, scene, path, v)
    with warnings.catch_warnings():  # cloud-plane's steps are thick at N = 48 (it says so)
        warnings.simplefilter("ignore", df.ThickStepWarning)
        images = model(p)
    for cam, img in images.items():
        want = np.load(DATA / scene_name / "set0" / f"{cam}.npy").astype(np.float64)
        got = np.asarray(img, np.float64)
        rms = np.sqrt(np.mean((got - want) ** 2)) / want.mean()
        assert rms < 1e-3, (cam, rms)


# The exact-geometry issue's aim: ζ, γ and the walls' albedo within 2% from finer targets
# (data_synthetic/, set 0), fit at N = 24, M = 3 without the model-error correction.  Measured
# by benchmarks/recovery_study.py: against targets at N = 48, M = 4 −1.1%, −0.2%, −0.9%
# (benchmarks/results/recovery.md, 2026-11-27); against N = 96, M = 5 −1.98%, −0.18%, −0.15%
# (recovery_stop59_n24.md, 2026-12-01; 1% noise: −1.94%): ζ 0.02 point inside, the sweep's
# lattice bias at N = 24, which fit(model_error="refine") corrects and states.
RECOVERY_BOUNDS = {
    ("fog-balls", "hires"): {"fog.scattering": 2.0, "fog.absorption": 2.0,
                             "shape.walls.albedo": 2.0},
    ("fog-balls", "noise01"): {"fog.scattering": 2.0, "fog.absorption": 2.0,
                               "shape.walls.albedo": 2.0},
}


@pytest.mark.slow
@pytest.mark.parametrize("scene_name,case", list(RECOVERY_BOUNDS))
def test_recovery_from_finer_targets_within_the_measured_bias(scene_name, case):
    res, truth = _recover(scene_name, case)
    assert res.converged, res.message
    for p, bound in RECOVERY_BOUNDS[(scene_name, case)].items():
        err = 100 * abs(res.estimates[p] / truth[p] - 1)
        assert err <= bound, (p, err)


# Issue 16's aim, at `difffog fit`'s defaults (N = 32, M = 3, both views at 1/4, the estimate
# corrected to N = 64, M = 4 with the model error's three checks): within 1% of the truth from
# the finer synthetic targets (set 0), within 2% from the Mitsuba 3 images, and the truth within
# 3 total uncertainties.  Measured (benchmarks/results/recovery_stop59_n32.md, 2026-12-01, the
# targets rendered at N = 96, M = 5): fog-balls −0.29 / −0.24 / −0.01% (set 0), −1.72 / +0.93 /
# +0.08% (Mitsuba); translucent-cube −0.53 / +0.34 / −0.23%, −1.09 / +0.26 / −0.32%.  Before
# the brightness floor (stop 53) the study's one miss was at N = 24: translucent-cube's ground
# albedo against Mitsuba lay 5.4 total uncertainties off (−0.32% against ±0.06%), a bias none
# of the lattice checks sees (docs/fitting.md); the floor covers it, checked below.
DEFAULT_FIT_BOUNDS = {("fog-balls", "hires"): 1.0, ("fog-balls", "mc"): 2.0,
                      ("translucent-cube", "hires"): 1.0, ("translucent-cube", "mc"): 2.0}


@pytest.mark.slow  # a fit at N = 32 and its three renders of the model error (~1 min each)
@pytest.mark.parametrize("scene_name,case", list(DEFAULT_FIT_BOUNDS))
def test_the_fits_defaults_recover_the_truth_within_their_uncertainty(scene_name, case):
    res, truth = _recover(scene_name, case, N=None, model_error="refine")
    assert res.converged, res.message
    assert [lv["resolution"] for lv in res.ladder] == [32, 64, 48, 32]
    for p, v in truth.items():
        assert 100 * abs(res.estimates[p] / v - 1) <= DEFAULT_FIT_BOUNDS[(scene_name, case)], (
            p, res.estimates[p], v)
        assert abs(res.estimates[p] - v) <= 3 * res.uncertainty[p], (
            p, res.estimates[p], v, res.uncertainty[p])


@pytest.mark.slow
def test_translucent_cube_ground_albedo_against_mitsuba_within_its_uncertainty_at_24():
    """The ground's albedo sits −0.32% against the Mitsuba image at every N and M tried, a
    bias no finer lattice reveals (its lattice parts are 0.02–0.04%): the brightness floor
    (0.5% for the sweep) covers it, and the top view's residual (1.6% of its mean, 1.4× what
    its noise, the lattice and the floor explain; stop 76) adds a misfit part of about 0.9%:
    the total stays informative (under 1.5%; 1.02% measured, 0.41% before the misfit part
    was counted), with no misfit warning."""
    with warnings.catch_warnings():
        warnings.simplefilter("error", df.MisfitWarning)
        res, truth = _recover("translucent-cube", "mc", N=24, model_error="refine")
    p = "shape.ground.albedo"
    parts = res.model_error_parts[p]
    assert parts["brightness"] > 3 * max(parts["lattice"], parts["directions"])
    assert 0 < parts["misfit"] < 0.012 * truth[p]
    assert abs(res.estimates[p] - truth[p]) <= 3 * res.uncertainty[p]
    assert res.uncertainty[p] < 0.015 * truth[p]


def test_stall_test_counts_rejected_steps_after_progress():
    """Rejected steps (unknowns unchanged, loss unchanged) end the fit once the unknowns have
    moved; the first rejections of a too-long step from the start do not."""
    from difffog.fit._driver import _stalled

    def hist(losses, values):
        return [{"loss": loss, "values": {"fog.scattering": v}} for loss, v in zip(losses, values)]

    rejected_at_optimum = hist([2.0, 1.0, 1.0, 1.0, 1.0], [1.0, 2.0, 2.0, 2.0, 2.0])
    assert _stalled(rejected_at_optimum, 3, 1e-4)
    rejected_from_the_start = hist([5.0, 5.0, 5.0, 5.0], [1.0, 1.0, 1.0, 1.0])
    assert not _stalled(rejected_from_the_start, 3, 1e-4)
    still_falling = hist([5.0, 4.0, 3.0, 2.0], [1.0, 1.5, 1.8, 1.9])
    assert not _stalled(still_falling, 3, 1e-4)
    moved_without_gain = hist([1.0, 1.0, 1.0, 1.0], [2.0, 2.1, 2.05, 2.02])
    assert _stalled(moved_without_gain, 3, 1e-4)
    assert not _stalled(rejected_at_optimum, 0, 1e-4)
    assert not _stalled(rejected_at_optimum[:3], 3, 1e-4)


def test_ladder_levels_and_model_error_arithmetic():
    """The ladder's resolutions (3/4 of the fit's, not below where a shape is thinner than a
    voxel) and the first-order Richardson model error and total uncertainty it reports."""
    from difffog.fit._driver import _ladder_levels, _with_model_error
    from difffog.fit._unknowns import within_bounds
    from difffog.fit._result import FitResult

    fog_balls = df.load_scene("fog-balls")  # walls 0.05 thick: resolution >= 20
    assert _ladder_levels(fog_balls, "sweep", 32, None, "auto") == (24, 32)
    assert _ladder_levels(fog_balls, "sweep", None, None, "auto") == (24, 32)  # fit default
    assert _ladder_levels(fog_balls, "sweep", 24, None, "auto") == (20, 24)
    assert _ladder_levels(fog_balls, "sweep", 20, None, "auto") == ()  # nothing coarser fits
    assert _ladder_levels(fog_balls, "sweep", 32, None, None) == ()
    with pytest.raises(DifffogError, match="ladder needs a named solver"):
        _ladder_levels(fog_balls, object(), 32, None, "auto")  # a model object
    assert _ladder_levels(fog_balls, "sweep", None, None, (16, 32)) == (16, 32)
    with pytest.raises(DifffogError, match="ends at 32, but resolution=48"):
        _ladder_levels(fog_balls, "sweep", 48, None, (16, 32))
    with pytest.raises(DifffogError, match="coarse then fine"):
        _ladder_levels(fog_balls, "sweep", None, None, (32, 16))

    def result(zeta, se, name="successful"):
        return FitResult(paths=["fog.scattering"], estimates={"fog.scattering": zeta},
                         stderr={"fog.scattering": se}, correlation=np.eye(1),
                         initial={"fog.scattering": 1.0}, residual_rms=0.0, loss=0.0,
                         iterations=3, time_s=1.0, result=name, message="", warnings=[],
                         history=[])

    r = _with_model_error(result(2.1, 0.04), result(2.0, 0.05), (24, 32))
    assert r.model_error["fog.scattering"] == pytest.approx(3 * 0.1)  # × 24 / (32 − 24)
    assert r.uncertainty["fog.scattering"] == pytest.approx(math.hypot(0.04, 0.3))
    assert [lv["resolution"] for lv in r.ladder] == [24, 32]
    assert "model error: fog.scattering" in r.summary()
    d = json.loads(json.dumps(r.to_json()))
    assert d["uncertainty"]["fog.scattering"] == pytest.approx(math.hypot(0.04, 0.3))
    assert within_bounds(df.Unknown("shape.walls.albedo"), 1.0) == pytest.approx(0.999)
    assert within_bounds(df.Unknown("fog.g"), -0.5) == -0.5
    failed = _with_model_error(result(2.1, 0.04), result(1.0, 0.05, "nonlinear_max_steps_reached"),
                               (24, 32))
    assert math.isnan(failed.model_error["fog.scattering"]) and failed.warnings


# Was a strict expected failure (ζ at N = 10 / 12 was 2.077 / 2.074, the ladder's 0.0025 × 5
# missing the error 0.074); it passed at stop 43 (at 4092148 too; since when is not known: not
# every slow test ran at every stop), so the mark is dropped.  Not a better estimator: the
# estimates still jump between resolutions, now the other way (ζ 2.189 / 2.102, uncertainty
# 0.436 against an error of 0.102; γ 0.551 / 0.542, 0.047 against 0.042; walls 0.7004 /
# 0.6999, 0.0024 against 0.0001).
@pytest.mark.slow  # two fits and two compiled models (~2 min on 2 cores)
def test_ladder_uncertainty_covers_the_truth_of_finer_targets():
    """Targets rendered on a finer lattice (N = 20) than the fit's (12, ladder from 10): the
    model error is real, and the total uncertainty must cover it (truth within 3 of them),
    where the noise-only standard error does not."""
    from helpers import FIT_DOWNSAMPLE, FIT_TRUTH, fit_scene

    scene = fit_scene()
    settings = {"M": 2, "tol": 1e-6}
    fine = make_model(scene, "sweep", cameras=["top", "oblique"], resolution=20,
                      downsample=FIT_DOWNSAMPLE, model_settings=settings)
    p = fine.params()
    for path, v in FIT_TRUTH.items():
        p = df.set_param(p, fine.scene, path, v)
    targets = {k: np.asarray(v) for k, v in fine(p).items()}
    start = {"fog.scattering": 1.5, "fog.absorption": 0.6, "shape.walls.albedo": 0.6}
    res = df.fit(scene, targets, start, resolution=12, downsample=FIT_DOWNSAMPLE,
                 model_settings=settings, ladder=(10, 12))
    assert res.converged, res.message
    assert [lv["resolution"] for lv in res.ladder] == [10, 12]
    for path, truth in FIT_TRUTH.items():
        err = abs(res.estimates[path] - truth)
        assert err <= 3 * res.uncertainty[path], (path, err, res.uncertainty[path])
        assert res.uncertainty[path] >= res.stderr[path]


def test_refine_resolution_arguments():
    from difffog.fit._driver import _refine_resolution

    fog_balls = df.load_scene("fog-balls")
    assert _refine_resolution(fog_balls, "sweep", 24, None, "refine", ()) == 48
    assert _refine_resolution(fog_balls, "sweep", None, None, "refine", ()) == 64  # default 32
    assert _refine_resolution(fog_balls, "sweep", 24, None, 40, ()) == 40
    assert _refine_resolution(fog_balls, "sweep", 24, None, None, ()) is None
    with pytest.raises(DifffogError, match="finer than the fit's"):
        _refine_resolution(fog_balls, "sweep", 24, None, 20, ())
    with pytest.raises(DifffogError, match="give one of ladder and model_error"):
        _refine_resolution(fog_balls, "sweep", 24, None, "refine", (18, 24))
    with pytest.raises(DifffogError, match="cannot"):
        _refine_resolution(fog_balls, object(), 24, None, "refine", ())


class LatticeToy(Toy):
    """The Toy with a first-order discretization error: its ζ reads (1 + 1/N) too strong on a
    lattice of N, as a coarse sweep's images are off by O(h)."""

    resolution: int = eqx.field(static=True)

    def __init__(self, resolution=10):
        super().__init__()
        self.resolution = resolution

    def images_from(self, light, p):
        img = super().images_from(light, p)["top"]
        return {"top": img + p.scattering * p.sun_irradiance * self.a / self.resolution}

    def at_resolution(self, n):
        return LatticeToy(n)


def test_refine_corrects_the_estimate_to_the_finer_lattice():
    """model_error="refine" returns the fit corrected to the doubled lattice (the Toy's images
    are linear in the unknowns, so one Gauss–Newton step lands on the finer lattice's own
    best fit, up to the log coordinate's curvature), keeps the fit itself in ``fitted``, and
    states the corrected estimate's first-order error, |corrected − fitted|·N/(N_f − N),
    which covers the truth (the limit N → ∞); a lattice between that lands on the first-order
    line adds nothing."""
    zeta, gamma = 1.5, 0.3
    truth = {"fog.scattering": zeta, "fog.absorption": gamma}
    exact = LatticeToy(10**9)  # the targets: the model without its discretization error
    target = _toy_target(exact, **truth)
    res = df.fit(exact.scene, target, {"fog.scattering": 0.5, "fog.absorption": 1.0},
                 forward=LatticeToy(10), model_error="refine")
    assert res.converged, res.message
    assert res.fitted["fog.scattering"] == pytest.approx(zeta / 1.1, rel=1e-4)
    assert res.estimates["fog.scattering"] == pytest.approx(zeta / 1.05, rel=2e-3)
    assert res.fitted["fog.absorption"] == pytest.approx(gamma, rel=1e-3)
    assert res.estimates["fog.absorption"] == pytest.approx(gamma, rel=1e-3)
    assert [lv["resolution"] for lv in res.ladder] == [10, 20, 15]  # the fit, N_f, between
    me = res.model_error["fog.scattering"]
    parts = res.model_error_parts["fog.scattering"]
    shift = abs(res.estimates["fog.scattering"] - res.fitted["fog.scattering"])
    assert parts["lattice"] == pytest.approx(shift)
    # N = 15 lies on the first-order line through N = 10 and 20 (up to the log coordinate's
    # curvature): no erratic part; the Toy has no direction set
    assert set(parts) == {"lattice", "lattice_between"}
    assert parts["lattice_between"] < 0.02 * parts["lattice"]
    assert me == pytest.approx(shift, rel=1e-3)
    assert abs(res.estimates["fog.scattering"] - zeta) <= 1.5 * res.uncertainty["fog.scattering"]
    assert res.uncertainty["fog.scattering"] >= me
    rep = res.to_json()
    assert rep["fitted"] == res.fitted and rep["estimates"] == res.estimates
    assert "corrected to N = 20" in res.summary()
    # a run with a text meter says what it renders after the steps, under its own label
    import io

    buf = io.StringIO()
    df.fit(exact.scene, target, {"fog.scattering": 0.5, "fog.absorption": 1.0},
           forward=LatticeToy(10), model_error="refine",
           progress=df.TextProgress("fit", file=buf))
    out = buf.getvalue()
    assert "fit " in out and "model error 0/2: N 20" in out and "model error 1/2: N 15" in out
    assert "model error 2/2" in out and out.index("fit ") < out.index("model error")
    plain = df.fit(exact.scene, target, {"fog.scattering": 0.5, "fog.absorption": 1.0},
                   forward=LatticeToy(10))
    assert plain.estimates == pytest.approx(res.fitted) and plain.to_json()["fitted"] == plain.estimates


class StrongLatticeToy(LatticeToy):
    """A lattice error ten times the LatticeToy's: ζ reads (1 + 10/N) too strong, so the
    correction from N = 10 to 20 is −25% and one Gauss–Newton step in log ζ stops short."""

    def images_from(self, light, p):
        img = Toy.images_from(self, light, p)["top"]
        return {"top": img + p.scattering * p.sun_irradiance * self.a * 10.0 / self.resolution}

    def at_resolution(self, n):
        return StrongLatticeToy(n)


def test_refine_iterates_the_correction_to_the_finer_fit():
    """The correction's further steps (the finer model's images at the last step's estimate,
    the fit's Jacobian: defect correction) land on the finer lattice's own best fit,
    ζ_true/(1 + 10/20), where one step stops 3.7% short (the log coordinate's curvature over a
    −25% step); they stop once a step is under a tenth of the stated uncertainty (measured: 3
    renders, 3e-7 off).  A cap reached before that warns and counts its last step in the
    model error; refine_steps=1 is the one step; a bad value is refused in one line."""
    zeta, gamma = 1.5, 0.3
    target = _toy_target(Toy(), **{"fog.scattering": zeta, "fog.absorption": gamma})
    start = {"fog.scattering": 0.5, "fog.absorption": 1.0}
    fine_fit = zeta / 1.5
    runs = {k: df.fit(Toy().scene, target, start, forward=StrongLatticeToy(10),
                      model_error="refine", refine_steps=k) for k in (1, 2, 4)}
    for k, res in runs.items():
        assert res.converged, res.message
        assert res.fitted["fog.scattering"] == pytest.approx(zeta / 2, rel=1e-4)
    one, capped, full = runs[1], runs[2], runs[4]
    assert one.ladder[1]["steps"] == 1 and capped.ladder[1]["steps"] == 2
    assert 2 <= full.ladder[1]["steps"] <= 4
    err = {k: abs(r.estimates["fog.scattering"] / fine_fit - 1) for k, r in runs.items()}
    assert err[1] > 0.01 and err[2] < 0.1 * err[1] and err[4] < 1e-4, err
    assert full.estimates["fog.absorption"] == pytest.approx(gamma, rel=1e-3)
    assert full.ladder[1]["estimates"] == full.estimates
    # the lattice part is the whole correction (× 1 for a doubled lattice), not the first step's
    assert full.model_error_parts["fog.scattering"]["lattice"] == pytest.approx(
        abs(full.estimates["fog.scattering"] - full.fitted["fog.scattering"]))
    assert "refine_steps" not in full.model_error_parts["fog.scattering"] and not full.warnings
    assert "3 Gauss–Newton steps (defect correction)" in full.summary()
    # the cap: its last step (larger than a tenth of the uncertainty) is counted and said
    last = capped.model_error_parts["fog.scattering"]["refine_steps"]
    assert last > 0.1 * capped.model_error["fog.scattering"]
    assert last == pytest.approx(abs(capped.estimates["fog.scattering"]
                                     - one.estimates["fog.scattering"]), rel=1e-3)
    assert any("stopped after 2 steps" in w and "refine_steps" in w for w in capped.warnings)
    for bad in (0, 1.5, True):
        with pytest.raises(df.DifffogError, match=r"refine_steps=.*an integer ≥ 1"):
            df.fit(Toy().scene, target, start, forward=StrongLatticeToy(10),
                   model_error="refine", refine_steps=bad)


class ErraticToy(LatticeToy):
    """A lattice error that does not shrink with N: ζ reads 5% too strong on an even lattice,
    5% too weak on an odd one (as where the nodes fall against a thin wall decides it)."""

    def images_from(self, light, p):
        img = Toy.images_from(self, light, p)["top"]
        sign = 1.0 if self.resolution % 2 == 0 else -1.0
        return {"top": img + sign * 0.05 * p.scattering * p.sun_irradiance * self.a}

    def at_resolution(self, n):
        return ErraticToy(n)


def test_refine_sees_a_lattice_error_that_does_not_shrink():
    """Fit at N = 10 and the doubled lattice agree (both even: the same +5%), so the first-order
    part is nil; the lattice between (N = 15, odd) lands off that line by the whole swing, and
    the total uncertainty covers the truth that the two even lattices alone would miss."""
    zeta, gamma = 1.5, 0.3
    truth = {"fog.scattering": zeta, "fog.absorption": gamma}
    target = _toy_target(Toy(), **truth)
    res = df.fit(Toy().scene, target, {"fog.scattering": 0.5, "fog.absorption": 1.0},
                 forward=ErraticToy(10), model_error="refine")
    assert res.converged, res.message
    parts = res.model_error_parts["fog.scattering"]
    assert res.estimates["fog.scattering"] == pytest.approx(zeta / 1.05, rel=1e-3)
    assert parts["lattice"] < 1e-3 * zeta
    # (one Gauss–Newton step in log ζ for a 10% swing: first order, not exact)
    assert parts["lattice_between"] == pytest.approx(zeta / 0.95 - zeta / 1.05, rel=0.1)
    err = abs(res.estimates["fog.scattering"] - zeta)
    assert 10 * res.stderr["fog.scattering"] < err <= res.uncertainty["fog.scattering"]


class UnconvergedBetweenToy(LatticeToy):
    """The LatticeToy whose light solve does not converge on the lattice between (N = 15)."""

    def light(self, params):
        code = df.RESULTS.max_iterations_reached if self.resolution == 15 else df.RESULTS.successful
        return ToyLight(result=jnp.asarray(code, jnp.int32),
                        iterations=jnp.asarray(1, jnp.int32),
                        error_estimate=jnp.asarray(0.0, params.scattering.dtype))

    def at_resolution(self, n):
        return UnconvergedBetweenToy(n)


def test_refine_says_which_check_it_left_out():
    """A check of the model error whose light solve fails is left out with a warning that
    names it (the correction and the other parts stand); a failed correction leaves the fit
    uncorrected, its model error NaN, and says so."""
    truth = {"fog.scattering": 1.5, "fog.absorption": 0.3}
    target = _toy_target(LatticeToy(10**9), **truth)
    start = {"fog.scattering": 0.5, "fog.absorption": 1.0}
    res = df.fit(Toy().scene, target, start, forward=UnconvergedBetweenToy(10),
                 model_error="refine")
    assert res.estimates["fog.scattering"] == pytest.approx(1.5 / 1.05, rel=2e-3)
    assert set(res.model_error_parts["fog.scattering"]) == {"lattice"}
    assert any("leaves out its check at N = 15" in w and "max_iterations_reached" in w
               for w in res.warnings), res.warnings
    res = df.fit(Toy().scene, target, start, forward=UnconvergedBetweenToy(10), model_error=15)
    assert res.estimates == res.fitted or not res.fitted  # not corrected
    assert math.isnan(res.model_error["fog.scattering"])
    # the total is unknown too, not the noise's standard error alone
    assert math.isnan(res.uncertainty["fog.scattering"]) and res.stderr["fog.scattering"] > 0
    assert any("the estimate is not corrected and the model error not estimated: at N = 15, "
               "that light solve did not converge" in w for w in res.warnings), res.warnings


def test_refine_counts_the_brightness_floor():
    """model_floor adds to the model error how far the estimates move when the camera's image
    is that much too bright.  The Toy's image is linear and homogeneous in ζ, γ and the walls'
    albedo, so a brightness bias ε is absorbed by scaling all three by 1 + ε: each part is
    ε·θ.  With an exposure among the unknowns the gain absorbs it alone.  "auto" gives a model
    of no registered solver no floor (the other refine tests), the sweep its 0.5%."""
    from difffog.fit._driver import _brightness_floor

    truth = {"fog.scattering": 1.5, "fog.absorption": 0.3, "shape.walls.albedo": 0.6}
    target = _toy_target(LatticeToy(10**9), **truth)
    start = {"fog.scattering": 0.5, "fog.absorption": 1.0, "shape.walls.albedo": 0.4}
    eps = 0.01
    res = df.fit(Toy().scene, target, start, forward=LatticeToy(10), model_error="refine",
                 model_floor=eps)
    assert res.converged, res.message
    for p in truth:
        parts = res.model_error_parts[p]
        assert parts["brightness"] == pytest.approx(eps * res.fitted[p], rel=0.02), p
        assert res.model_error[p] == pytest.approx(
            math.sqrt(sum(v * v for v in parts.values())), rel=1e-9)
    assert res.model_floor == eps and res.to_json()["model_floor"] == eps
    assert "a 1.00% brightness floor" in res.summary()
    fog = {"fog.scattering": 1.5, "fog.absorption": 0.3}  # the walls' albedo known
    gain = df.fit(Toy().scene, _toy_target(LatticeToy(10**9), **fog),
                  {"fog.scattering": 0.5, "fog.absorption": 1.0, "exposure": 1.0},
                  forward=LatticeToy(10), model_error="refine", model_floor=eps)
    assert gain.model_error_parts["exposure"]["brightness"] == pytest.approx(
        eps * gain.fitted["exposure"], rel=0.02)
    for p in fog:
        assert gain.model_error_parts[p]["brightness"] < 1e-3 * eps * gain.fitted[p], p
    assert _brightness_floor("sweep", "auto") == 0.005
    assert _brightness_floor(LatticeToy(10), "auto") == 0.0
    for bad in (-0.1, 1.0, float("nan"), "0.01", True):
        with pytest.raises(df.DifffogError, match=r"model_floor=.*use \"auto\" or a relative"):
            df.fit(Toy().scene, target, start, forward=LatticeToy(10), model_error="refine",
                   model_floor=bad)


def test_a_truth_of_zero_reads_as_an_absolute_error():
    """A fog without absorption (γ = 0) has no relative error: relative_error and the summary
    give the estimate's difference instead (they divided by zero)."""
    truth = {"fog.scattering": 1.5, "fog.absorption": 0.3}
    res = df.fit(Toy().scene, _toy_target(Toy(), **truth),
                 {"fog.scattering": 0.5, "fog.absorption": 1.0}, forward=Toy())
    said = {"fog.scattering": 1.5, "fog.absorption": 0.0}
    err = res.relative_error(said)
    assert err["fog.absorption"] == res.estimates["fog.absorption"] == pytest.approx(0.3, rel=1e-3)
    assert err["fog.scattering"] == pytest.approx(res.estimates["fog.scattering"] / 1.5 - 1)
    line = [ln for ln in res.summary(said).splitlines() if ln.startswith("fog.absorption")][0]
    assert line.endswith("+0.3 (absolute)"), line


def test_an_unknown_whose_best_value_is_its_bound_is_held_there_with_a_one_sided_limit():
    """A fog that does not absorb: the Toy's images of γ = 0 with 2% noise whose least-squares
    γ is negative.  In log coordinates γ only creeps towards 0 (max_steps); the fit then holds
    it at 0 and fits ζ and the walls again, converged, to the linear least squares of the other
    two columns; γ's standard error, and the others', are the three-column model's (the Toy is
    linear: σ²(AᵀA)⁻¹ with σ² from the two-column residual), and the images allow γ up to
    1.645 of it (95%, one-sided)."""
    toy = Toy()
    truth = {"fog.scattering": 1.5, "fog.absorption": 0.0, "shape.walls.albedo": 0.6}
    clean = _toy_target(toy, **truth)["top"].astype(np.float64)
    rng = np.random.default_rng(5)
    target = (clean + 0.02 * clean.mean() * rng.standard_normal(clean.shape)).astype(np.float32)
    sun = float(toy.params().sun_irradiance)
    A = np.stack([sun * np.asarray(toy.a).ravel(), np.asarray(toy.b).ravel(),
                  np.asarray(toy.c).ravel()], axis=1)
    t = target.ravel().astype(np.float64)
    assert np.linalg.lstsq(A, t, rcond=None)[0][1] < 0  # the images want γ below its bound
    two = np.linalg.lstsq(A[:, [0, 2]], t, rcond=None)[0]
    s2 = float(np.sum((A[:, [0, 2]] @ two - t) ** 2)) / (t.size - 3)
    se = np.sqrt(s2 * np.diag(np.linalg.inv(A.T @ A)))
    res = df.fit(toy.scene, {"top": target}, {"fog.scattering": 0.5, "fog.absorption": 1.0,
                                              "shape.walls.albedo": 0.4}, forward=Toy())
    assert res.converged and res.iterations > 50, (res.result, res.message)
    assert res.estimates["fog.absorption"] == 0.0
    assert res.estimates["fog.scattering"] == pytest.approx(two[0], rel=1e-4)
    assert res.estimates["shape.walls.albedo"] == pytest.approx(two[1], rel=1e-4)
    for k, p in enumerate(truth):
        assert res.stderr[p] == pytest.approx(se[k], rel=1e-3), p
    limit = res.at_bound["fog.absorption"]
    assert limit["bound"] == 0.0 and limit["upper_95"] == pytest.approx(1.6449 * se[1], rel=1e-3)
    assert "fog.absorption ran to its bound (0): the images need none of it" in res.message
    assert res.paths == list(truth) and res.initial["fog.absorption"] == 1.0
    assert res.correlation.shape == (3, 3) and np.all(np.isfinite(res.correlation))
    assert res.history[-1]["values"]["fog.absorption"] == 0.0
    assert res.to_json()["at_bound"] == res.at_bound
    assert "+0 (absolute)" in res.summary(truth)
    # with the model error: the finer lattice's pull on γ at the bound is its lattice part
    fine = df.fit(toy.scene, {"top": target}, {"fog.scattering": 0.5, "fog.absorption": 1.0,
                                               "shape.walls.albedo": 0.4},
                  forward=LatticeToy(10), model_error="refine")
    assert fine.converged and fine.estimates["fog.absorption"] == 0.0, fine.message
    assert math.isfinite(fine.model_error["fog.absorption"])
    assert fine.uncertainty["fog.absorption"] >= fine.stderr["fog.absorption"] > 0


def test_noise_sigma_reads_white_noise_not_shading_or_edges():
    """The noise estimate behind the goodness of fit: 0 for shading that is a sum of a function
    of x and one of y (the filter is a product of second differences) and for a sharp edge (a
    few columns, outside the median), the σ of white noise added to them within 10%."""
    from difffog.fit._misfit import noise_sigma

    rng = np.random.default_rng(0)
    y, x = np.mgrid[0:64, 0:80] / 64.0
    shaded = 1.0 + 0.5 * x ** 2 + np.sin(3 * y)
    edged = shaded + (x > 0.6)
    assert noise_sigma(shaded) < 1e-12 and noise_sigma(edged) < 1e-12
    for sigma in (0.01, 0.05):
        assert noise_sigma(edged + sigma * rng.standard_normal(edged.shape)) == pytest.approx(
            sigma, rel=0.1)
    assert noise_sigma(np.ones((2, 9))) == 0.0  # too small to tell


MISFIT_TRUTH = {"fog.scattering": 1.5, "fog.absorption": 0.3, "shape.walls.albedo": 0.6}
MISFIT_START = {"fog.scattering": 0.5, "fog.absorption": 1.0, "shape.walls.albedo": 0.4}


def misfit_targets():
    """The Toy's 'top' image at MISFIT_TRUTH without its lattice error, and the same with a
    bright blob the Toy has no term for (as a misplaced highlight or a wrong albedo leaves):
    (right, wrong), each {"top": image}."""
    right = _toy_target(LatticeToy(10**9), **MISFIT_TRUTH)
    y, x = np.mgrid[0:8, 0:10] / 7.0
    blob = 0.15 * right["top"].mean() * np.exp(-((x - 0.9) ** 2 + (y - 0.5) ** 2) / 0.05)
    return right, {"top": right["top"] + blob.astype(np.float32)}


def test_a_fit_says_so_when_the_model_does_not_explain_the_images():
    """A target with something the model lacks (a bright blob the Toy has no term for, as a
    misplaced highlight or a wrong albedo leaves) is fit with a residual far above what the
    lattice explains: a MisfitWarning, the goodness of fit says which camera, and the misfit's
    part of the model error brings the biased estimates within 3 total uncertainties of the
    truth.  The right target (the Toy without its lattice error) fits to its float rounding:
    no warning, no misfit part; the LatticeToy's lattice error (a multiple of ζ's column) is
    what the unknowns absorb, so it explains no residual."""
    truth, start = MISFIT_TRUTH, MISFIT_START
    right, wrong = misfit_targets()
    res = df.fit(Toy().scene, right, start, forward=LatticeToy(10), model_error="refine")
    g = res.goodness_of_fit["top"]
    assert res.converged and g["ratio"] < 0.1 and g["unexplained"] == 0.0, g
    assert g["lattice"] < 1e-5 and g["noise"] < 1e-6 and g["floor"] == 0.0
    assert g["expected"] == pytest.approx(1e-3)  # what the fit's tolerances resolve
    assert all("misfit" not in parts for parts in res.model_error_parts.values())
    assert res.to_json()["goodness_of_fit"] == res.goodness_of_fit
    with pytest.warns(df.MisfitWarning, match=r"the model does not explain the images: "
                                              r"residual RMS top .* of its mean"):
        bad = df.fit(Toy().scene, wrong, start, forward=LatticeToy(10), model_error="refine")
    g = bad.goodness_of_fit["top"]
    assert bad.converged and g["ratio"] > 2 and 0.75 < g["unexplained"] <= 1, g
    assert any("the model does not explain the images" in w for w in bad.warnings)
    assert "top" in bad.summary() and "(misfit)" in bad.summary()
    before = []
    for p, v in truth.items():
        parts = bad.model_error_parts[p]
        assert parts["misfit"] > 0, p
        without = math.hypot(bad.stderr[p], math.sqrt(sum(
            u * u for k, u in parts.items() if k != "misfit")))
        before.append(abs(bad.estimates[p] - v) / without)
        assert abs(bad.estimates[p] - v) <= 3 * bad.uncertainty[p], (p, parts)
    assert max(before) > 3, before  # the misfit's part is what covers them


class TooBigToy(LatticeToy):
    """The LatticeToy whose lattices finer than 15 do not fit in memory."""

    def at_resolution(self, n):
        if n > 15:
            raise df.ResourceError(f"N = {n} needs more memory than this machine has")
        return TooBigToy(n)


def test_refine_falls_back_to_a_lattice_that_fits():
    """When the doubled lattice (N = 20) is refused for memory, "refine" estimates the model
    error at 1.5 N (15) instead, says so, and its total uncertainty is of the error's size
    (the Toy's error is not only first order: 0.094 against 0.084 stated)."""
    truth = {"fog.scattering": 1.5, "fog.absorption": 0.3}
    target = _toy_target(LatticeToy(10**9), **truth)
    res = df.fit(Toy().scene, target, {"fog.scattering": 0.5, "fog.absorption": 1.0},
                 forward=TooBigToy(10), model_error="refine")
    assert res.ladder[1]["resolution"] == 15
    assert any("estimated at N = 15, not 20" in w and "more memory" in w
               for w in res.warnings), res.warnings
    err = abs(res.estimates["fog.scattering"] - 1.5)
    assert 0.5 * err < res.uncertainty["fog.scattering"] and err < 3 * res.uncertainty[
        "fog.scattering"]
    assert res.uncertainty["fog.scattering"] > 10 * res.stderr["fog.scattering"]


@pytest.mark.slow  # two fits and two compiled models (~4 min on 2 cores)
def test_refined_model_error_predicts_the_finer_fit_and_covers_the_truth():
    """Targets rendered on a finer lattice (N = 32) than the fit's (12): model_error=24 renders
    the fitted model at N = 24 with one more direction (M = 3) once and predicts, by one
    Gauss–Newton step, the estimate a fit there reaches (checked against that fit; at M = 2
    measured −0.147 against −0.145 in ζ), which becomes the estimate; its total uncertainty (the step × 12/(24 − 12), first order in the
    voxel size) covers the truth, where the noise-only standard error of the N = 12 fit does
    not cover that fit's error.  Each predicted shift is held to 20% of the finer
    fit's, or a quarter of the unknown's noise standard error where that is larger: the
    walls' albedo moves by less than one standard error (predicted +0.00066, the finer fit
    +0.00050, standard error 0.00085), and 20% of so small a shift would test the noise of one
    Gauss–Newton step, not the prediction the total uncertainty uses."""
    from helpers import FIT_DOWNSAMPLE, FIT_TRUTH, fit_scene

    scene = fit_scene()
    truth = df.apply_overrides(scene, [f"{k}={v}" for k, v in FIT_TRUTH.items()])
    targets = df.render(truth, accuracy=None, resolution=32, M=2).images
    start = {"fog.scattering": 1.5, "fog.absorption": 0.7, "shape.walls.albedo": 0.6}
    kw = dict(downsample=FIT_DOWNSAMPLE, model_settings={"M": 2})
    res = df.fit(scene, targets, start, resolution=12, model_error=24, **kw)
    assert res.converged, res.message
    # the correction's model: N = 24 with one more direction (M = 3)
    finer = df.fit(scene, targets, start, resolution=24, downsample=FIT_DOWNSAMPLE,
                   model_settings={"M": 3})
    predicted = res.ladder[1]["estimates"]
    assert predicted == res.estimates  # the estimate is the fit corrected to N = 24
    for path, v in FIT_TRUTH.items():
        shift = predicted[path] - res.fitted[path]
        actual = finer.estimates[path] - res.fitted[path]
        assert shift == pytest.approx(actual, rel=0.2, abs=0.25 * res.stderr[path]), path
        err = abs(res.fitted[path] - v)
        if path != "shape.walls.albedo":  # the noise-only error bar misses the model's error
            # (the walls' albedo's came from the reduced pixels' edges: since the fit's model
            # takes 16 edge rays per reduction it is within its standard error, 0.00025)
            assert err > 2 * res.stderr[path], path
        err = abs(res.estimates[path] - v)
        assert err <= 3 * res.uncertainty[path], (path, err, res.uncertainty[path])
    zeta = "fog.scattering"  # the unknown the lattice moves most: the correction helps
    assert abs(res.estimates[zeta] - FIT_TRUTH[zeta]) < abs(res.fitted[zeta] - FIT_TRUTH[zeta])
    assert "model error" in res.summary()


def test_reported_time_is_the_wall_time_of_the_call():
    """FitResult.time_s covers the whole call, the final statistics pass included (the
    bookkeeping, not a speed: it must lie within the wall time measured around the call and
    be most of it)."""
    import time

    toy = Toy()
    target = _toy_target(toy, **{"fog.scattering": 1.5, "fog.absorption": 0.3})
    t = time.perf_counter()
    res = df.fit(toy.scene, target, {"fog.scattering": 0.5, "fog.absorption": 1.0}, forward=toy)
    wall = time.perf_counter() - t
    assert 0.8 * wall <= res.time_s <= wall


def test_a_fit_of_g_from_an_isotropic_start_carries_the_moments(monkeypatch):
    """``fog.g`` as an unknown of a fog that starts isotropic (phase "isotropic", or g = 0):
    the sweep's "auto" order would be 0 there, the δ-isotropic scaling in which g only
    rescales ζ, and the fit fitted that (fog-balls from images of another absorption:
    g = −0.92 ± 0.001, "successful").  The fit's models carry the moments; a fog already
    anisotropic, an order the caller gives, another solver and other unknowns keep theirs."""
    from difffog.fit import _driver

    seen = []

    def stop(scene, forward, resolution, model_settings, ladder):
        seen.append(model_settings)
        raise RuntimeError("stop here: the models' settings are known")

    monkeypatch.setattr(_driver, "_ladder_levels", stop)
    iso = df.load_scene("fog-balls")
    target = {"top": np.ones((128, 128))}
    cases = [(iso, ["fog.g"], {}, {"phase_order": 3}),
             (df.apply_overrides(iso, ["fog.g=0"]), ["fog.g"], None, {"phase_order": 3}),
             (df.load_scene("cloud-plane"), ["fog.g"], None, None),
             (iso, ["fog.g"], {"phase_order": 1}, {"phase_order": 1}),
             (iso, ["fog.absorption"], None, None)]
    for scene, unknowns, given, expected in cases:
        with pytest.raises(RuntimeError, match="stop here"):
            df.fit(scene, target, unknowns, model_settings=given)
        assert seen[-1] == expected, (unknowns, given, seen[-1])
    with pytest.raises(RuntimeError, match="stop here"):
        df.fit(iso, target, ["fog.g"], forward="splat")
    assert seen[-1] is None


def test_a_fit_running_to_a_bound_says_so_when_it_runs_out_of_steps():
    """fog-balls' γ fitted to images of γ = 0 ran to max_steps (50 steps, 138 s) with γ falling
    a few per cent a step (log coordinates: its optimum is at u → −∞), and the message said
    "raise max_steps or start closer", which cannot help.  The history of that fit (γ from 0.3,
    0.0104 → 0.0016 over its last 40 steps) now gets one line on what to do; an unknown
    converging slowly elsewhere, or one that turned back, gets none."""
    from difffog.fit._driver import _towards_bound

    coords = [Coordinate("fog.absorption", 0.0, math.inf),
              Coordinate("fog.scattering", 0.0, math.inf),
              Coordinate("shape.walls.albedo", 0.0, 1.0)]
    hist = [{"values": {"fog.absorption": 0.3, "fog.scattering": 1.5,
                        "shape.walls.albedo": 0.5}}]
    hist += [{"values": {"fog.absorption": 0.0104 * 0.953 ** k, "fog.scattering": 2.12 - 0.002 * k,
                         "shape.walls.albedo": 0.7 - 0.01 * k}} for k in range(41)]
    msgs = _towards_bound(hist, coords)
    assert len(msgs) == 1, msgs
    assert msgs[0].startswith("fog.absorption fell from ") and "towards its bound 0" in msgs[0]
    assert "--set fog.absorption=0 without --unknown fog.absorption" in msgs[0]
    turned = hist[:-1] + [{"values": {**hist[-1]["values"],
                                      "fog.absorption": hist[-3]["values"]["fog.absorption"]}}]
    assert _towards_bound(turned, coords) == []
    slow = [{"values": {**e["values"], "fog.absorption": 0.2 + 0.3 * 0.9 ** k}}
            for k, e in enumerate(hist)]  # converging to 0.2, not to the bound
    assert _towards_bound(slow, coords) == []
    assert _towards_bound(hist[:8], coords) == []
