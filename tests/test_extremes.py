"""Stability at the extremes: a matrix of fog and surface parameters, both dtypes, every solver.

ζ, γ ∈ {0, 1e-6, 1, 1e3, 1e6} per unit length (fog albedo 0 … 1 comes with them) and
surface albedo ∈ {0, 1e-6, 0.5, 1 − 1e-6, 1}, float32 and float64: images finite and
non-negative, the sun's transmittance in [0, 1], the furnace's energy balance (radiance ≤
E/(1 − ρ), = where nothing absorbs and the solve converged), gradients finite, and continuity as
ζ → 0 (the no-fog image) and γ → 0 (the conservative image).  A closed box that conserves all
energy and emits has no steady state: a SolverError, not a hang or an Inf.

Every matrix point also checks the light solve's result code (``light.result``): it is a
:class:`difffog.RESULTS` member consistent with the solve's own record (successful: the
estimated error reached the tolerance and the fields are finite; max_iterations_reached: the
cap was hit; stagnated: stopped early short of the tolerance; nonfinite: non-finite fields),
and a solve reported successful gives the right answer where one is known (the furnace without
absorption).  The matrix runs the images unchecked (``throw=False`` semantics: the code is
returned, not raised), so unconverged corners report their code instead of failing.

The parameters are traced values, so one compile per (solver, scene, dtype) serves the whole
matrix.  To add a solver, add one entry to SOLVERS (a forward model: ``.params()``,
``.light(params)`` with ``.result``, ``.images_from(light, params)``).
"""

import dataclasses
import itertools
import warnings

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import difffog as df
from difffog import SolverError, load_scene, set_param

# (1e-3 left the default matrix for the suite's 12-minute budget; it had passed in every run)
VALUES = [0.0, 1e-6, 1.0, 1e3, 1e6]
ALBEDOS = [0.0, 1e-6, 0.5, 1 - 1e-6, 1.0]
DTYPES = ["float32", "float64"]
TOL = 1e-4
MAX_ITERATIONS = 40


def _sweep(scene, N, **kw):
    return df.forward_model(scene, "sweep", accuracy=None, resolution=N, M=1, tol=TOL,
                            max_iterations=MAX_ITERATIONS, supersample=1, **kw)


SOLVERS = {"sweep": _sweep}


def _small(scene, res=(6, 5)):
    return scene.replace(cameras=tuple(dataclasses.replace(c, resolution=res)
                                       for c in scene.cameras))


def _open_scene():  # fog, three balls in an open box, sun and sky; walls > one voxel at N = 10
    return _small(load_scene("fog-balls", ["shape.walls.thickness=0.15"]))


def _furnace(albedo=0.5):  # closed box, emission 1: radiance 1/(1 - albedo) without absorption
    return _small(load_scene("furnace", [f"shape.walls.albedo={albedo}",
                                         "shape.walls.thickness=0.15"]))


def _with(p, zeta=None, gamma=None, albedo=None):
    if zeta is not None:
        p = eqx.tree_at(lambda q: q.scattering, p, jnp.asarray(zeta, p.scattering.dtype))
    if gamma is not None:
        p = eqx.tree_at(lambda q: q.absorption, p, jnp.asarray(gamma, p.absorption.dtype))
    if albedo is not None:
        p = eqx.tree_at(lambda q: q.albedo, p, jnp.full_like(p.albedo, albedo))
    return p


def _loss(model, p):
    light = model.light(p)
    imgs = model.images_from(light, p)  # unchecked: the result code comes back in ``light``
    return sum(jnp.sum(v) for v in imgs.values()), (imgs, light)


@eqx.filter_jit
def _value_and_grad(model, p):
    return jax.value_and_grad(lambda q: _loss(model, q), has_aux=True)(p)


class _Case:
    """One model and one compiled function per dtype: images, light and the gradient of the
    images' sum w.r.t. every parameter (so every matrix point checks the gradient too)."""

    def __init__(self, solver, scene, N):
        self.model = SOLVERS[solver](scene, N, throw=False)

    def fwd(self, p):
        """(images, light, gradient, adjoint warnings): an unconverged tangent/adjoint solve of
        the implicit gradient warns (the model's solver is built with throw=False)."""
        with warnings.catch_warnings(record=True) as w:
            warnings.simplefilter("always", df.AdjointWarning)
            (_, (imgs, light)), g = jax.block_until_ready(_value_and_grad(self.model, p))
        return imgs, light, g, [x for x in w if issubclass(x.category, df.AdjointWarning)]


_CACHE = {}


def _case(solver, which, dtype):
    key = (solver, which, dtype)
    if key not in _CACHE:
        scene = _open_scene() if which == "open" else _furnace()
        _CACHE[key] = _Case(solver, scene, 10 if which == "open" else 8)
    return _CACHE[key]


_MODELS = {}


def _model(key, build):
    if key not in _MODELS:
        _MODELS[key] = build()
    return _MODELS[key]


# float64 runs with -m slow (the default suite keeps float32, the harder case for overflow and
# underflow; both passed when last run in full)
@pytest.fixture(params=[pytest.param(d, marks=pytest.mark.slow) if d == "float64" else d
                        for d in DTYPES])
def dtype(request):
    old = jax.config.jax_enable_x64
    jax.config.update("jax_enable_x64", request.param == "float64")
    yield jnp.dtype(request.param)
    jax.config.update("jax_enable_x64", old)


def _images(out):
    return np.concatenate([np.asarray(v, np.float64).ravel() for v in out.values()])


def _finite_grad(g):
    return all(np.all(np.isfinite(np.asarray(x))) for x in jax.tree.leaves(g))


def _code(light):
    """The light's RESULTS member, or a string saying why its code is inconsistent."""
    code = int(light.result)
    if code not in set(df.RESULTS):
        return f"unknown result code {code}"
    code = df.RESULTS(code)
    k, err = int(light.iterations), float(light.error_estimate)
    finite = all(np.all(np.isfinite(np.asarray(x))) for x in
                 (light.fluence, light.radiosity, light.sun_fluence, light.sky_fluence))
    reached = err <= TOL
    ok = {df.RESULTS.successful: finite and reached and k <= MAX_ITERATIONS,
          df.RESULTS.max_iterations_reached: finite and not reached and k == MAX_ITERATIONS,
          df.RESULTS.stagnated: finite and not reached and k < MAX_ITERATIONS,
          df.RESULTS.nonfinite: not finite}[code]
    return code if ok else (f"{code.name} inconsistent (iterations {k}, error {err:.3g}, "
                            f"finite {finite})")


def _label(code, warned):
    """The code's name (+ a note where the gradient's adjoint solve warned), for the record."""
    name = code.name if isinstance(code, df.RESULTS) else code
    return name + (" (adjoint warned)" if warned else "")


#: furnace points (ζ, γ) whose light solve reports success with a wrong light field (see
#: test_furnace_energy_balance_matrix): the thick-fog issue.  (1e3, 0) left the set with the
#: conservative fluence (J = 0 before, 2 now); at (1e6, 0) J is 1.92-2.00 instead of 2.
THICK_FOG_KNOWN_WRONG = {(1e6, 0.0)}

#: {(scene, dtype): {point: code name}} of the last matrix runs, for reports (``-s`` prints it)
CODES: dict = {}


def _record(which, dtype, codes):
    CODES[(which, dtype.name)] = codes
    failed = {k: v for k, v in codes.items() if v != "successful"}
    # every point returned its code (none raised); failure codes are allowed, inconsistent
    # codes are not (checked by the caller)
    print(f"\n{which} {dtype.name}: {len(codes) - len(failed)}/{len(codes)} successful; "
          f"others: {failed}")


@pytest.mark.parametrize("solver", list(SOLVERS))
def test_open_scene_matrix(solver, dtype):
    """fog-balls over ζ × γ (surface albedo 0.5) and surface albedo × a few fogs; values,
    gradients and the result code at every point."""
    c = _case(solver, "open", dtype.name)
    p0 = c.model.params(dtype)
    F = float(p0.sun_irradiance)
    grid = [dict(zeta=z, gamma=g, albedo=0.5) for z, g in itertools.product(VALUES, VALUES)]
    grid += [dict(zeta=z, gamma=g, albedo=a) for a in ALBEDOS
             for z, g in [(0.0, 0.0), (1.0, 1e-6), (1e3, 1.0)]]
    bad, codes = [], {}
    for kw in grid:
        p = _with(p0, **kw)
        imgs, light, grad, warned = c.fwd(p)
        x = _images(imgs)
        t_sun = np.asarray(light.sun_fluence, np.float64) / F
        ok = (np.all(np.isfinite(x)) and x.min() >= 0
              and t_sun.min() >= 0 and t_sun.max() <= 1 + 1e-6
              and np.all(np.isfinite(np.asarray(light.fluence)))
              and np.asarray(light.radiosity).min() >= 0)
        if not ok:
            bad.append(("values", kw, float(x.min()), float(x.max())))
        if not _finite_grad(grad):
            bad.append(("gradient", kw))
        code = _code(light)
        codes[tuple(kw.values())] = _label(code, warned)
        if not isinstance(code, df.RESULTS):
            bad.append(("result", kw, code))
    _record("open", dtype, codes)
    assert not bad, bad
    # the extremes push the gradient's adjoint solve past its budget somewhere, and it says
    # so (an AdjointWarning), never silently: the sweep's adjoint goes through CheckedSolver
    assert any(v.endswith("(adjoint warned)") for v in codes.values()), codes


@pytest.mark.parametrize("solver", list(SOLVERS))
def test_furnace_energy_balance_matrix(solver, dtype):
    """Closed box, emission 1, walls albedo 0.5: radiance ≤ 2 everywhere, = 2 where the fog does
    not absorb (the solve converged there; and wherever it reports success); ≥ 0 and finite
    always."""
    c = _case(solver, "furnace", dtype.name)
    p0 = c.model.params(dtype)
    geom = c.model.geometry
    fog = np.asarray(geom.free) & (np.asarray(geom.density) > 0)  # the fog inside the box
    bad, codes, wrong = [], {}, {}
    for z, g in itertools.product(VALUES, VALUES):
        imgs, light, grad, warned = c.fwd(_with(p0, zeta=z, gamma=g))
        x = _images(imgs)
        if not _finite_grad(grad):
            bad.append(("gradient", z, g))
        code = _code(light)
        codes[(z, g)] = _label(code, warned)
        if not isinstance(code, df.RESULTS):
            bad.append(("result", z, g, code))
        converged = code == df.RESULTS.successful
        rtol = 1e-2 if dtype == jnp.float32 else 1e-3  # tolerance 1e-4 × the furnace's 1/(1-ρ)
        if not (np.all(np.isfinite(x)) and x.min() >= 0 and x.max() <= 2 * (1 + rtol)):
            bad.append(("bounds", z, g, float(x.min()), float(x.max())))
        if g == 0 and z <= 1 and not (converged and np.allclose(x, 2.0, rtol=rtol)):
            bad.append(("balance", z, g, float(x.min()), float(x.max()), codes[(z, g)]))
        # a light solve that reports success has the furnace's answer: the mean radiance J =
        # Λ/4π in the fog is 2 without absorption, at most 2 with it
        if converged and z > 0:
            J = np.asarray(light.fluence, np.float64)[fog] / (4 * np.pi)
            if J.max() > 2 * (1 + rtol) or (g == 0 and not np.allclose(J, 2.0, rtol=rtol)):
                wrong[(z, g)] = (float(J.min()), float(J.max()))
    _record("furnace", dtype, codes)
    print(f"furnace {dtype.name}: light wrong although successful at {wrong}")
    # Known (the thick-fog issue, not fixed yet): at ζ = 1e6 a node's half-step optical depth
    # (ζh/2 ≈ 6e4 at N = 8) couples neighbouring nodes only through the 1/(2τ) ≈ 1e-5 part of
    # the segment-averaged fluence, near float32's resolution, and the solve stops 4% short
    # of the furnace's J = 2 while reporting success (before the conservative fluence, J was
    # 0 there and at ζ = 1e3).  Any other wrong answer reported as successful fails here.
    new = {k: v for k, v in wrong.items() if k not in THICK_FOG_KNOWN_WRONG}
    assert not new, ("light wrong although successful", new)
    assert not bad, bad


@pytest.mark.parametrize("solver", list(SOLVERS))
def test_continuity_at_zero(solver, dtype):
    """ζ → 0 gives the no-fog image, γ → 0 the conservative one (relative to the image's max)."""
    c = _case(solver, "open", dtype.name)
    p0 = c.model.params(dtype)

    def img(**kw):
        imgs, light, _, _ = c.fwd(_with(p0, **kw))
        assert int(light.result) == df.RESULTS.successful, kw
        return _images(imgs)

    nofog = _model((solver, "nofog"), lambda: SOLVERS[solver](_open_scene().replace(fog=None), 10))
    ref_nofog = _images(nofog(nofog.params(dtype)))  # raises if its light solve failed
    scale = ref_nofog.max()
    tol = 2e-3 if dtype == jnp.float32 else 1e-4
    assert np.max(np.abs(img(zeta=1e-6, gamma=1e-6) - ref_nofog)) < tol * scale
    assert np.max(np.abs(img(zeta=0.0, gamma=0.0) - ref_nofog)) < tol * scale
    for g in (0.0, 0.5):
        assert np.max(np.abs(img(zeta=1e-6, gamma=g) - img(zeta=0.0, gamma=g))) < tol * scale
    cons = img(zeta=2.0, gamma=0.0)
    assert np.max(np.abs(img(zeta=2.0, gamma=1e-6) - cons)) < tol * scale
    assert np.max(np.abs(img(zeta=2.0, gamma=1e-3) - cons)) < 10 * tol * scale


def test_closed_conservative_emitting_box_is_an_error():
    """Furnace with albedo 1: no steady state → SolverError naming the fix, up front."""
    scene = _furnace(albedo=1.0)
    m = SOLVERS["sweep"](scene, 8)
    with pytest.raises(SolverError, match="no steady state.*albedo below 1"):
        m.images(m.params())  # host-side check of concrete parameters, before any work
    with pytest.raises(SolverError, match="no steady state"):
        df.render(m)
    # inside a trace it is the light solve's result code (no host callback in the program,
    # which XLA's persistent cache would not store), and a throwing model raises with it; the
    # matrix's compiled function for the furnace (its albedo a traced parameter) serves
    c = _case("sweep", "furnace", "float32")
    p1 = _with(c.model.params(jnp.float32), albedo=1.0)
    _, light, _, _ = c.fwd(p1)
    assert int(light.result) == df.RESULTS.no_steady_state
    assert "albedo below 1" in df.RESULTS.no_steady_state.message
    throwing = SOLVERS["sweep"](scene, 8)
    with pytest.raises(Exception, match="no steady state"):
        eqx.filter_jit(lambda m, p: m(p))(throwing, p1)
    text = eqx.filter_jit(lambda m, p: m.light(p).result).lower(throwing, p1).as_text()
    assert "callback" not in text.lower()
    # absorbing fog inside: a steady state exists, and it is finite
    imgs, light, _, _ = c.fwd(set_param(p1, scene, "fog.absorption", 0.5))
    assert int(light.result) == df.RESULTS.successful
    x = _images(imgs)
    assert np.all(np.isfinite(x)) and x.min() > 0


def test_terms_guard_names_the_dropped_term():
    """A scene without fog gets terms without fog; giving it fog later is a SolverError naming
    the fix."""
    scene = _open_scene().replace(fog=None)
    m = _model(("sweep", "nofog"), lambda: SOLVERS["sweep"](scene, 10))
    p = set_param(m.params(), scene, "fog.scattering", 1.0)
    with pytest.raises(SolverError, match="terms='all'"):
        m.images(p)
    with pytest.raises(SolverError, match="terms='all'"):
        df.render(m, p)
    light = eqx.filter_jit(lambda m, p: m.light(p))(m, p)  # traced: the result code
    assert int(light.result) == df.RESULTS.terms_dropped
    full = SOLVERS["sweep"](scene, 10, terms="all")
    x = _images(full(set_param(full.params(), scene, "fog.scattering", 1.0)))
    assert np.all(np.isfinite(x)) and x.min() >= 0


@pytest.mark.parametrize("solver", list(SOLVERS))
def test_open_scene_monotone_in_absorption_and_albedo(solver):
    """Physics, not only finiteness: more absorption (γ) never brightens any pixel, and a
    higher surface albedo never darkens one — the transport solution is monotone in both, and
    so is the sweep's scheme (both coefficients of the step update, e^(−τ) and ζ·h·(1 −
    e^(−τ))/τ, fall as γ grows).  Checked pixel by pixel within the solve's tolerance."""
    c = _case(solver, "open", "float32")
    p0 = c.model.params(jnp.float32)

    def image(**kw):
        imgs, light, _, _ = c.fwd(_with(p0, **kw))
        assert int(light.result) == df.RESULTS.successful, kw
        return _images(imgs)

    slack = 4 * TOL  # the relative tolerance of each of the two solves, with margin
    gammas = [0.0, 1e-3, 0.3, 3.0, 1e3]
    imgs = [image(zeta=1.0, gamma=g, albedo=0.5) for g in gammas]
    for g0, g1, a, b in zip(gammas, gammas[1:], imgs, imgs[1:]):
        assert np.all(b <= a + slack * a.max()), (g0, g1, float(np.max(b - a)))
    # and the trend is real, not flat: a third of the pixels (measured 35%) lose more than
    # half their light; not all: the 0.15-thick walls' tops, half of the top view, stand at
    # the fog's top face, where the sun reaches them through no fog (exactly so since the
    # sun's depth at a hit ends at the fog's box)
    assert np.mean(imgs[-1] < 0.5 * imgs[0]) > 0.25
    albedos = [0.0, 0.3, 0.7, 1.0]
    imgs = [image(zeta=1.0, gamma=0.1, albedo=a) for a in albedos]
    for a0, a1, a, b in zip(albedos, albedos[1:], imgs, imgs[1:]):
        assert np.all(b >= a - slack * b.max()), (a0, a1, float(np.min(b - a)))
    assert imgs[-1].mean() > 1.5 * imgs[0].mean()
