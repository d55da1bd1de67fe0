"""The sweep solver against an independent renderer and its slab convergence (docs/design.md
ladder 3-4).

References: Mitsuba 3 images of the benchmark scenes and the adding-doubling slab table,
shipped with the package (:mod:`difffog.study.references`).  The bounds are what
``benchmarks/validate_references.py`` and ``benchmarks/slab_convergence.py`` measured, with a
margin; ``benchmarks/results/references.md`` and ``slab_convergence.md`` hold the full tables.
"""

import functools
import math

import equinox as eqx
import jax.numpy as jnp
import numpy as np
import pytest

import difffog as df
from difffog import Params, SweepSolver, load_scene
from difffog.study import references
from difffog.study._slab import slab_problem, slab_reflectance


def _reference(scene: str, camera: str):
    ref = references.reference(scene, camera)
    assert ref is not None, (f"no shipped reference for {scene}/{camera} in "
                             f"{references.references_dir()}")
    img, noise = ref
    assert noise is not None, f"{scene}/{camera}: the shipped reference has no noise estimate"
    return np.asarray(img, np.float64), float(noise)


def _errors(img, scene: str, camera: str):
    """(bias, rel. RMSE, rel. RMSE with the reference noise removed in quadrature)."""
    ref, noise = _reference(scene, camera)
    img = np.asarray(img, np.float64)
    assert img.shape == ref.shape
    mean = ref.mean()
    rmse = math.sqrt(np.mean((img - ref) ** 2))
    return img.mean() / mean - 1.0, rmse / mean, math.sqrt(max(rmse**2 - noise**2, 0.0)) / mean


@functools.lru_cache(maxsize=None)
def _render(scene: str, N: int, M: int, tol: float):
    model = df.SweepModel(load_scene(scene), resolution=N, solver=SweepSolver(M=M, tol=tol))
    out = df.render(model)  # raises if the light solve did not converge
    assert out.result == df.RESULTS.successful
    assert int(out.light.result) == df.RESULTS.successful
    return {k: np.asarray(v, np.float64) for k, v in out.images.items()}


def test_references_are_shipped():
    """Every benchmark scene's reference image, with its noise estimate, and the slab table."""
    assert (references.references_dir() / "slab_adding_doubling.csv").is_file()
    for scene, camera in [("furnace", "inside"), *AIMED, ("cloud-plane", "top"),
                          ("cloud-plane", "oblique")]:
        img, noise = _reference(scene, camera)
        assert img.ndim == 2 and np.all(np.isfinite(img)) and noise > 0


# ---------------------------------------------------------------- 3. furnace (fast)
# Measured at N = 16, M = 2, tol = 1e-4 (float32, 196 iterations): max |image/10 − 1| = 1.2e-4;
# against Mitsuba: bias −0.05% (the reference's mean is 10.0035), rel. RMSE 2.18% of which the
# reference's own noise is 2.16%, 0.30% with that noise removed.
FURNACE_MAX_DEV = 1e-3
FURNACE_BIAS = 0.005
FURNACE_REL_RMSE = 0.025
FURNACE_REL_RMSE_CORR = 0.01


@pytest.mark.slow  # the suite's 12-minute budget; test_cli's render checks the furnace's 10
def test_furnace_image_is_ten_and_matches_mitsuba():
    img = _render("furnace", 16, 2, 1e-4)["inside"]
    assert np.all(np.isfinite(img))
    assert np.max(np.abs(img / 10.0 - 1.0)) < FURNACE_MAX_DEV
    bias, rel, rel_corr = _errors(img, "furnace", "inside")
    assert abs(bias) < FURNACE_BIAS, bias
    assert rel < FURNACE_REL_RMSE, rel
    assert rel_corr < FURNACE_REL_RMSE_CORR, rel_corr


# ---------------------------------------------------------------- 3. benchmark scenes (slow)
# Every camera of fog-balls, ring-box and translucent-cube within 5% relative RMSE of the
# Monte Carlo reference (its noise removed) at the default preset (N = 64, M = 3), the bias of
# the mean within 2%: the exact-geometry issue's aim (measured 1.4-3.2% and ≤ 0.5%,
# benchmarks/results/references.md).  Not a tuned bound: the same for every camera.
AIMED = [(s, c) for s in ("fog-balls", "ring-box", "translucent-cube") for c in ("top", "oblique")]


@pytest.mark.slow
@pytest.mark.parametrize("scene,camera", AIMED)
def test_scene_against_mitsuba(scene, camera):
    img = _render(scene, 64, 3, 1e-3)[camera]
    bias, _, rel_corr = _errors(img, scene, camera)
    assert rel_corr < 0.05, rel_corr
    assert abs(bias) < 0.02, bias


# ---------------------------------------------------------------- 4. slab convergence (slow)
@eqx.filter_jit
def _solve_jit(solver, geom, params):
    return solver.solve(geom, params)


def _slab_errors(albedo, tau, n_fog, M):
    R_ref, T_ref = next(
        (r["R_total"], r["T_total"]) for r in references.slab_table()
        if r["albedo"] == albedo and r["tau"] == tau and r["g"] == 0
        and r["illumination"] == "diffuse"
    )
    scene, lat, margin = slab_problem(tau, albedo, n_fog, M)
    solver = SweepSolver(M=M, max_iterations=5000, tol=1e-8)
    params = Params.from_scene(scene, jnp.float64)
    light = _solve_jit(solver, solver.prepare(scene, lat), params)
    assert int(light.result) == df.RESULTS.successful
    sigma = tau * np.asarray(lat.density, np.float64)[0, 0]  # g = 0: σ_t = τ per unit length
    R, T = slab_reflectance(sigma, np.asarray(light.source)[0, 0], None, margin, lat.h, sky=1.0)
    return R / R_ref - 1.0, T / T_ref - 1.0


@pytest.mark.slow
def test_slab_error_falls_with_resolution(x64):
    """a = 0.9, τ = 1, M = 3: measured R −0.69% → −0.40%, T +0.52% → +0.38% (N = 16 → 64)."""
    eR16, eT16 = _slab_errors(0.9, 1.0, 16, 3)
    eR64, eT64 = _slab_errors(0.9, 1.0, 64, 3)
    assert abs(eR64) < abs(eR16) and abs(eT64) < abs(eT16), (eR16, eT16, eR64, eT64)
    assert abs(eR64) < 0.006 and abs(eT64) < 0.006
