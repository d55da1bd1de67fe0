"""The sub-stepped scheme (``SweepSolver(scheme="substep")``, issue 14): each lattice segment,
which spans M planes, is crossed in M sub-steps that take the extinction and source of the
node nearest to where the ray crosses each plane, so the transport resolves the lattice
spacing h instead of the segment's M·h.

Independent truths: exact conservation (a purely scattering slab returns what it receives:
``test_linear_scheme.test_conservative_slab_returns_what_it_receives``), the thick cube's
float64 Monte Carlo value (``THICK_CUBE_REFERENCE``), finite differences for gradients.
"""

import warnings

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import difffog as df
from difffog import SweepSolver
from difffog.forward.sweep._kernel import substep_offsets
from difffog.geometry._directions import direction_set
from difffog.geometry._lattice import voxelize
from helpers import assert_light_gradient


@pytest.mark.parametrize("M", [2, 3, 5])
def test_intermediate_points_are_the_nearest_nodes(M):
    """Offsets of the M − 1 crossings of each direction (p, q, M) from the node it arrives at:
    within half a spacing of the exact crossing (p, q)·(M − j)/M, the same magnitude for ±p,
    and walking from the arrival (j = M − 1, next to it) back towards y − L (j = 1)."""
    pq = direction_set(M).pq
    off = substep_offsets(pq, M)
    assert off.shape == (M - 1, len(pq), 2)
    for j in range(1, M):
        exact = pq * (M - j) / M
        assert np.all(np.abs(off[j - 1] - exact) <= 0.5)
        assert np.array_equal(np.abs(off[j - 1]), np.abs(substep_offsets(-pq, M)[j - 1]))
    assert np.all(np.abs(off[0]) >= np.abs(off[-1]))  # nearer y − L first


# slow: the default suite's 12-minute budget on 2 cores (stop 56); the sub-stepped scheme is not a
# default
@pytest.mark.slow
def test_sub_steps_bring_the_thick_cube_closer_to_its_independent_value():
    """Issue 14's cube (ζ = 100, γ = 0.001, a ball in it; float64 Monte Carlo 0.7271 ±
    0.0007) at N = 16, M = 2 with the step scheme's transport: sub-stepping each segment
    through its planes moves the top view from +6.5% (segments of 2 planes sampling only
    their ends; measured) to within 10% below, and the gap shrinks with N (N = 32: +8.3%
    step, −3.0% substep, measured; benchmarks/results/thick_cube.md)."""
    from difffog.study._semi_infinite import THICK_CUBE_REFERENCE, thick_cube

    ref = THICK_CUBE_REFERENCE[100.0][0]
    scene = thick_cube(100.0)
    got = {}
    for scheme in ("step", "substep"):
        m = df.forward_model(scene, "sweep", accuracy=None, resolution=16, M=2, tol=1e-4,
                             max_iterations=2000, supersample=1, scheme=scheme)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", df.ThickStepWarning)
            out = df.render(m)
        assert out.result == df.RESULTS.successful
        assert out.settings["solver_options"]["scheme"] == scheme  # the report names it
        got[scheme] = float(out.images["top"].mean()) / ref - 1
    assert got["step"] > 0.04  # the step scheme's surplus
    assert -0.10 < got["substep"] < 0.0, got
    assert m.settings()["solver_options"]["kernel"] == "loop"  # a CPU's direction loop


# default again since stop 83 (the suite compiles XLA's code at -O0: 16 s here): the density
# fit's scheme's gradients against differences on every CI run
def test_gradients_match_finite_differences(x64):
    """A heterogeneous cloud over a ground quad (cloud-tomo at N = 10, M = 3: crossings at
    lateral offsets, blocked segments at the ground), in float64: jax.grad through the
    implicit adjoint of the sub-stepped sweep against central differences."""
    scene = df.load_scene("cloud-tomo")
    lat = voxelize(scene, 10, 3)
    solver = SweepSolver(M=3, max_iterations=2000, tol=1e-12, adjoint_rtol=1e-11,
                         scheme="substep")
    assert_light_gradient(solver, scene, lat, seed=7)


# slow: the default suite's 12-minute budget on 2 cores (stop 56); the sub-stepped scheme is not a
# default
@pytest.mark.slow
def test_jvp_matches_finite_differences(x64):
    """The tangent of the sub-stepped light solve (forward mode, what a fit's Jacobian uses)
    against a central difference in ζ, on a small cloud over a ground quad in float64."""
    scene = df.load_scene("cloud-tomo")
    lat = voxelize(scene, 8, 3)
    solver = SweepSolver(M=3, max_iterations=2000, tol=1e-12, scheme="substep")
    geom = solver.prepare(scene, lat)
    p0 = df.Params.from_scene(scene, jnp.float64)
    wt = jnp.asarray(np.random.default_rng(1).random(geom.shape))

    def f(z):
        return jnp.sum(wt * solver.solve(geom, eqx.tree_at(lambda p: p.scattering, p0, z)).fluence)

    z0 = p0.scattering
    _, t = jax.jit(lambda z: jax.jvp(f, (z,), (jnp.ones_like(z),)))(z0)
    eps = 1e-4 * float(z0)
    fd = (float(jax.jit(f)(z0 + eps)) - float(jax.jit(f)(z0 - eps))) / (2 * eps)
    assert float(t) == pytest.approx(fd, rel=1e-6)


# slow: the default suite's 12-minute budget on 2 cores (stop 56); the sub-stepped scheme is not a
# default
@pytest.mark.slow
@pytest.mark.parametrize("zeta", [100.0, 1000.0, 10000.0])
def test_the_thick_cube_at_n32_is_within_5_percent_of_its_monte_carlo_value(zeta):
    """Issue 14's thick conservative limit, judged against the cube's own float64 Monte Carlo
    image (``THICK_CUBE_REFERENCE``: 0.7271 ± 0.0007, 0.7668 ± 0.0016, 0.770 ± 0.007): with
    sub-stepped segments N = 32, M = 2 (one lattice step 6, 62 and 625 mean free paths) reads
    −3.0%, −2.5% and −2.4% (measured), where the default scheme reads +5.1%, +3.5% and +1.7%
    (its ζ = 100 case is test_thick.py's strict xfail).  Within 5%, and below the
    semi-infinite medium's 0.773 (the cube's open sides lose light)."""
    from difffog.study._semi_infinite import THICK_CUBE_REFERENCE, semi_infinite_value, thick_cube

    ref, err = THICK_CUBE_REFERENCE[zeta]
    m = df.forward_model(thick_cube(zeta), "sweep", accuracy=None, resolution=32, M=2,
                         tol=1e-4, max_iterations=2000, supersample=1, scheme="substep")
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", df.ThickStepWarning)
        out = df.render(m)
    assert out.result == df.RESULTS.successful
    v = float(out.images["top"].mean())
    assert abs(v / ref - 1) < 0.05, (v, ref)
    assert v < semi_infinite_value()



def _loop_matches_batched(cases):
    """The CPU's direction loop (``_sweep_face_substep_loop``: the values on a CPU) against
    the batched program (the values on a GPU, and the derivatives everywhere) on random faces
    with surfaces and blocked segments: ``cases`` = (M, face shape, periodic sides, L).  The
    loop takes the host's weight scale (``substep_weight_scale``, as ``prepare_sweep`` makes
    it), the batched program sums the weights itself; for the first periodic combination the
    loop also runs without the scale (it then sums them too)."""
    import equinox as eqx

    from difffog.forward.sweep._harmonics import basis
    from difffog.forward.sweep._kernel import (_sweep_face_substep, _sweep_face_substep_loop,
                                               face_consts, substep_weight_scale)
    from helpers import random_face_geometry

    rng = np.random.default_rng(3)
    f32 = lambda a: jnp.asarray(a, jnp.float32)  # noqa: E731
    for M, shape, periodics, L in cases:
        D = (2 * M + 1) ** 2
        harm = basis(L, M).faces if L else None
        consts = face_consts(direction_set(M), 0, harm=harm, substep=True)
        Q = rng.random(shape + ((1 + harm.shape[-1],) if L else ()))
        if L:
            Q[..., 1:] *= 0.1
        args = (f32(Q), f32(rng.random(shape)), f32(0.8 * rng.random(shape)),
                f32(rng.random(D)), random_face_geometry(rng, shape, D), consts)

        geo = args[4]
        scales = [f32(substep_weight_scale(
            geo.free, geo.surf, geo.blocked, consts.pq, consts.sub, consts.weight, M=M,
            periodic=p, warmup=4 if p[0] else 0, surfaces=True)) for p in periodics]

        @jax.jit
        def both(scales, *a, M=M, periodics=periodics):
            out = []
            for i, periodic in enumerate(periodics):
                kw = dict(M=M, periodic=periodic, warmup=4 if periodic[0] else 0,
                          surfaces=True)
                scaled = eqx.tree_at(lambda g: g.wscale, a[4], scales[i],
                                     is_leaf=lambda x: x is None)
                ref = _sweep_face_substep(*a, **kw)
                out.append((_sweep_face_substep_loop(*a[:4], scaled, a[5], **kw), ref))
                if i == 0:
                    out.append((_sweep_face_substep_loop(*a, **kw), ref))
            return out

        for periodic, (a, b) in zip(periodics[:1] + periodics, both(scales, *args)):
            for x, y in zip(a, b):
                assert x.shape == y.shape
                np.testing.assert_allclose(np.asarray(x), np.asarray(y), rtol=2e-6, atol=2e-6,
                                           err_msg=f"M={M} {shape} {periodic}")
            assert float(jnp.max(a[0])) > 0.1  # the fluence was accumulated


@pytest.mark.parametrize("L", [0, 2])
def test_loop_restricted_to_the_fog_slabs_gives_the_same_light(L):
    """The sub-stepped loop given the planes that hold fog (``vol_range``, as the plan makes
    it) only moves the rays through the other slabs: E and the exit radiance everywhere, and Λ
    over the fog's planes, equal the loop that does the fog step everywhere, with surfaces,
    blocked segments, a periodic side and (L = 2) per-direction sources; Λ is 0 well away from
    the fog."""
    from difffog.forward.sweep._harmonics import basis
    from difffog.forward.sweep._kernel import (_sweep_face_substep_loop, face_consts,
                                               substep_weight_scale, sweep_face_transposed)
    from helpers import random_face_geometry

    rng = np.random.default_rng(5)
    M, shape, lo, hi = 3, (17, 9, 8), 6, 10
    D = (2 * M + 1) ** 2
    harm = basis(L, M).faces if L else None
    consts = face_consts(direction_set(M), 0, harm=harm, substep=True)
    fog = np.zeros(shape, bool)
    fog[lo:hi] = True
    Q = rng.random(shape + ((1 + harm.shape[-1],) if L else ()))
    Q[~fog] = 0.0
    if L:
        Q[..., 1:] *= 0.1
    tau = np.where(fog, 0.8 * rng.random(shape), 0.0)
    geo = random_face_geometry(rng, shape, D)
    periodic = (False, True, False)
    geo = eqx.tree_at(lambda g: g.wscale, geo, jnp.asarray(substep_weight_scale(
        geo.free, geo.surf, geo.blocked, consts.pq, consts.sub, consts.weight, M=M,
        periodic=periodic, warmup=0, surfaces=True), jnp.float32), is_leaf=lambda x: x is None)
    f32 = lambda a: jnp.asarray(a, jnp.float32)  # noqa: E731
    args = (f32(Q), f32(rng.random(shape)), f32(tau), f32(rng.random(D)), geo, consts)
    kw = dict(M=M, periodic=periodic, warmup=0, surfaces=True)
    run = jax.jit(lambda *a: (_sweep_face_substep_loop(*a, **kw),
                              _sweep_face_substep_loop(*a, **kw, vol=(True, True, (lo, hi)))))
    (lam, irr, ex), (lam_r, irr_r, ex_r) = run(*args)
    np.testing.assert_allclose(np.asarray(irr_r), np.asarray(irr), rtol=2e-6, atol=2e-6)
    np.testing.assert_allclose(np.asarray(ex_r), np.asarray(ex), rtol=2e-6, atol=2e-6)
    np.testing.assert_allclose(np.asarray(lam_r[lo:hi]), np.asarray(lam[lo:hi]), rtol=2e-6,
                               atol=2e-6)
    far = -(-hi // M) * M + M  # the planes after the slab that finishes the fog's
    assert float(jnp.max(jnp.abs(lam[far:]))) > 0.1  # the full loop's vacuum Λ
    assert float(jnp.max(jnp.abs(lam_r[far:]))) == 0.0  # not computed there
    assert float(jnp.max(lam_r[lo:hi])) > 0.1

    # its transpose (a gradient's adjoint) is the restricted loop's, to rounding: ⟨R(Q, B),
    # (Λ̄, Ē)⟩ = ⟨(Q, B), Rᵀ(Λ̄, Ē)⟩ with no boundary light, Λ̄ over the fog's planes
    lam_bar = np.zeros(lam.shape)
    lam_bar[lo:hi] = rng.standard_normal(lam_bar[lo:hi].shape)
    irr_bar = rng.standard_normal(shape)
    nq = Q.shape[-1] if L else 0
    tr = jax.jit(lambda lb, eb: sweep_face_transposed(
        lb, eb, args[2], geo, consts, **kw, q_channels=nq, vol_range=(lo, hi)))
    q_bar, b_bar = tr(f32(lam_bar), f32(irr_bar))
    fwd = jax.jit(lambda q, b: _sweep_face_substep_loop(q, b, *args[2:3], jnp.zeros_like(
        args[3]), *args[4:], **kw, vol=(True, True, (lo, hi)))[:2])
    lam0, irr0 = fwd(*args[:2])
    lhs = np.sum(np.asarray(lam0, np.float64) * lam_bar) + np.sum(np.asarray(irr0) * irr_bar)
    rhs = (np.sum(np.asarray(args[0], np.float64) * np.asarray(q_bar))
           + np.sum(np.asarray(args[1], np.float64) * np.asarray(b_bar)))
    assert abs(lhs - rhs) < 1e-5 * (abs(lhs) + 1.0), (lhs, rhs)
    # and it gives what the full transpose gives, where the fog is and on the surfaces
    q_full, b_full = jax.jit(lambda lb, eb: sweep_face_transposed(
        lb, eb, args[2], geo, consts, **kw, q_channels=nq))(f32(lam_bar), f32(irr_bar))
    np.testing.assert_allclose(np.asarray(b_bar), np.asarray(b_full), rtol=2e-5, atol=2e-5)
    np.testing.assert_allclose(np.asarray(q_bar[lo:hi]), np.asarray(q_full[lo:hi]), rtol=2e-5,
                               atol=2e-5)


# slow: the default suite's 12-minute budget on 2 cores (stop 56); the sub-stepped scheme is not a
# default
@pytest.mark.slow
def test_loop_program_matches_batched_program():
    """All sides open, and all periodic (the deposits folded back across u and v), at M = 3
    with the plane's rows in three tiles (deposits cross the tiles' edges);
    per-direction (anisotropic) sources at M = 2 with a periodic sweep axis and u side."""
    _loop_matches_batched([(3, (5, 36, 6), [(False,) * 3, (True,) * 3], 0),  # 3 row tiles
                           (2, (6, 7, 5), [(True, True, False)], 2)])


@pytest.mark.slow
def test_loop_program_matches_batched_program_everywhere():
    """Every combination of periodic sides at M = 3, a plane thinner than M, and more
    anisotropic cases."""
    import itertools

    combos = list(itertools.product([False, True], repeat=3))  # (w, u, v) periodic
    _loop_matches_batched([(3, (9, 8, 10), combos, 0), (3, (7, 1, 5), combos, 0),
                           (2, (6, 7, 5), combos, 2), (3, (5, 6, 7), combos[::3], 1)])
