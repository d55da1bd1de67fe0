"""The gradient's adjoint light solve by hand-written transposed face sweeps
(``SweepSolver(adjoint="transposed")``, the default on a CPU for the step and sub-stepped
schemes): each face's transpose equals JAX's transpose of the batched sweep (float64, to
rounding), and gradients
through it equal those through JAX's route ("linearised") and finite differences (the
existing gradient checks run it too, since "auto" picks it on a CPU)."""

import itertools
import warnings

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import difffog as df
from difffog.forward.sweep._harmonics import basis
from difffog.forward.sweep._kernel import (_source_table, _sweep_face_batched,
                                           _sweep_face_substep, face_consts,
                                           substep_weight_scale, sweep_face_transposed)
from difffog.geometry._directions import direction_set
from helpers import random_face_geometry


def _transposes_agree(cases, substep: bool = False):
    """``cases``: (M, face shape, surfaces, L, sun phase, periodic combinations).  The
    sub-stepped scheme's reference is JAX's vjp of its batched program (its renormalization
    by the weight of the sub-steps whose light is known divides by a sum JAX cannot tell is
    constant, so ``jax.linear_transpose`` refuses it); the transpose takes the host's weight
    scale (``substep_weight_scale``), so the comparison checks that too."""
    rng = np.random.default_rng(2)
    f64 = lambda a: jnp.asarray(a, jnp.float64)  # noqa: E731
    program = _sweep_face_substep if substep else _sweep_face_batched
    for M, shape, surfaces, L, sun, combos in cases:
        D = (2 * M + 1) ** 2
        consts = face_consts(direction_set(M), 0, harm=basis(L, M).faces if L else None,
                             substep=substep)
        if sun:
            consts = eqx.tree_at(lambda c: c.sun_phase, consts, f64(rng.random(D)),
                                 is_leaf=lambda x: x is None)
        nj = _source_table(consts, jnp.float64)[0].shape[1]
        qshape = shape + ((1 + nj,) if nj else ())
        tau, bc = f64(0.8 * rng.random(shape)), jnp.zeros(D, jnp.float64)
        geo = random_face_geometry(rng, shape, D)
        geo = eqx.tree_at(lambda g: g.normal, geo, f64(geo.normal))
        for periodic in combos:
            kw = dict(M=M, periodic=periodic, warmup=4 if periodic[0] else 0, surfaces=surfaces)

            def sweep(Q, B, kw=kw):
                return program(Q, B, tau, bc, geo, consts, **kw)[:2]

            zeros = (jnp.zeros(qshape, jnp.float64), jnp.zeros(shape, jnp.float64))
            outs = jax.eval_shape(sweep, *zeros)
            cot = tuple(f64(rng.standard_normal(o.shape)) for o in outs)
            ref = jax.vjp(sweep, *zeros)[1](cot)
            g = geo
            if substep:
                g = eqx.tree_at(lambda g: g.wscale, geo, f64(substep_weight_scale(
                    geo.free, geo.surf, geo.blocked, consts.pq, consts.sub, consts.weight,
                    **kw)), is_leaf=lambda x: x is None)
            got = sweep_face_transposed(*cot, tau, g, consts, q_channels=1 + nj if nj else 0,
                                        **kw)
            for a, b in zip(got, ref):
                assert a.shape == b.shape
                scale = max(float(jnp.max(jnp.abs(b))), 1e-300)
                assert float(jnp.max(jnp.abs(a - b))) <= 1e-12 * scale, (M, shape, periodic)
            assert float(jnp.max(jnp.abs(ref[0]))) > 0.1  # something was carried back


# slow: the default suite's 12-minute budget on 2 cores (stop 56); by default the adjoint's
# gradients are checked against differences
# (test_sweep.py::test_gradients_match_finite_differences)
@pytest.mark.slow
def test_face_transpose_equals_jax_transpose_of_the_batched_sweep(x64):
    """Open and periodic sides (the carried cotangent's margins folded back, the periodic
    sweep's initial guess), blocked segments and surfaces, several row tiles, and
    per-direction sources (moments and the sun's phase channel)."""
    _transposes_agree([(2, (9, 20, 10), True, 0, False, [(False,) * 3, (True,) * 3]),
                       (2, (6, 7, 5), True, 1, True, [(True, False, True)])])


@pytest.mark.slow
def test_face_transpose_equals_jax_transpose_everywhere(x64):
    combos = list(itertools.product([False, True], repeat=3))
    _transposes_agree([(2, (9, 8, 10), False, 0, False, combos),
                       (2, (9, 8, 10), True, 0, False, combos),
                       (3, (7, 20, 5), True, 0, False, combos),
                       (3, (7, 1, 5), True, 0, False, combos[::2]),
                       (2, (6, 7, 5), True, 2, False, combos),
                       (2, (6, 7, 5), True, 1, True, combos)])


# slow: the default suite's 12-minute budget on 2 cores (stop 56); the sub-stepped scheme is not a
# default
@pytest.mark.slow
def test_substep_face_transpose_equals_the_batched_programs(x64):
    """The sub-stepped scheme's transpose (``_sweep_face_substep_transposed``): crossings'
    deposits and sources in the padded two-slab window, surface restarts, the periodic
    sweep's extra slab, several row tiles, moments and the sun's phase channel."""
    _transposes_agree([(3, (4, 20, 5), True, 1, True, [(True, False, True)])], substep=True)


@pytest.mark.slow
def test_substep_face_transpose_equals_the_batched_programs_everywhere(x64):
    combos = list(itertools.product([False, True], repeat=3))
    _transposes_agree([(2, (9, 8, 10), False, 0, False, combos),
                       (2, (9, 20, 10), True, 0, False, combos),
                       (3, (7, 8, 5), True, 0, False, combos),
                       (3, (6, 1, 5), True, 0, False, combos[::2]),
                       (2, (6, 7, 5), True, 2, False, combos),
                       (2, (6, 7, 5), True, 1, True, combos)], substep=True)


def _gradients(scene, adjoint, **settings):
    m = df.forward_model(scene, "sweep", accuracy=None, supersample=1, tol=1e-10,
                         adjoint=adjoint, **settings)
    p = m.params(jnp.float64)

    def loss(q):
        light = m.light(q)
        return jnp.sum(light.fluence ** 2) + jnp.sum(light.radiosity ** 2)

    assert m.solver.resolved_adjoint(m.solver.problem(m.geometry, p)) == adjoint
    return jax.tree.leaves(jax.grad(loss)(p))


# 45-55 s each on 2 cores: in -m slow (the default suite's finite-difference gradient checks
# take this route already: "auto" is "transposed" on a CPU)
@pytest.mark.slow
@pytest.mark.parametrize("name,settings", [
    ("fog-balls", dict(resolution=10, M=2)),  # surfaces, blocked segments, the sun
    ("cloud-plane", dict(resolution=10, M=2, scheme="step")),  # moments, the sun's phase
    ("fog-balls", dict(resolution=10, M=2, scheme="substep")),  # sub-steps past surfaces
    ("cloud-tomo", dict(resolution=8, M=3, scheme="substep")),  # sub-steps, density grid
    ("cloud-plane", dict(resolution=10, M=2, scheme="substep"))])  # sub-steps with moments
def test_gradients_by_both_adjoint_routes_agree(x64, name, settings):
    scene = df.load_scene(name)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # a coarse lattice's thin-wall and thick-step notes
        a = _gradients(scene, "linearised", **settings)
        b = _gradients(scene, "transposed", **settings)
    for x, y in zip(a, b):
        np.testing.assert_allclose(np.asarray(y), np.asarray(x), rtol=1e-9,
                                   atol=1e-12 * max(1.0, float(np.max(np.abs(x)))))
    assert any(float(np.max(np.abs(x))) > 0 for x in a)


# slow: the default suite's 12-minute budget on 2 cores (stop 56)
@pytest.mark.slow
def test_auto_takes_the_transposed_adjoint_where_it_applies_and_refuses_it_elsewhere():
    """On a CPU (the loop kernel) "auto" is "transposed" for the step and sub-stepped schemes
    in an isotropic fog, "linearised" for the linear scheme (where "transposed" is refused with a one-line
    error) and with an anisotropic phase's moments but where the sub-stepped scheme's native
    transpose serves."""
    from difffog.forward.sweep import _native

    scene = df.load_scene("cloud-tomo")
    native = "transposed" if _native.serves(jnp.float32) else "linearised"
    for name, scheme, want in (("cloud-tomo", "step", "transposed"),
                               ("cloud-tomo", "substep", "transposed"),
                               ("cloud-tomo", "linear", "linearised"),
                               ("cloud-plane", "step", "linearised"),
                               ("cloud-plane", "substep", native)):
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", UserWarning)  # cloud-plane's airplane at N = 8
            m = df.forward_model(df.load_scene(name), "sweep", accuracy=None, resolution=8,
                                 M=2, supersample=1, scheme=scheme)
        assert m.solver.resolved_adjoint(m.solver.problem(m.geometry, m.params())) == want
    m = df.forward_model(scene, "sweep", accuracy=None, resolution=8, M=2, supersample=1,
                         scheme="linear", adjoint="transposed")
    with pytest.raises(df.SceneError, match="has the step and sub-stepped schemes"):
        m.solver.resolved_adjoint(m.solver.problem(m.geometry, m.params()))
    with pytest.raises(df.SceneError, match="adjoint must be one of auto, transposed"):
        df.SweepSolver(adjoint="jax")
    with pytest.raises(df.SceneError, match="needs tangents=\"matrix-free\""):
        df.SweepSolver(adjoint="transposed", tangents="linearised")
