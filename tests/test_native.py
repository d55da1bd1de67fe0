"""The native CPU kernel of the step scheme's face sweep (``forward/sweep/_native.py``) against
the XLA loop it replaces, and what happens where it cannot be built."""

import functools
import os
import shutil

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from difffog.forward.sweep import _kernel as K
from difffog.forward.sweep import _native
from difffog.geometry._directions import direction_set

needs_compiler = pytest.mark.skipif(
    not (os.environ.get("CXX") or shutil.which("c++") or shutil.which("g++")),
    reason="no C++ compiler: the native kernel is not built here (the XLA loop serves)")


@pytest.fixture
def native_state():
    """The native kernel's state as the process had it, back after the test."""
    saved = dict(_native._STATE)
    yield
    _native._STATE.clear()
    _native._STATE.update(saved)


@pytest.fixture
def native_off(native_state):
    """Run with the native kernel turned off."""
    _native._STATE.clear()
    _native._STATE.update(ok=False, why="off (test)")


def _face(M, shape, dt, seed=0):
    """Random inputs of one face sweep: fog with some empty nodes, surfaces with random
    normals and blocking bits, boundary radiance."""
    rng = np.random.default_rng(seed)
    D = (2 * M + 1) ** 2
    free = rng.random(shape) > 0.2
    surf = ~free & (rng.random(shape) > 0.5)
    normal = rng.normal(size=shape + (3,))
    normal /= np.linalg.norm(normal, axis=-1, keepdims=True)
    geo = K.FaceGeometry(free=jnp.asarray(free), surf=jnp.asarray(surf),
                         normal=jnp.asarray(normal, dt),
                         blocked=jnp.asarray(rng.integers(0, 256, shape + ((D + 7) // 8,),
                                                          dtype=np.uint8)))
    tau = rng.random(shape) * 3.0 * (rng.random(shape) > 0.3)  # thin to thick, some 0
    arrays = [jnp.asarray(a, dt) for a in (rng.random(shape), rng.random(shape), tau)]
    return (*arrays, jnp.asarray(rng.random(D), dt), geo,
            K.face_consts(direction_set(M), 2))


def _general_form(M, shape, dt, rng, linear: bool, order: int, sun: bool, face: int = 2):
    """(Q, consts) of the general form: Q with the moments' channels of the δ-M ``order``'s
    basis, the sun's phase channel, the linear scheme's three slope channels (random)."""
    import dataclasses

    from difffog.forward.sweep._harmonics import basis

    harm = basis(order, M).faces if order else None
    consts = K.face_consts(direction_set(M), face, harm=harm, linear=linear)
    if sun:
        consts = dataclasses.replace(consts, sun_phase=jnp.asarray(rng.random((2 * M + 1) ** 2)))
    channels = 1 + (harm.shape[2] if order else 0) + int(sun) + (3 if linear else 0)
    Q = jnp.asarray(np.concatenate([rng.random(shape + (1,)),
                                    0.2 * rng.standard_normal(shape + (channels - 1,))], -1), dt)
    return Q, consts


def _sweep(args, **kw):
    return jax.jit(lambda *a: K._sweep_face_loop(*a, **kw))(*args)


CASES = [  # M, surfaces, periodic (w, u, v), vol = (attenuate, fluence, vol_range)
    (2, True, (False, False, False), (True, True, None)),
    (2, True, (True, True, True), (True, True, None)),
    (3, False, (False, True, False), (True, True, (3, 9))),
    (3, True, (False, False, True), (True, False, None)),
    (2, True, (False, False, False), (False, True, None)),
]


@needs_compiler
@pytest.mark.parametrize("dtype", ["float64", "float32"])
@pytest.mark.parametrize("M,surfaces,periodic,vol", CASES)
def test_native_face_sweep_equals_the_xla_loop(M, surfaces, periodic, vol, dtype, x64,
                                               native_off):
    """Λ, E and the exit radiance of one face sweep, native against XLA's loop, to rounding:
    open and periodic sides (the border wrap), surfaces (blocking bits, normals), fog only
    in some slabs (``vol_range``), no fluence, no fog step; a plane whose rows are not a
    multiple of the kernel's tile."""
    dt = jnp.dtype(dtype)
    args = _face(M, (11, 9, 7), dt)
    kw = dict(M=M, periodic=periodic, warmup=2 * M + 1, surfaces=surfaces, vol=vol)
    ref = _sweep(args, **kw)  # the XLA loop (native_off)
    _native._STATE.clear()
    assert _native.available(), _native.status()
    got = _sweep(args, **kw)
    rtol = 1e-13 if dtype == "float64" else 1e-6
    for r, g in zip(ref, got):
        assert g.shape == r.shape and g.dtype == r.dtype
        np.testing.assert_allclose(np.asarray(g), np.asarray(r), rtol=rtol,
                                   atol=rtol * float(jnp.max(jnp.abs(r))))
    assert float(jnp.max(got[0] if vol[1] else got[1])) > 0  # something was summed


def _mixed_face(M, shape, dt, seed=1):
    """``_face``'s inputs with the surfaces where a lattice has them: SURFACE nodes (with
    normals) in a band of columns and a few rows, blocking bits in a shell around them and
    nowhere else, the rest fog without normals, so that a row has whole 64-byte vectors of fog
    only, of surfaces, and of blocking only, and a remainder."""
    rng = np.random.default_rng(seed)
    D = (2 * M + 1) ** 2
    nw, nu, nv = shape
    v = np.arange(nv)[None, None, :]
    u = np.arange(nu)[None, :, None]
    surf = np.broadcast_to((v >= 22) & (v < 26) | (u == nu - 1), shape).copy()
    shell = np.broadcast_to((v >= 17) & (v < 31) | (u >= nu - 3), shape) & ~surf
    free = ~surf & (rng.random(shape) > 0.05)
    normal = np.where(surf[..., None], rng.normal(size=shape + (3,)), 0.0)
    normal /= np.maximum(np.linalg.norm(normal, axis=-1, keepdims=True), 1e-30)
    bits = rng.integers(0, 256, shape + ((D + 7) // 8,), dtype=np.uint8)
    bits *= (shell & (rng.random(shape) > 0.3))[..., None].astype(np.uint8)
    geo = K.FaceGeometry(free=jnp.asarray(free), surf=jnp.asarray(surf),
                         normal=jnp.asarray(normal, dt), blocked=jnp.asarray(bits))
    tau = rng.random(shape) * 2.0 * ~surf
    arrays = [jnp.asarray(a, dt) for a in (rng.random(shape), rng.random(shape), tau)]
    return (*arrays, jnp.asarray(rng.random(D), dt), geo,
            K.face_consts(direction_set(M), 1))


@needs_compiler
@pytest.mark.parametrize("dtype", ["float64", "float32"])
@pytest.mark.parametrize("M,periodic,vol,threads", [
    (2, (False, False, True), (True, True, None), "2"),
    (3, (True, False, False), (True, True, None), "2"),
    # the kernel's other forms: no fog step (an empty volume), and the planes outside a volume
    # range (neither fog step nor fluence) beside those inside it without the fluence; and
    # the blocks on one thread (each pytest-xdist worker's share of two cores)
    (2, (False, False, False), (False, True, None), "2"),
    (2, (False, False, False), (True, False, (4, 11)), "1"),
])
def test_native_blocks_of_directions_on_long_rows_equal_the_xla_loop(M, periodic, vol, threads,
                                                                     dtype, x64, native_off,
                                                                     monkeypatch):
    """The isotropic step scheme's kernel on a large face (directions in blocks, each swept
    through the face one 64-byte vector at a time, its sums in registers) on rows of whole
    vectors: fog-only vectors, vectors with SURFACE nodes, vectors blocked for some directions
    only, and a remainder, against XLA's loop.  (The small faces above go plane by plane.)"""
    monkeypatch.setenv("DIFFFOG_THREADS", threads)  # two: the blocks shared between threads
    dt = jnp.dtype(dtype)
    shape = (16, 100, 53) if M == 2 else (16, 51, 53)  # ≥ 2¹⁸ updates: by blocks
    assert (2 * M + 1) ** 2 * np.prod(shape) >= 2 ** 18
    args = _mixed_face(M, shape, dt)
    kw = dict(M=M, periodic=periodic, warmup=2 * M + 1, surfaces=True, vol=vol)
    ref = _sweep(args, **kw)
    _native._STATE.clear()
    assert _native.available(), _native.status()
    got = _sweep(args, **kw)
    rtol = 1e-13 if dtype == "float64" else 2e-6
    for r, g in zip(ref, got):
        np.testing.assert_allclose(np.asarray(g), np.asarray(r), rtol=rtol,
                                   atol=rtol * float(jnp.max(jnp.abs(r))))
    lam, irr = np.asarray(got[0]), np.asarray(got[1])
    assert (lam.max() > 0) == vol[1]  # Λ summed where asked
    assert irr.max() > 0 and (irr[:, :-1, :17] == 0).all()  # E at normals only


def test_difffog_threads_sets_the_kernels_threads(monkeypatch):
    """``DIFFFOG_THREADS`` sets the kernels' threads (pytest-xdist's workers get their share
    of the cores through it, conftest.py); a value that is not a whole number is refused with
    a message that names the variable."""
    monkeypatch.setenv("DIFFFOG_THREADS", "3")
    assert _native._threads() == 3
    monkeypatch.setenv("DIFFFOG_THREADS", "0")
    assert _native._threads() == 1
    monkeypatch.setenv("DIFFFOG_THREADS", "two")
    with pytest.raises(ValueError, match="DIFFFOG_THREADS='two'"):
        _native._threads()
    monkeypatch.delenv("DIFFFOG_THREADS")
    assert _native._threads() >= 1


@needs_compiler
def test_native_sweeps_give_the_same_bits_at_every_call(x64, monkeypatch):
    """The kernels share their work among threads, each thread summing into its own arrays:
    each thread's share is fixed (the step scheme's blocks of directions, the sub-stepped
    scheme's row tiles), so a sweep repeated gives the same bits.  (Shares taken as threads
    came free summed Λ in an order that changed from call to call: a fit's Jacobian computed
    twice differed in its last bits.)"""
    monkeypatch.setenv("DIFFFOG_THREADS", "2")  # the blocks shared between two threads
    assert _native.available(), _native.status()
    args = _mixed_face(3, (16, 51, 53), jnp.dtype("float32"))  # by blocks (≥ 2¹⁸ updates)
    kw = dict(M=3, periodic=(False, False, False), warmup=7, surfaces=True,
              vol=(True, True, None))
    step = jax.jit(lambda *a: K._sweep_face_loop(*a, **kw))
    sargs, _, M, _, _, surfaces, vol, periodics = _substep_case(2, "float32")
    skw = dict(M=M, periodic=periodics[0], warmup=0, surfaces=surfaces, fluence=vol[1],
               vol=vol)
    sub = jax.jit(lambda *a: K._native_substep_call(*a, **skw))
    for f, a in ((step, args), (sub, sargs)):
        first = [np.asarray(x) for x in f(*a)]
        for _ in range(5):
            for x, y in zip(first, f(*a)):
                assert np.array_equal(x, np.asarray(y))


@needs_compiler
@pytest.mark.parametrize("dtype", ["float64", "float32"])
@pytest.mark.parametrize("linear,order,sun", [(True, 0, False), (False, 1, True),
                                               (True, 1, True)])
def test_native_general_form_equals_the_xla_loop(linear, order, sun, dtype, x64, native_off):
    """The kernel's general form (anisotropic fog, the linear scheme): each direction's source
    from the moments' and the sun's channels, the linear node update (its φ, ψ series near
    τ = 0: a fifth of the nodes have no fog), Λ's moments; open sides with surfaces and fog in
    some slabs only, and periodic sides (the initial carry from each direction's source)
    without surfaces or fluence: Λ (and its moments), E and the exit radiance to rounding."""
    M, shape = 2, (11, 9, 7)
    dt = jnp.dtype(dtype)
    _, B, tau, bc, geo, _ = _face(M, shape, dt, seed=5)
    Q, consts = _general_form(M, shape, dt, np.random.default_rng(5), linear, order, sun)
    args = (Q, B, tau, bc, geo, consts)
    rtol = 1e-12 if dtype == "float64" else 2e-6
    for periodic, surfaces, vol in [((False, False, False), True, (True, True, (3, 9))),
                                    ((True, True, False), False, (True, False, None))]:
        kw = dict(M=M, periodic=periodic, warmup=2 * M + 1, surfaces=surfaces, vol=vol)
        _native._STATE.clear()
        _native._STATE.update(ok=False, why="off (test)")
        ref = _sweep(args, **kw)  # the XLA loop
        _native._STATE.clear()
        assert _native.available(), _native.status()
        got = _sweep(args, **kw)
        for r, g in zip(ref, got):
            assert g.shape == r.shape and g.dtype == r.dtype
            np.testing.assert_allclose(np.asarray(g), np.asarray(r), rtol=rtol,
                                       atol=rtol * float(jnp.max(jnp.abs(r))))
        assert float(jnp.max(jnp.abs(got[2]))) > 0
        if vol[1] and order:
            assert got[0].shape == shape + ((order + 1) ** 2,)
            assert float(jnp.max(jnp.abs(got[0][..., 1:]))) > 0  # the moments were summed


SUBSTEP_CASES = [  # M, shape, L, sun, surfaces, vol, periodic sides (w, u, v)
    (2, (9, 7, 6), 0, False, True, (True, True, None), [(False,) * 3, (True,) * 3]),
    (3, (11, 9, 7), 2, True, True, (True, True, None), [(True, False, True),
                                                         (False, True, False)]),
    (3, (17, 9, 8), 0, False, True, (True, True, (6, 10)), [(False, True, False)]),
    (3, (10, 8, 9), 1, False, False, (True, False, None), [(True, True, False)]),
    (4, (9, 3, 10), 0, False, True, (False, True, None), [(False, False, True)]),
]


@needs_compiler
@pytest.mark.parametrize("case,dtype", [
    (0, "float64"), (1, "float64"), (2, "float32"), (3, "float64"), (4, "float32"),
    # slow: each compiles XLA's loop (4-8 s); the default suite's 12 minutes
    *[pytest.param(c, d, marks=pytest.mark.slow)
      for c, d in ((0, "float32"), (1, "float32"), (2, "float64"), (3, "float32"),
                   (4, "float64"))]])
def test_native_substep_equals_the_xla_loop(case, dtype, x64):
    """The sub-stepped scheme's native kernel (``_native.sweep_substep``) against XLA's loop
    (``_sweep_face_substep_loop``), to rounding: Λ (over the sub-steps whose light is known,
    its moments), E and the exit radiance, with surfaces (blocking bits, chains restarting or
    lost inside shapes), open and periodic sides (the deposits folded back, a periodic sweep
    axis's extra slab), anisotropic sources with the sun's channel, fog in some slabs only,
    no fluence, no fog step, a plane thinner than M."""
    assert _native.available(), _native.status()
    args, _, M, _, _, surfaces, vol, periodics = _substep_case(case, dtype)
    rtol = 1e-13 if dtype == "float64" else 3e-6
    for periodic in periodics:
        kw = dict(M=M, periodic=periodic, warmup=4 if periodic[0] else 0, surfaces=surfaces,
                  fluence=vol[1], vol=vol)
        ref = jax.jit(lambda *a: K._sweep_face_substep_loop(*a, **kw))(*args)
        got = jax.jit(lambda *a: K._native_substep_call(*a, **kw))(*args)
        for r, g in zip(ref, got):
            assert g.shape == r.shape and g.dtype == r.dtype
            np.testing.assert_allclose(np.asarray(g), np.asarray(r), rtol=rtol,
                                       atol=rtol * float(jnp.max(jnp.abs(r))),
                                       err_msg=f"{periodic}")
        assert float(jnp.max(jnp.abs(got[2]))) > 0.05  # light left the face
        if vol[0] and vol[1]:
            assert float(jnp.max(got[0])) > 0.1  # the fluence was accumulated


def _substep_case(case, dtype):
    """``SUBSTEP_CASES[case]``'s random face: (args of the sweep, its geometry with the host's
    weight scale per periodic combination, M, L's moment count, the source channels,
    surfaces, vol, periodics)."""
    import dataclasses

    import equinox as eqx

    from difffog.forward.sweep._harmonics import basis
    from helpers import random_face_geometry

    M, shape, L, sun, surfaces, vol, periodics = SUBSTEP_CASES[case]
    rng = np.random.default_rng(case)
    dt = jnp.dtype(dtype)
    D = (2 * M + 1) ** 2
    harm = basis(L, M).faces if L else None
    consts = K.face_consts(direction_set(M), 0, harm=harm, substep=True)
    if sun:
        consts = dataclasses.replace(consts, sun_phase=jnp.asarray(rng.random(D)))
    nk = harm.shape[-1] if L else 0
    nch = nk + int(sun)
    Q = rng.random(shape + ((1 + nch,) if nch else ()))
    if nch:
        Q[..., 1:] *= 0.1
    geo = random_face_geometry(rng, shape, D)
    geo = dataclasses.replace(geo, normal=jnp.asarray(geo.normal, dt))
    tau = 1.5 * rng.random(shape) * (rng.random(shape) > 0.2)  # some nodes without fog
    args = (jnp.asarray(Q, dt), jnp.asarray(rng.random(shape), dt), jnp.asarray(tau, dt),
            jnp.asarray(rng.random(D), dt), geo, consts)
    scaled = [eqx.tree_at(lambda g: g.wscale, geo, jnp.asarray(K.substep_weight_scale(
        geo.free, geo.surf, geo.blocked, consts.pq, consts.sub, consts.weight, M=M,
        periodic=p, warmup=4 if p[0] else 0, surfaces=surfaces), dt),
        is_leaf=lambda x: x is None) for p in periodics]
    return args, scaled, M, nk, (1 + nch) if nch else 0, surfaces, vol, periodics


@needs_compiler
@pytest.mark.parametrize("case,dtype", [(0, "float64"), (1, "float64"), (2, "float32"),
                                        (3, "float64"), (4, "float64")])
def test_native_substep_transpose_equals_the_xla_loop(case, dtype, x64, native_state):
    """The sub-stepped sweep's transpose (a gradient's adjoint light solve) from the native
    kernel (``_native.sweep_substep_transposed``) against XLA's
    (``_sweep_face_substep_transposed``) to rounding, Q̄ (every source channel) and B̄, on the
    cases of the forward's test; and it is the native forward's transpose: ⟨R(Q, B), (Λ̄, Ē)⟩
    = ⟨(Q, B), Rᵀ(Λ̄, Ē)⟩ with no boundary light."""
    args, scaled, M, nk, nq, surfaces, vol, periodics = _substep_case(case, dtype)
    saved = dict(_native._STATE)
    assert _native.available(), _native.status()
    rng = np.random.default_rng(10 + case)
    shape = args[2].shape
    dt = jnp.dtype(dtype)
    lam_bar = jnp.asarray(rng.standard_normal(shape + ((1 + nk,) if nk else ())), dt)
    irr_bar = jnp.asarray(rng.standard_normal(shape), dt)
    rtol = 1e-13 if dtype == "float64" else 3e-5
    for periodic, geo in zip(periodics, scaled):
        kw = dict(M=M, periodic=periodic, warmup=4 if periodic[0] else 0, surfaces=surfaces,
                  fluence=vol[1], q_channels=nq, vol_range=vol[2], attenuate=vol[0])

        def tr(lb, eb, kw=kw, geo=geo):
            return K._sweep_face_substep_transposed(lb, eb, args[2], geo, args[5], **kw)

        _native._STATE.clear()
        _native._STATE.update(ok=False, why="off (test)")
        ref = jax.jit(lambda lb, eb: tr(lb, eb))(lam_bar, irr_bar)  # XLA's loop
        _native._STATE.clear()
        _native._STATE.update(saved)
        run = jax.jit(lambda lb, eb: tr(lb, eb))
        assert _native.SUBSTEP_T_TARGET in run.lower(lam_bar, irr_bar).as_text()
        got = run(lam_bar, irr_bar)
        for r, g in zip(ref, got):
            assert g.shape == r.shape and g.dtype == r.dtype
            np.testing.assert_allclose(np.asarray(g), np.asarray(r), rtol=rtol,
                                       atol=rtol * float(jnp.max(jnp.abs(r))),
                                       err_msg=f"{periodic}")
        if vol[0] and vol[1]:  # (without fluence or fog only B̄ is not 0, with surfaces)
            assert float(jnp.max(jnp.abs(got[0]))) > 0
        assert float(jnp.max(jnp.abs(got[1]))) > 0 or not surfaces
        if dtype == "float64":  # the adjoint identity with the native forward
            fw = dict(M=M, periodic=periodic, warmup=kw["warmup"], surfaces=surfaces,
                      fluence=vol[1], vol=vol)
            lam, irr, _ = jax.jit(lambda q, b: K._native_substep_call(
                q, b, args[2], jnp.zeros_like(args[3]), geo, args[5], **fw))(*args[:2])
            lhs = float(jnp.sum(lam * lam_bar) + jnp.sum(irr * irr_bar))
            rhs = float(jnp.sum(args[0] * got[0]) + jnp.sum(args[1] * got[1]))
            assert abs(lhs - rhs) < 1e-11 * (abs(lhs) + 1.0), (lhs, rhs)


@needs_compiler
def test_the_substep_scheme_on_a_cpu_runs_the_native_kernel():
    """``sweep_face`` with the loop kernel and the sub-stepped scheme's constants calls the
    native kernel (its custom call is in the compiled program), unless it is turned off."""
    assert _native.available(), _native.status()
    args = _face(2, (6, 5, 4), jnp.dtype("float32"))
    consts = K.face_consts(direction_set(2), 2, substep=True)
    kw = dict(M=2, periodic=(False, False, False), warmup=0, surfaces=True, kernel="loop")
    text = jax.jit(lambda *a: K.sweep_face(*a, consts, **kw)).lower(*args[:5]).as_text()
    assert _native.SUBSTEP_TARGET in text


@needs_compiler
def test_native_face_sweep_under_vmap_is_each_member(x64):
    """A batched light solve (``render_batch``, a fit's tangents) vmaps the sweep: the custom
    call then runs once per member, each equal to its own sweep."""
    assert _native.available(), _native.status()
    args = _face(2, (7, 6, 5), jnp.dtype("float64"))
    kw = dict(M=2, periodic=(False, False, False), warmup=5, surfaces=True,
              vol=(True, True, None))
    Qb = jnp.stack([args[0], 2.0 * args[0] + 0.1])
    out = jax.jit(jax.vmap(lambda q: K._sweep_face_loop(q, *args[1:], **kw)))(Qb)
    for i in range(2):
        one = _sweep((Qb[i], *args[1:]), **kw)
        for b, o in zip(out, one):
            np.testing.assert_allclose(np.asarray(b[i]), np.asarray(o), rtol=1e-13, atol=1e-15)


def test_without_a_compiler_the_xla_loop_serves(tmp_path, monkeypatch, x64, native_state):
    """No compiler (or a failed build): ``available()`` is False, ``status()`` says why in
    one line, nothing is left in the build folder, and the sweep is the XLA loop's."""
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path))
    monkeypatch.setenv("CXX", str(tmp_path / "no-such-compiler"))
    _native._STATE.clear()
    assert not _native.available()
    line = _native.status()
    assert line.startswith("XLA loop: not built (") and "\n" not in line
    assert not list((tmp_path / "difffog" / "native").glob("*"))  # nothing half-written
    args = _face(2, (5, 4, 4), jnp.dtype("float64"))
    lam, irr, exit_ = _sweep(args, M=2, periodic=(False,) * 3, warmup=5, surfaces=True,
                             vol=(True, True, None))
    assert lam.shape == (5, 4, 4) and exit_.shape == (2, 25, 4, 4)
    assert float(jnp.max(lam)) > 0
    monkeypatch.setenv("DIFFFOG_NATIVE", "0")
    _native._STATE.clear()
    assert not _native.available() and "turned off" in _native.status()


def test_a_part_that_fails_to_compile_leaves_nothing(tmp_path, monkeypatch, native_state):
    """The library is compiled as ``PARTS`` objects at once: one part's compiler error (the
    others succeeding) makes ``available()`` False with that error's line in ``status()``, and
    leaves neither objects nor a library in the build folder."""
    fake = tmp_path / "fake-c++"
    fake.write_text("#!/bin/sh\n"
                    "case \"$*\" in *--version*) echo 'fake c++ 1.0'; exit 0;; esac\n"
                    "case \"$*\" in *-DDIFFFOG_PART=1*) echo 'sweep_face.cc:1: error: part 1 "
                    "broke' >&2; exit 1;; esac\n"
                    "for a; do [ \"$prev\" = -o ] && : > \"$a\"; prev=$a; done\n")
    fake.chmod(0o755)
    cache = tmp_path / "cache"
    monkeypatch.setenv("XDG_CACHE_HOME", str(cache))
    monkeypatch.setenv("CXX", str(fake))
    _native._STATE.clear()
    assert not _native.available()
    assert _native.status() == "XLA loop: not built (sweep_face.cc:1: error: part 1 broke)"
    assert not list((cache / "difffog" / "native").rglob("*"))


def test_old_builds_are_pruned(tmp_path):
    """Builds of other sources, compilers or CPUs are deleted once not loaded for
    ``PRUNE_DAYS``; recent ones, the one being kept and other files stay."""
    import time

    now = time.time()
    ages = {"sweep_face-old.so": 40, "sweep_face-recent.so": 5, "sweep_face-keep.so": 90,
            "notes.txt": 90}
    for name, days in ages.items():
        p = tmp_path / name
        p.write_bytes(b"x")
        os.utime(p, (now - days * 86400, now - days * 86400))
    gone = _native._prune(tmp_path, keep=tmp_path / "sweep_face-keep.so")
    assert gone == [tmp_path / "sweep_face-old.so"]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["notes.txt", "sweep_face-keep.so",
                                                          "sweep_face-recent.so"]


@needs_compiler
def test_blocks_of_directions_in_the_world_frame_equal_the_face_frame(x64, monkeypatch):
    """The step scheme's blocks on a large face (≥ 2¹⁸ updates) reading q, b and writing Λ, E
    in the world frame (gathered and written back by whole planes per thread) against the
    face-frame path, on faces whose plane count is odd (the threads' planes unequal)."""
    monkeypatch.setenv("DIFFFOG_THREADS", "2")  # the blocks shared between two threads
    from difffog.geometry._directions import FACE_AXES

    assert _native.available(), _native.status()
    M, world, dt = 2, (47, 44, 41), jnp.dtype("float64")
    assert (2 * M + 1) ** 2 * np.prod(world) >= 2 ** 18
    rng = np.random.default_rng(5)
    q = jnp.asarray(rng.random(world), dt)
    b = jnp.asarray(rng.random(world), dt)
    for f in (0, 5):
        axis, sign = FACE_AXES[f]
        shape = K.to_face(jnp.zeros(world), axis, sign).shape
        _, _, tau, bc, geo, consts = _mixed_face(M, shape, dt, seed=f)
        consts = K.face_consts(direction_set(M), f)
        kw = dict(M=M, periodic=(False, False, False), warmup=2 * M + 1, surfaces=True)
        got = jax.jit(lambda *a: K.sweep_face_world(*a, axis=axis, sign=sign, **kw))(
            q, b, tau, bc, geo, consts)
        path = functools.partial(K._face_path, axis, sign, M, kw["periodic"], 2 * M + 1, True,
                                 (True, True, None), False)
        ref = jax.jit(path)(q, b, tau, bc, geo, consts)
        for r, g in zip(ref, got):
            np.testing.assert_allclose(np.asarray(g), np.asarray(r), rtol=1e-13,
                                       atol=1e-13 * float(jnp.max(jnp.abs(r))))
        assert float(jnp.max(got[0])) > 0 and float(jnp.max(got[1])) > 0


@needs_compiler
@pytest.mark.parametrize("dtype", ["float32", "float64"])
def test_the_plans_surface_records_give_the_kernels_own_bits(dtype, x64, monkeypatch):
    """The blocked sweep's surface records made once with the plan (``_native.
    surface_records``, float32's 16-lane layout) give the same bits as the records the kernel
    makes at every call, on faces whose rows end in a partial vector (nv = 41) and in whole
    ones (nv = 48); the kernel reads them (records without their blocking bits change the
    answer), and a float64 sweep, whose vectors are 8 lanes wide, ignores them."""
    monkeypatch.setenv("DIFFFOG_THREADS", "2")
    from difffog.geometry._directions import FACE_AXES

    assert _native.available(), _native.status()
    M, world, dt = 2, (47, 48, 41), jnp.dtype(dtype)
    D = (2 * M + 1) ** 2
    rng = np.random.default_rng(7)
    q = jnp.asarray(rng.random(world), dt)
    b = jnp.asarray(rng.random(world), dt)
    kw = dict(M=M, periodic=(False, False, False), warmup=2 * M + 1, surfaces=True)
    for f in (0, 5):
        axis, sign = FACE_AXES[f]
        shape = K.to_face(jnp.zeros(world), axis, sign).shape
        assert D * np.prod(shape) >= 2 ** 18 and _native.records_apply(D, shape)
        _, _, tau, bc, geo, _ = _mixed_face(M, shape, dt, seed=f)
        consts = K.face_consts(direction_set(M), f)
        rec = _native.surface_records(np.asarray(geo.normal, np.float32),
                                      np.asarray(geo.blocked), np.asarray(geo.surf), D)
        assert rec["index"].shape == shape[:2] + (shape[2] // 16 + 1,)
        assert 0 < len(rec["touch"]) < rec["index"].size  # some vectors have records
        sweep = jax.jit(lambda r, *a: K.sweep_face_world(*a, axis=axis, sign=sign, **kw,
                                                         records=r))
        own = [np.asarray(x) for x in sweep(None, q, b, tau, bc, geo, consts)]
        planned = sweep(rec, q, b, tau, bc, geo, consts)
        unblocked = sweep(dict(rec, bits=np.zeros_like(rec["bits"])), q, b, tau, bc, geo,
                          consts)
        for x, y in zip(own, planned):
            assert np.array_equal(x, np.asarray(y))
        assert np.array_equal(own[0], np.asarray(unblocked[0])) == (dtype == "float64")


@needs_compiler
@pytest.mark.parametrize("form", ["isotropic", "general"])
def test_world_frame_equals_the_face_frame(form, x64):
    """``sweep_face_world`` (the kernel reading q, b and writing Λ, E at each face node's world
    node) against the face-frame path it replaces (``to_face`` → the face sweep →
    ``from_face``), on every face of a lattice with three different sides, open and periodic:
    equal values, equal tangents (its JVP is the face path's) and under vmap each member."""
    from difffog.geometry._directions import FACE_AXES

    assert _native.available(), _native.status()
    M, world, dt = 2, (7, 6, 5), jnp.dtype("float64")
    rng = np.random.default_rng(3)
    for f, (axis, sign) in enumerate(FACE_AXES):
        shape = K.to_face(jnp.zeros(world), axis, sign).shape
        _, _, tau, bc, geo, consts = _face(M, shape, dt, seed=f)
        if form == "general":
            Qf, consts = _general_form(M, shape, dt, rng, linear=True, order=1, sun=True, face=f)
            q = jnp.asarray(rng.random(world + Qf.shape[3:]), dt)
        else:
            q = jnp.asarray(rng.random(world), dt)
        b = jnp.asarray(rng.random(world), dt)
        for periodic in [(False, False, False), (True, True, False)]:
            kw = dict(M=M, periodic=periodic, warmup=2 * M + 1, surfaces=not periodic[0])
            vol = (True, True, None)
            got = jax.jit(lambda *a: K.sweep_face_world(*a, axis=axis, sign=sign, **kw))(
                q, b, tau, bc, geo, consts)
            path = functools.partial(K._face_path, axis, sign, M, periodic, 2 * M + 1,
                                     kw["surfaces"], vol, False)
            ref = jax.jit(path)(q, b, tau, bc, geo, consts)
            for r, g in zip(ref, got):
                assert g.shape == r.shape
                np.testing.assert_allclose(np.asarray(g), np.asarray(r), rtol=1e-13,
                                           atol=1e-13 * float(jnp.max(jnp.abs(r))))
            assert float(jnp.max(got[0])) > 0  # Λ summed, and E where there are surfaces
            assert (float(jnp.max(got[1])) > 0) == kw["surfaces"]
        # tangents in q, b and τ: the face path's (the batched program's)
        dq, db, dtau = (jnp.asarray(rng.standard_normal(x.shape), dt) for x in (q, b, tau))
        kw = dict(M=M, periodic=(False, False, False), warmup=2 * M + 1, surfaces=True)
        fw = lambda *a: K.sweep_face_world(*a, axis=axis, sign=sign, **kw)  # noqa: E731
        pw, tw = jax.jvp(lambda *a: fw(*a, bc, geo, consts), (q, b, tau), (dq, db, dtau))
        path = functools.partial(K._face_path, axis, sign, M, (False,) * 3, 2 * M + 1, True,
                                 (True, True, None), False)
        pr, tr = jax.jvp(lambda *a: path(*a, bc, geo, consts), (q, b, tau), (dq, db, dtau))
        for x, y in zip(tw + pw, tr + pr):
            np.testing.assert_allclose(np.asarray(x), np.asarray(y), rtol=1e-12,
                                       atol=1e-12 * float(jnp.max(jnp.abs(y))))
        assert float(jnp.max(jnp.abs(tw[0]))) > 0
        if f == 0:  # vmapped (render_batch): each member
            qb = jnp.stack([q, 2.0 * q + 0.1])
            out = jax.jit(jax.vmap(lambda x: fw(x, b, tau, bc, geo, consts)))(qb)
            for i in range(2):
                one = fw(qb[i], b, tau, bc, geo, consts)
                for x, y in zip(out, one):
                    np.testing.assert_allclose(np.asarray(x[i]), np.asarray(y), rtol=1e-13)


@needs_compiler
@pytest.mark.parametrize("dtype", ["float32", "float64"])
def test_native_gram_schmidt_equals_the_xla_products(dtype, x64):
    """GMRES's Arnoldi step orthogonalized by the native kernel (the live rows only) equals
    XLA's products over all rows (``_krylov._cgs2``), also with stale rows beyond the live
    ones and under vmap; w is orthogonal to the live rows."""
    from difffog.forward.sweep import _krylov

    assert _native.available() and _krylov._native_gram_schmidt(jnp.dtype(dtype), True)
    assert not _krylov._native_gram_schmidt(jnp.dtype(dtype), False)
    rng = np.random.default_rng(3)
    n, rows = 3 * 1024 + 77, 9  # not a whole number of the kernel's column blocks
    q, _ = np.linalg.qr(rng.standard_normal((n, rows)))
    V = jnp.asarray(q.T, dtype)  # orthonormal rows, as GMRES keeps them
    a = jnp.asarray(rng.standard_normal(n) + 3.0 * q[:, 0], dtype)
    tol = 1e-12 if dtype == "float64" else 2e-5
    for j in (0, 3, rows - 1):
        h, w, hn = jax.jit(_native.gram_schmidt)(V, a, j + 1)
        h_x, w_x, hn_x = _krylov._cgs2(V, a, j)
        np.testing.assert_allclose(h, h_x, rtol=tol, atol=tol * 3)
        np.testing.assert_allclose(w, w_x, rtol=tol, atol=tol * 3)
        np.testing.assert_allclose(hn, hn_x, rtol=tol)
        assert j + 1 == rows or float(jnp.max(jnp.abs(h[j + 1:]))) == 0.0
        assert float(jnp.max(jnp.abs(V[: j + 1] @ w))) < 10 * tol * float(hn)
    hb, wb, nb = jax.vmap(_native.gram_schmidt, in_axes=(None, 0, 0))(
        V, jnp.stack([a, 2 * a]), jnp.array([2, 5], jnp.int32))
    for k, (aa, live) in enumerate(((a, 2), (2 * a, 5))):
        h1, w1, n1 = _native.gram_schmidt(V, aa, live)
        np.testing.assert_array_equal(hb[k], h1)
        np.testing.assert_array_equal(wb[k], w1)


@needs_compiler
def test_gmres_with_the_native_gram_schmidt_solves_as_with_xla(x64):
    """The same restarted GMRES solve (a nonsymmetric contraction, restarts included) with the
    native Gram–Schmidt and with XLA's products: the same solution and step count, float64."""
    from difffog.forward.sweep import _krylov

    rng = np.random.default_rng(5)
    n = 300
    K = jnp.asarray(0.9 * rng.random((n, n)) / n * 2.0 * np.eye(n)[rng.permutation(n)] +
                    0.95 * rng.random((n, n)) / n, jnp.float64)
    b = jnp.asarray(rng.standard_normal(n), jnp.float64)
    x_true = np.linalg.solve(np.eye(n) - np.asarray(K), np.asarray(b))

    def apply_k(u, with_sources):
        return K @ u + jnp.where(with_sources, b, 0.0)

    out = {nat: _krylov.gmres(apply_k, (n,), jnp.float64, restart=5, max_matvecs=200,
                              tol=1e-10, native=nat) for nat in (True, False)}
    (x_n, _, k_n, _), (x_x, _, k_x, _) = out[True], out[False]
    assert int(k_n) == int(k_x) and int(k_n) > 6  # more than one cycle
    np.testing.assert_allclose(x_n, x_x, rtol=1e-11, atol=1e-12)
    np.testing.assert_allclose(x_n, x_true, rtol=1e-8, atol=1e-9)


def _sky_inputs(shape, dt, seed=3):
    """Random fog (thin to 40 mean free paths a node, some empty), opaque nodes and normals."""
    rng = np.random.default_rng(seed)
    tau = rng.random(shape) * np.where(rng.random(shape) < 0.1, 400.0, 3.0)
    sigma = jnp.asarray(tau * (rng.random(shape) > 0.2), dt)
    opaque = jnp.asarray(rng.random(shape) < 0.1)
    normal = jnp.asarray(rng.standard_normal(shape + (3,)), dt)
    return sigma, opaque, normal


@needs_compiler
@pytest.mark.parametrize("dtype", ["float64", "float32"])
@pytest.mark.parametrize("harm,slope", [(False, False), (True, True)])
def test_native_sky_pass_equals_the_xla_program(dtype, harm, slope, x64, monkeypatch):
    """The sky's first collision (fluence and irradiance from 128 sky directions in five groups
    by the axis their sheets run along; with a Henyey–Greenstein fog its moments, with the
    linear scheme the fluence's slope) from the native kernel equals XLA's program, on a
    lattice whose rows are not whole vectors, with the same bits on 1, 2 and 3 threads (each
    node's sums run on one thread, over the directions in order).  A periodic domain keeps
    XLA's program."""
    from difffog.forward.sweep._uncollided import sky_uncollided
    from difffog.geometry._directions import sky_quadrature

    dirs, wts = sky_quadrature(8, 16)
    dt = jnp.dtype(dtype)
    kw = dict(harm=np.random.default_rng(4).standard_normal((len(dirs), 5)) if harm else None,
              slope=slope)
    args = (*_sky_inputs((11, 9, 21), dt), dirs, wts, 0.05, False)

    def jaxpr(periodic):
        return str(jax.make_jaxpr(lambda s: sky_uncollided(s, *args[1:6], periodic, **kw))(
            args[0]))

    assert "ffi_call" in jaxpr(False) and "ffi_call" not in jaxpr(True)
    xla = sky_uncollided(*args, native=False, **kw)
    assert len(xla) == 2 + harm + slope
    tol = 1e-13 if dtype == "float64" else 2e-6
    runs = []
    for threads in (1, 2, 3):
        monkeypatch.setattr(_native, "_threads", lambda t=threads: t)
        runs.append(sky_uncollided(*args, **kw))
    for k in range(len(xla)):
        top = float(jnp.max(jnp.abs(xla[k])))
        if k < 2:  # (deep in the thick fog the sky hardly reaches: values over two decades)
            assert top > 0.5 and float(jnp.min(xla[k])) < 0.02 * top
        np.testing.assert_allclose(runs[0][k], xla[k], rtol=tol, atol=tol * top)
        for r in runs[1:]:
            np.testing.assert_array_equal(r[k], runs[0][k])


# slow since stop 80 (the default suite's 12-minute budget on 2 cores: ~25 s there); by default
# the sky's first collision is differentiated through this kernel in test_sweep.py's gradients
# against differences (fog-balls has a sky; the step scheme, no moments or slopes)
@pytest.mark.slow
@needs_compiler
def test_native_sky_pass_derivatives_match_differences(x64):
    """A loss of the sky's first collision through the native kernel (whose derivative rule is
    XLA's program), its moments and slope included: its tangent and its gradient in the
    extinction match central differences in float64, also under vmap."""
    from difffog.forward.sweep._uncollided import sky_uncollided
    from difffog.geometry._directions import sky_quadrature

    dirs, wts = sky_quadrature(4, 8)
    sigma, opaque, normal = _sky_inputs((7, 6, 8), jnp.float64, seed=5)
    sigma = sigma / 20.0  # light through the fog, not only off its top
    w = jnp.asarray(np.random.default_rng(1).random(sigma.shape))

    harm = np.random.default_rng(6).standard_normal((len(dirs), 3))

    def loss(s):
        flu, irr, mom, slope = sky_uncollided(s, opaque, normal, dirs, wts, 0.1, False,
                                              harm=harm, slope=True)
        return (jnp.sum(w * flu) + jnp.sum(w * w * irr) + jnp.sum(w[..., None] * mom)
                + jnp.sum(w[..., None] * slope))

    dsig = jnp.asarray(np.random.default_rng(2).random(sigma.shape))
    e = 1e-6
    fd = (loss(sigma + e * dsig) - loss(sigma - e * dsig)) / (2 * e)
    _, tangent = jax.jvp(loss, (sigma,), (dsig,))
    grad = jax.grad(loss)(sigma)
    assert abs(float(fd)) > 1e-3
    assert float(tangent) == pytest.approx(float(fd), rel=1e-7)
    assert float(jnp.sum(grad * dsig)) == pytest.approx(float(fd), rel=1e-7)
    both = jax.vmap(loss)(jnp.stack([sigma, 2.0 * sigma]))
    np.testing.assert_allclose(both, [loss(sigma), loss(2.0 * sigma)], rtol=1e-14)
