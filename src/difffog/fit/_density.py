"""Density tomography: the fog's density grid from images of several views (issue 17).

The unknowns are the logarithms of the grid's cells inside a support (so the density stays
positive and the cells outside stay exactly 0, as the sweep model's traced density requires,
``difffog.with_density``); the loss is the images' mean squared misfit relative to the
targets' brightness plus a weighted prior (the grid's total variation, or its squared
gradient: ``prior="smooth"``); L-BFGS-B (SciPy: a Python loop
around one compiled value-and-gradient, which optimistix' jitted step would compile a second
time) minimises it
from a coarse grid to the final one (each level starts from the last one's estimate,
upsampled).  The support is the start grid's nonzero cells less the cells that some target
pixel sees through to clear sky or ground (space carving: a pixel whose target equals the
model's image of the scene without fog, within ``carve_tol``).

Every evaluation is one light solve, one adjoint light solve (the implicit function theorem:
one for all the cells) and the cameras' march and its reverse.
"""

from __future__ import annotations

import dataclasses
import json
import math
import time
import warnings
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from .._errors import AdjointWarning, DifffogError, SceneError
from .._progress import as_meter
from ..forward.sweep._implicit import solves_by_value
from ..scene._description import Scene
from ..scene._params import with_density
from ._targets import _block_mean, reduced_scene

#: the priors ``fit_density`` offers, each with its default weight against the images'
#: relative mean squared misfit: "tv", the total variation Σ|∇g| / (cells · mean); "smooth",
#: the squared gradient Σ|∇g|² / (cells · mean²) (forward differences; cells and mean: the
#: level's support and its start's mean density there).  TV keeps edges and flattens peaks;
#: "smooth" penalises cell-to-cell noise far more than broad structure.
#: "shape" is "smooth" of the grid's shape, g / Σg: Σ|∇g|² · (m₀ / Σg)² with m₀ the start's
#: mass (the same value at the start), so that it says nothing about the total mass, which
#: the images determine; "smooth" ∝ (Σg)² at a fixed shape pulls every fit's mass down.
PRIORS = {"tv": 1e-3, "smooth": 3e-5, "shape": 3e-5}
#: the prior a density fit uses unless told: "shape" with the sub-stepped scheme
#: (``DENSITY_SCHEME``) came closest to the truth from Mitsuba images on cloud-tomo, -b and -c
#: (0.140 / 0.197 / 0.204 against smooth's 0.142 / 0.215 / 0.238 with the step scheme, the
#: mass within 6% where smooth took 7-11% off b and c), and on cloud-tomo-d, made afterwards
#: to check it (docs/tomography.md, stop 51)
DEFAULT_PRIOR = "shape"
#: the balancing principle's share of the prior in the loss at the final level: after the
#: final level's L-BFGS run, a fit whose prior term over data term, at its best point, lies
#: outside [BALANCE / BALANCE_TOL, BALANCE · BALANCE_TOL] takes a new weight that would bring
#: it there and runs the final level again from its estimate (``balance``).  0.8 is the share
#: cloud-tomo's fit holds at its good fixed weight (0.82 at W = 3e-5; 0.46 at 1e-5 overfits,
#: and cloud-tomo-b's fit has its mass right at 0.62–0.81 and is too thin at 1.10):
#: docs/tomography.md.  Per prior: "tv" has none measured, so it balances only when told;
#: "shape" takes smooth's (the same roughness at the start).  With "shape" the fits end at
#: shares 0.71–1.4 (stop 51, today's defaults, six Mitsuba-target fits): the share responds
#: more steeply to W than BALANCE_POWER says, so one rebalance overshoots; not re-measured
#: cleanly yet (docs/tomography.md, stop 51).
BALANCE = {"smooth": 0.8, "shape": 0.8}
BALANCE_TOL = 1.2
#: how the share grows with the weight, share ∝ W^BALANCE_POWER (measured at the final level:
#: 0.53 on cloud-tomo, 0.52 on cloud-tomo-b between W = 1e-5 and 3e-5); the new weight is
#: W · (BALANCE / share)^(1 / BALANCE_POWER), by at most a factor of 10 either way
BALANCE_POWER = 0.5
#: a target pixel within this relative difference of the fog-free image sees clear sky or
#: ground: its ray carves the cells it crosses out of the support
DEFAULT_CARVE_TOL = 0.02
#: the light solve's scheme a density fit uses unless ``settings`` names one: the sub-stepped
#: scheme, exact-conservation segments whose images of the true clouds are the closest to
#: Mitsuba 3 (cloud-tomo 1.17% RMS at N = 32, step 1.84%; its collided light in the skin
#: within 2% of N = 96, the step scheme's 8% too bright).  The step scheme fits in less than
#: half the time but needs the "smooth" prior's pull on the mass to come out right (with
#: "shape" it puts 23% too much mass into cloud-tomo); scheme="auto" would take the linear
#: scheme for clouds, the furthest from Mitsuba (docs/tomography.md)
DENSITY_SCHEME = "substep"
#: the final level's image pixels per lattice node along the longest axis (the coarser levels
#: take one): 64² targets on a 32-node lattice are fitted at their own resolution, 2² rays per
#: pixel, as many rays as one pixel per node at 4² (rays_per_pixel_side), so the same camera
#: work and no 2×2 averaging of the cloud's edges away (targets larger than 4 pixels per node
#: keep 4² rays per reduced pixel: there the final level casts 4 times the rays it did).  Against 1 (stop 51, Mitsuba targets,
#: defaults otherwise): cloud-tomo 0.140 / −1.6% both, -b 0.193 / +3.7% (0.197 / +4.4%), -c
#: 0.198 / +5.9% (0.204 / +5.7%), -d 0.197 / −1.1% (0.201 / −1.1%), each no slower
#: (docs/tomography.md)
FINAL_PIXELS_PER_NODE = 2
#: the smallest density a support cell starts from, relative to the start's largest (its log
#: must be finite)
_FLOOR = 1e-3
#: the largest optical depth of one grid cell, (ζ + γ)·density·(cell width), that a fit's
#: L-BFGS-B may try: the log-densities are bounded there (``log_density_cap``).  Unbounded, a
#: line-search trial of cloud-tomo-c's cold fit (final level, evaluation 30) reached log
#: densities of 105: an infinite density, a NaN light field, and an adjoint solve that failed on
#: it, which ended the level.  A cell 100 mean free paths thick is opaque to every camera.
MAX_CELL_DEPTH = 100.0


@dataclasses.dataclass
class DensityFit:
    """What :func:`fit_density` returns.

    density: (nx, ny, nz) float32, the estimate, indexed [ix, iy, iz] as scene files are.
    support: (nx, ny, nz) bool, the cells the fit could fill (the rest are 0).
    history: one entry per evaluation: level, step, loss, data and prior terms, seconds.
    levels: one entry per grid level: its grid, lattice resolution, image downsampling,
        steps, final loss, carved cells, seconds (compile included) and ``compile_s``, the
        time of its first call (the compile and one evaluation).
    result: "successful" (the loss stopped falling), "max_steps" (the last level's step
        budget ran out), "light_failed" (the light solve at the estimate did not converge) or
        "adjoint_failed" (an evaluation's gradient, its adjoint light solve, did not converge:
        the last level stopped there at its best point so far, with an ``AdjointWarning``).
    time_s: the whole fit's wall time.
    settings: the fit's options (JSON-able).
    passes: the final level's estimate after each of its passes (one unless the balancing
        principle changed the weight: ``levels[-1]["balance"]``), float32 like ``density``;
        the last is ``density``.
    """

    density: np.ndarray
    support: np.ndarray
    history: list[dict]
    levels: list[dict]
    result: str
    time_s: float
    settings: dict
    passes: list = dataclasses.field(default_factory=list, repr=False)
    # the last level's loss and its estimate's coordinates (not serialized): what a caller
    # differentiates further (``_value_and_grad(x, loss)``, compiled already)
    final_level: Any = dataclasses.field(default=None, repr=False, compare=False)

    def relative_error(self, truth) -> float:
        """‖estimate − truth‖ / ‖truth‖ over all cells (the truth resampled to this grid)."""
        t = resample(np.asarray(truth, np.float64), self.density.shape)
        return float(np.linalg.norm(self.density - t) / np.linalg.norm(t))

    def mass_bias(self, truth) -> float:
        """Σ estimate / Σ truth − 1 (the truth resampled to this grid)."""
        t = resample(np.asarray(truth, np.float64), self.density.shape)
        return float(self.density.sum(dtype=np.float64) / t.sum() - 1.0)

    def _level(self, what: str):
        """(the last level's loss, its estimate's coordinates), compiled already."""
        if self.final_level is None:
            raise DifffogError(f"DensityFit.{what}: this result has no compiled level (it was "
                               f"loaded, not fitted)")
        return self.final_level

    def images(self) -> tuple[dict, dict]:
        """({camera: the estimate's image}, {camera: its target}) at the last level's lattice
        and image size (one more evaluation of the fit's compiled program)."""
        loss, x = self._level("images")
        (_, (_, _, _, imgs)), _ = _value_and_grad(x, loss)
        return ({c: np.asarray(v) for c, v in imgs.items()},
                {c: np.asarray(v) for c, v in loss.targets.items()})

    def gradient(self, density=None) -> tuple[float, np.ndarray]:
        """(loss, d loss / d density): the last level's loss (the images' relative misfit +
        the prior) and its gradient for every cell (0 outside the support and in carved
        cells, which the fit holds empty) at ``density`` (the level's grid shape; default: the
        estimate), by the fit's compiled program: one light solve and one adjoint solve for
        all the cells."""
        loss, x = self._level("gradient")
        if density is not None:
            g = np.asarray(density, np.float64)
            if g.shape != loss.shape:
                raise DifffogError(f"DensityFit.gradient: a grid of shape {loss.shape} is "
                                   f"needed (the last level's), got {g.shape}")
            cells = g.reshape(-1)[np.asarray(loss.support)]
            x = jnp.asarray(np.log(np.maximum(cells, 1e-30)), x.dtype)
        (val, _), gx = _value_and_grad(x, loss)
        if not np.all(np.isfinite(np.asarray(gx))):
            raise DifffogError("DensityFit.gradient: the gradient's adjoint light solve did not "
                               "converge; raise the solver's max_iterations or adjoint_rtol")
        dens = np.exp(np.asarray(x, np.float64)) * np.asarray(loss.keep, np.float64)
        out = np.zeros(math.prod(loss.shape))
        out[np.asarray(loss.support)] = np.where(dens > 0, np.asarray(gx, np.float64)
                                                 / np.where(dens > 0, dens, 1.0), 0.0)
        return float(val), out.reshape(loss.shape)

    def to_json(self) -> dict:
        return {"result": self.result, "time_s": self.time_s, "grid": list(self.density.shape),
                "support_cells": int(self.support.sum()), "levels": self.levels,
                "history": self.history, "settings": self.settings}

    def save(self, out) -> None:
        """``out/density.npz`` (key ``density``, float32 [ix, iy, iz]) and ``out/fit.json``,
        written together or not at all."""
        from .._output import atomic_folder

        with atomic_folder(out) as tmp:
            np.savez_compressed(tmp / "density.npz", density=self.density.astype(np.float32))
            (tmp / "fit.json").write_text(json.dumps(self.to_json(), indent=1))


class _Budget(Exception):
    """A level's evaluations are spent."""


class _AdjointFailed(Exception):
    """An evaluation's tangent/adjoint light solve (its gradient) did not converge."""


def resample(g: np.ndarray, shape) -> np.ndarray:
    """A cell-centred grid resampled to ``shape`` (trilinear between cell centres, clamped;
    the same map the lattice uses), so that a coarse level's estimate seeds the next."""
    from ..geometry._lattice import _lerp_matrix

    out = np.asarray(g, np.float64)
    for a, n in enumerate(shape):
        m = out.shape[a]
        if m == n:
            continue
        u = (np.arange(n) + 0.5) / n * m - 0.5
        out = np.moveaxis(np.tensordot(_lerp_matrix(m, u), out, axes=([1], [a])), 0, a)
    return out


def _grad2(g):
    """|∇g|² per cell, forward differences (0 past the grid)."""
    d = [jnp.diff(g, axis=a, append=jnp.take(g, jnp.array([-1]), axis=a)) for a in range(3)]
    return d[0] ** 2 + d[1] ** 2 + d[2] ** 2


def total_variation(g, eps):
    """Σ over cells of sqrt(|∇g|² + eps²) − eps, forward differences (0 past the grid)."""
    return jnp.sum(jnp.sqrt(_grad2(g) + eps * eps) - eps)


def roughness(g, prior: str, eps, mass0=None):
    """The prior's measure of the grid: its total variation ("tv"), Σ|∇g|² ("smooth"), or
    Σ|∇g|² · (``mass0`` / Σg)² ("shape": the squared gradient of the grid's shape at the mass
    ``mass0``, unchanged when the whole grid is scaled)."""
    if prior == "tv":
        return total_variation(g, eps)
    r = jnp.sum(_grad2(g))
    if prior == "shape":
        r = r * (mass0 / jnp.maximum(jnp.sum(g), 1e-30 * mass0)) ** 2
    return r


class _Loss(eqx.Module):
    """The loss of one level: (loss, (data, prior, light result, images))."""

    model: Any
    params: Any
    targets: dict
    support: jax.Array  # flat indices of the support cells
    keep: jax.Array  # (support cells,) 1, or 0 where carving emptied the cell
    shape: tuple = eqx.field(static=True)
    prior: str = eqx.field(static=True)  # one of PRIORS
    # arguments, not constants, so that levels of one shape share one compiled program
    scale: jax.Array  # 1 / (pixels · brightness²)
    prior_weight: jax.Array
    prior_norm: jax.Array  # 1 / (support cells · start's mean (tv) or its square (smooth))
    eps: jax.Array
    mass0: jax.Array  # the start's mass over the support ("shape")

    def grid(self, x):
        g = jnp.zeros(math.prod(self.shape), x.dtype).at[self.support].set(
            jnp.exp(x) * self.keep.astype(x.dtype))
        return g.reshape(self.shape)

    def __call__(self, x):
        g = self.grid(x)
        light = self.model.light(with_density(self.params, g))
        imgs = self.model.images_from(light, with_density(self.params, g))
        data = 0.5 * self.scale * sum(jnp.sum((imgs[c] - self.targets[c]) ** 2)
                                      for c in self.targets)
        prior = self.prior_weight * self.prior_norm * roughness(g, self.prior, self.eps,
                                                                self.mass0)
        return data + prior, (data, prior, light.result, imgs)


@eqx.filter_jit
def _value_and_grad(x, loss):
    """((loss, (data, prior, light result, images)), d loss / d x): the fit's one compiled
    program (the carving's fog-free images come from it too).  An adjoint light solve that
    did not converge makes the gradient NaN (``solves_by_value``: no host callback, so that
    XLA's persistent cache keeps the program for the next process); callers check it."""
    with solves_by_value():
        return eqx.filter_value_and_grad(loss, has_aux=True)(x)


def _carved(scene: Scene, cameras, targets, clear, shape, tol: float, *, fine=None,
            fine_support=None, rays: int = 1, views: int = 1, inner: float = 0.3) -> np.ndarray:
    """(nx, ny, nz) bool: the grid cells that clear pixels see through, up to the surface.

    A pixel is clear where its target is within ``tol`` of the fog-free image (``clear``); its
    ``rays``² sub-pixel rays mark the cells of the ``fine`` grid (default ``shape``) whose
    central part (within ``inner`` of a cell's width from its centre, along each axis) they
    cross: a ray that only grazes a cell's corner leaves it, since a cell with fog at its
    centre can leave such a pixel unchanged.  A fine cell is carved when rays of at least
    ``views`` cameras mark it: fog as bright as the ground behind it can leave one view's pixel
    unchanged, rarely two views' (on cloud-tomo-b one view's carving emptied cells of density
    0.45, 4% of the cloud's mass; docs/tomography.md).  A cell of ``shape`` coarser than
    ``fine`` is carved only when every fine cell in it is (or lies outside ``fine_support``):
    one pixel-centre ray through a coarse cell emptied it whole, 18% of the cloud's mass at 8³.
    """
    from ..forward._camera import camera_rays
    from ..geometry._hits import first_hits

    fine = tuple(shape) if fine is None else tuple(fine)
    lo = np.asarray(scene.domain.min, float)
    size = np.asarray(scene.domain.max, float) - lo
    nf = np.asarray(fine)
    count = np.zeros(fine, np.int64)
    step = 0.25 * float(np.min(size / nf))
    for cam in cameras:
        t, c = np.asarray(targets[cam.name], np.float64), np.asarray(clear[cam.name], np.float64)
        ref = np.maximum(np.abs(c), 0.1 * float(np.mean(np.abs(c))) + 1e-12)
        rows, cols = np.nonzero(np.abs(t - c) <= tol * ref)
        if not len(rows):
            continue
        mark = np.zeros(fine, bool)
        o, d = camera_rays(cam, rays)
        o, d = o[rows, cols].reshape(-1, 3), d[rows, cols].reshape(-1, 3)
        t_hit = np.asarray(first_hits(scene, o, d).t, np.float64)
        with np.errstate(divide="ignore", invalid="ignore"):
            ta, tb = (lo - o) / d, (lo + size - o) / d
        t0 = np.maximum(np.nanmax(np.minimum(ta, tb), axis=1), 0.0)
        t1 = np.minimum(np.nanmin(np.maximum(ta, tb), axis=1), t_hit)
        for k in range(int(np.ceil(np.max(t1 - t0, initial=0.0) / step)) + 1):
            tk = t0 + (k + 0.5) * step
            ok = tk < t1
            if not ok.any():
                break
            u = (o[ok] + tk[ok, None] * d[ok] - lo) / size * nf
            idx = np.floor(u).astype(np.int64)
            sel = np.all((idx >= 0) & (idx < nf) & (np.abs(u - idx - 0.5) < inner), axis=1)
            idx = idx[sel]
            mark[idx[:, 0], idx[:, 1], idx[:, 2]] = True
        count += mark
    cut = count >= views
    if tuple(shape) == fine:
        return cut
    return coarsen_carved(cut if fine_support is None else cut | ~np.asarray(fine_support),
                          shape)


def coarsen_carved(empty: np.ndarray, shape) -> np.ndarray:
    """A coarser grid's cells that are empty: those whose every fine cell (by the fine cells'
    centres) is empty in ``empty``."""
    out = np.ones(tuple(shape), bool)
    ijk = [np.minimum(((np.arange(f) + 0.5) / f * n).astype(np.int64), n - 1)
           for f, n in zip(empty.shape, shape)]
    np.logical_and.at(out, tuple(np.meshgrid(*ijk, indexing="ij")), empty)
    return out


def level_loss(scene: Scene, targets: Mapping[str, np.ndarray], seed: np.ndarray,
               resolution: int, downsample: int, prior_weight: float, M: int = 3,
               supersample: int = 1, settings: Mapping | None = None,
               prior: str = DEFAULT_PRIOR):
    """One level's loss (``_Loss``), its start x (the log of ``seed``'s nonzero cells, the
    support), its forward model and scene: the sweep on a lattice of ``resolution``, the
    cameras of ``targets`` reduced ``downsample`` times (the targets box-averaged to match)."""
    from ..forward._registry import forward_model

    lev_scene = reduced_scene(scene, list(targets), downsample)
    lev_scene = lev_scene.replace(fog=dataclasses.replace(scene.fog, density=seed))
    model = forward_model(lev_scene, "sweep", resolution=resolution, M=M,
                          supersample=supersample, accuracy=None,
                          **{"scheme": DENSITY_SCHEME, **dict(settings or {})})
    p = model.params()
    dt = p.scattering.dtype
    T = {c: jnp.asarray(_block_mean(np.asarray(targets[c], np.float64), downsample)
                        if downsample > 1 else targets[c], dt) for c in targets}
    pixels = sum(int(np.prod(v.shape)) for v in T.values())
    bright = float(np.sqrt(np.mean(np.concatenate(
        [np.asarray(v, np.float64).ravel() for v in T.values()]) ** 2)))
    sup = seed > 0
    idx = np.flatnonzero(sup)
    mean = float(seed[sup].mean())
    loss = _Loss(model=model, params=p, targets=T, support=jnp.asarray(idx),
                 keep=jnp.ones(len(idx), dt), shape=tuple(seed.shape), prior=prior,
                 scale=jnp.asarray(1.0 / (pixels * bright ** 2), dt),
                 prior_weight=jnp.asarray(float(prior_weight), dt),
                 prior_norm=jnp.asarray(1.0 / (len(idx) * (mean if prior == "tv" else mean ** 2)),
                                        dt),
                 eps=jnp.asarray(1e-3 * float(seed.max()), dt),
                 mass0=jnp.asarray(float(seed[sup].sum()), dt))
    return loss, jnp.asarray(np.log(seed.reshape(-1)[idx]), dt), model, lev_scene


def balanced_weight(weight: float, share: float, target: float) -> float | None:
    """The balancing principle's next prior weight, or None when ``share`` (the prior term
    over the data term at a fit's best point) is within ``BALANCE_TOL`` times of ``target``
    (or is not a finite positive number): ``weight · (target / share)^(1 / BALANCE_POWER)``,
    by at most a factor of 10 either way."""
    if not (np.isfinite(share) and share > 0) or \
            abs(math.log(share / target)) <= math.log(BALANCE_TOL):
        return None
    return weight * float(np.clip((target / share) ** (1.0 / BALANCE_POWER), 0.1, 10.0))


def log_density_cap(scene: Scene, shape, x0) -> float:
    """The upper bound of a level's log-densities: ``MAX_CELL_DEPTH`` mean free paths per
    cell of ``shape`` over ``scene``'s domain, and at least 10× the start's densest cell."""
    ext = float(scene.fog.scattering) + float(scene.fog.absorption)
    size = np.asarray(scene.domain.max, float) - np.asarray(scene.domain.min, float)
    width = float(np.min(size / np.asarray(shape, float)))
    cap = math.log(MAX_CELL_DEPTH / max(ext * width, 1e-30))
    return max(cap, float(np.max(np.asarray(x0))) + math.log(10.0))


def rays_per_pixel_side(downsample: int) -> int:
    """A level's default supersampling: two rays per target pixel side (the targets' box
    filter sampled as finely as their own pixels), at most 4 per reduced pixel side, at least
    2."""
    return max(2, min(4, 2 * int(downsample)))


def _ladder(final: tuple, grids) -> list[tuple]:
    """The grid shapes of the levels: each of ``grids`` (cells along the longest axis) below
    the final grid's, the final grid's shape last."""
    big = max(final)
    out = []
    for k in grids or ():
        if k < big:
            out.append(tuple(max(1, round(n * k / big)) for n in final))
    out.append(tuple(final))
    return out


def fit_density(scene: Scene, targets: Mapping[str, Any], *, start=None, grid=None,
                grids: Sequence[int] | None = (8, 16), resolution: int | None = None,
                resolutions: Sequence[int] | None = None,
                downsample: Sequence[int] | int | None = None,
                prior_weight: float | None = None, prior: str = DEFAULT_PRIOR,
                balance: float | bool | None = None, balance_rounds: int = 1,
                carve: bool = True, carve_tol: float = DEFAULT_CARVE_TOL,
                max_steps: Sequence[int] | int | None = None, rtol: float = 1e-3, M: int = 3,
                supersample: Sequence[int] | int | None = None,
                settings: Mapping | None = None, progress=True, checkpoint=None,
                resume: bool = False) -> DensityFit:
    """The fog's density grid from images (density tomography).

    scene: the scene (geometry, sun, sky, cameras, ζ and γ); its fog's density grid, or a
        uniform 1 where it has none, is the start unless ``start`` is given.
    targets: {camera name: (H, W) linear image at the camera's resolution}.
    start: a start grid (3-D, cell-centred over the domain); its nonzero cells are the
        support the fit may fill.
    grid: the estimate's shape (default: the start's).
    grids: the coarser levels' cells along the longest axis (default 8 and 16), each level
        starting from the last one's estimate.
    resolution: the final level's lattice resolution (default 32); ``resolutions``: one per
        level (default: 1.5 nodes per cell, at least 16, at most ``resolution``; the final
        level ``resolution``).
    downsample: the images' reduction per level (default: to about one pixel per lattice
        node along the longest axis on the coarser levels and two on the final one,
        ``FINAL_PIXELS_PER_NODE``, at least 1).
    prior, prior_weight: the prior ("shape", the default, "smooth" or "tv", see ``PRIORS``)
        and its (start) weight (default: the prior's in ``PRIORS``).
    balance: the weight chosen per fit by the balancing principle: the prior term's share of
        the data term at the final level's best point that the fit aims for (``True``: the
        prior's in ``BALANCE``; ``False``: the weight stays ``prior_weight``).  Default: on,
        at ``BALANCE``, when ``prior_weight`` is not given and the prior has one; off when a
        weight is given.  When the share is off by more than ``BALANCE_TOL`` times, the final
        level runs again from its estimate at the weight that brings it there
        (``BALANCE_POWER``), up to ``balance_rounds`` times (each with ``max_steps``' final
        budget).  ``levels[-1]["balance"]`` records the weights and shares.
    carve, carve_tol: space carving of the support (see the module's docstring).
    max_steps: L-BFGS evaluations per level (one number for all levels, or one per level;
        default 20 per coarser level and 40 for the final one).
    rtol: a level stops when an iteration lowers its loss by less than ``rtol`` of the level's
        start loss (or after ``max_steps`` evaluations).
    M: the sweep solver's direction half-width.
    supersample: the cameras' rays per (reduced) pixel side, one number or one per level
        (default: two per target pixel side, ``min(4, 2·downsample)``, at least 2: a level's
        images then sample the targets' box filter as finely as the targets' pixels; with one
        ray per target pixel the truth's own misfit to the Mitsuba images of cloud-tomo was
        3.44e-4 at the final level, with two per side 2.01e-4: docs/tomography.md).
    settings: further forward-model settings (the light solve's scheme is ``DENSITY_SCHEME``,
        "substep", unless they name one: ``{"scheme": "step"}`` takes less than half the
        time, best with ``prior="smooth"``; ``{"scheme": "auto"}`` the sweep's choice).
    checkpoint: a file (.npz) written atomically after every evaluation: the finished levels'
        estimate and records, the current level's best point and its evaluations.
    resume: continue from ``checkpoint`` (a killed fit's, or one that ran out of
        ``max_steps``: give more).  Finished levels are not run again; the current level goes
        on from its best point with the evaluations it has spent, and a fresh L-BFGS memory
        (so the path differs from an uninterrupted fit's after the resume point).  The
        checkpoint must come from the same scene, targets, start and settings.
    """
    t_start = time.perf_counter()
    if prior not in PRIORS:
        raise DifffogError(f"prior: {prior!r} is not one of {', '.join(PRIORS)}")
    if balance is None:
        balance = prior_weight is None and prior in BALANCE
    if balance is True:
        if prior not in BALANCE:
            raise DifffogError(f"balance: the {prior!r} prior has no default share; give one "
                               f"(balance=0.8: the prior term at 0.8 of the data term)")
        balance = BALANCE[prior]
    elif balance is False:
        balance = None
    else:
        try:
            balance = float(balance)
        except (TypeError, ValueError):
            balance = -1.0
        if not (np.isfinite(balance) and balance > 0):
            raise DifffogError(f"balance: a share > 0 (the prior term over the data term), "
                               f"True or False is needed, got {balance!r}")
    if isinstance(balance_rounds, bool) or not isinstance(balance_rounds, (int, np.integer)) \
            or balance_rounds < 0:
        raise DifffogError(f"balance_rounds: a whole number >= 0 is needed, got "
                           f"{balance_rounds!r}")
    prior_weight = PRIORS[prior] if prior_weight is None else float(prior_weight)
    if not (np.isfinite(prior_weight) and prior_weight >= 0):
        raise DifffogError(f"prior_weight: a finite weight >= 0 is needed, got {prior_weight!r}")
    if balance is not None and prior_weight == 0:
        raise DifffogError("prior_weight: 0 cannot be balanced (no prior term); give a weight "
                           "> 0 or balance=False")
    if scene.fog is None:
        raise SceneError("fit_density: the scene has no [fog]; add one (its ζ and γ multiply "
                         "the density grid the fit estimates)")
    names = [c.name for c in scene.cameras]
    if not isinstance(targets, Mapping) or not targets:
        raise DifffogError("targets: give a dict {camera name: (H, W) image}, at least one")
    for name in targets:
        if name not in names:
            raise DifffogError(f"target '{name}': the scene has no camera of that name "
                               f"(cameras: {', '.join(names)})")
    tgt = {}
    for c in scene.cameras:
        if c.name in targets:
            a = np.asarray(targets[c.name], np.float64)
            if a.shape != (c.height, c.width):
                raise DifffogError(f"target '{c.name}': {a.shape[1] if a.ndim > 1 else '?'}x"
                                   f"{a.shape[0]} pixels, camera is {c.width}x{c.height}; "
                                   f"give the image at the camera's resolution")
            if not np.all(np.isfinite(a)):
                raise DifffogError(f"target '{c.name}': has non-finite pixels; mask or fill "
                                   f"them")
            tgt[c.name] = a
    if start is None:
        start = (np.ones((16, 16, 16)) if scene.fog.density is None
                 else np.asarray(scene.fog.density, np.float64))
    start = np.asarray(start, np.float64)
    if start.ndim != 3 or not np.all(np.isfinite(start)) or np.any(start < 0):
        raise DifffogError(f"start: a 3-D grid of finite densities >= 0 is needed, got shape "
                           f"{start.shape}")
    if not np.any(start > 0):
        raise DifffogError("start: every cell is 0, so the fit has no support to fill; give "
                           "a positive density where the fog may be")
    final = tuple(start.shape) if grid is None else (
        (int(grid),) * 3 if np.ndim(grid) == 0 else tuple(int(n) for n in grid))
    shapes = _ladder(final, grids)
    L = len(shapes)
    per = lambda v: list(v) if isinstance(v, Sequence) else [v] * L  # noqa: E731
    top = 32 if resolution is None else int(resolution)
    res = per(resolutions) if resolutions is not None else [
        int(min(top, max(16, round(1.5 * max(s))))) for s in shapes[:-1]] + [top]
    ds = per(downsample) if downsample is not None else level_downsample(scene, tgt, res)
    steps = per(max_steps) if max_steps is not None else [20] * (L - 1) + [40]
    rays = per(supersample) if supersample is not None else [
        rays_per_pixel_side(k) for k in ds]
    if not (len(res) == len(ds) == len(steps) == len(rays) == L):
        raise DifffogError(f"resolutions, downsample, max_steps and supersample need one value "
                           f"per level ({L} levels: grids {[max(s) for s in shapes]})")
    settings_json = {"grids": [list(s) for s in shapes], "resolutions": res, "downsample": ds,
                     "prior": prior, "prior_weight": prior_weight, "balance": balance,
                     "balance_rounds": int(balance_rounds), "carve": carve,
                     "carve_tol": carve_tol,
                     "max_steps": steps, "rtol": rtol, "M": M, "supersample": rays}
    history, levels = [], []
    g_prev, result = None, "max_steps"
    ckpt = None if checkpoint is None else Path(checkpoint)
    # (not max_steps: a resume may give more)
    print_ = _fingerprint(scene, tgt, start, settings,
                          {k: v for k, v in settings_json.items() if k != "max_steps"})
    lev0, resumed = 0, None
    if resume:
        if ckpt is None:
            raise DifffogError("resume=True needs checkpoint=PATH (the file an earlier fit "
                               "wrote)")
        lev0, g_prev, resumed, history, levels = _load(ckpt, print_, len(shapes))
        if lev0 >= len(shapes):
            raise DifffogError(f"resume: the fit in {ckpt} finished (its last level converged); "
                               f"its result is the one to use, or delete the checkpoint")
        history.append({"level": lev0, "step": -1, "what": "resume"})
    meter = as_meter(progress, "density fit")
    support_start = start > 0
    fine_support = resample(support_start.astype(float), final) > 0.5
    try:
        for lev, (shape, n_res, k_ds, n_steps, n_rays) in enumerate(zip(shapes, res, ds, steps,
                                                                        rays)):
            if lev < lev0:  # finished before the resume
                continue
            t_lev = time.perf_counter()
            sup = resample(support_start.astype(float), shape) > 0.5
            seed = resample(start if g_prev is None else g_prev, shape)
            seed = np.where(sup, np.maximum(seed, _FLOOR * max(float(seed.max()), 1e-12)), 0.0)
            loss, x, model, lev_scene = level_loss(scene, tgt, seed, n_res, k_ds,
                                                   prior_weight, M, n_rays, settings,
                                                   prior)
            dt = x.dtype
            x_cap = log_density_cap(scene, shape, x)
            T = loss.targets
            idx = np.asarray(loss.support)
            carved = 0
            # the level's first call compiles its program: its time (with that one evaluation)
            first_call = [None]
            if carve:  # the fog-free images (every support cell at ~0) against the targets
                t_c = time.perf_counter()
                (_, (_, _, _, clear)), _ = _value_and_grad(jnp.full_like(x, -30.0), loss)
                first_call[0] = time.perf_counter() - t_c
                # on the final grid (a coarse cell only when all of its fine cells are), one
                # ray per target pixel, two views agreeing where there are two
                cut = _carved(lev_scene, model.cameras, {c: np.asarray(T[c]) for c in T},
                              {c: np.asarray(v) for c, v in clear.items()}, shape, carve_tol,
                              fine=final, fine_support=fine_support, rays=k_ds,
                              views=min(2, len(T)))
                keep = ~cut.reshape(-1)[idx]
                carved = int((~keep).sum())
                if not keep.any():
                    raise DifffogError("fit_density: space carving removed every cell of the "
                                       "support (every target pixel matches the fog-free "
                                       "image); check the targets, or carve=False")
                history.append({"level": lev, "step": -1, "what": "carve",
                                "carved_cells": carved, "seconds": time.perf_counter() - t_c})
                # held at 0 by the mask (their gradient is 0: L-BFGS never moves them), so
                # that the compiled program stays the one it is
                loss = eqx.tree_at(lambda lo: lo.keep, loss, jnp.asarray(keep, dt))
            # L-BFGS-B (SciPy) on the host, one compiled value-and-gradient per evaluation
            # (one light solve, one adjoint solve, the cameras' march and its reverse); the
            # final level may run again at a balanced weight (a pass each)
            weights, shares = [prior_weight], []
            pass_ = 0
            if resumed is not None:  # this is lev0: go on from its pass's best point
                if resumed["x"].shape != x.shape:
                    raise DifffogError(f"resume: the checkpoint {ckpt} does not match this "
                                       f"fit's level {lev}; delete it or run without resume")
                if resumed["pass"] > 0:
                    pass_ = resumed["pass"]
                    weights = list(resumed["weights"])
                    shares = list(resumed["shares"])
                    loss = eqx.tree_at(lambda lo: lo.prior_weight, loss,
                                       jnp.asarray(weights[-1], dt))
            spent_all = 0
            passes = []
            while True:
                best, count, spent, stopped = _lbfgs_pass(
                    loss, x, x_cap, lev, pass_, n_steps, rtol, history, first_call, meter,
                    sum(steps[:lev]) + spent_all, sum(steps) + spent_all, resumed,
                    lambda best, count, unit, lev=lev, w=weights, sh=shares, p=pass_: _save(
                        ckpt, print_, lev, g_prev, best, count, unit, history, levels,
                        {"pass": p, "weights": w, "shares": sh}) if ckpt is not None else None)
                resumed = None
                spent_all += count
                failed = not np.isfinite(best[0])  # no evaluation's light solve converged
                if stopped and not failed:
                    warnings.warn(f"fit_density: the gradient's adjoint light solve did not "
                                  f"converge at evaluation {count} of level {lev} (grid "
                                  f"{'x'.join(map(str, shape))}); the level stopped at its "
                                  f"best point so far; raise settings' max_iterations or "
                                  f"adjoint_rtol", AdjointWarning, stacklevel=2)
                x = jnp.asarray(best[1], dt)
                # (not g_prev yet: the checkpoints of a second pass seed a resumed level
                # from the level before)
                est = np.asarray(loss.grid(x), np.float64)
                passes.append(est.astype(np.float32))
                if failed or balance is None or lev < L - 1:
                    break
                terms = best[2]
                if terms is None:  # a checkpoint from before the terms were kept
                    break
                share = terms["prior"] / terms["data"] if terms["data"] > 0 else np.inf
                shares.append(share)
                new = balanced_weight(weights[-1], share, balance)
                if pass_ >= balance_rounds or new is None:
                    break
                weights.append(new)
                history.append({"level": lev, "step": -1, "what": "balance",
                                "share": share, "prior_weight": weights[-1]})
                loss = eqx.tree_at(lambda lo: lo.prior_weight, loss,
                                   jnp.asarray(weights[-1], dt))
                pass_ += 1
            g_prev = est
            levels.append({"grid": list(shape), "resolution": n_res, "downsample": k_ds,
                           "steps": spent_all, "loss": best[0],
                           "support_cells": int(np.sum(np.asarray(loss.keep) > 0)),
                           "carved_cells": carved, "compile_s": first_call[0],
                           "seconds": time.perf_counter() - t_lev})
            if lev == L - 1 and balance is not None:
                levels[-1]["balance"] = {"target": balance, "prior_weights": weights,
                                         "shares": shares}
            if failed:
                result = "adjoint_failed" if stopped else "light_failed"
                what = ("the first evaluation's adjoint light solve (its gradient) did not "
                        "converge" if stopped else "no light solve converged")
                warnings.warn(f"fit_density: {what} at level {lev} (grid "
                              f"{'x'.join(map(str, shape))}); the estimate is its start; "
                              f"raise the solver's max_iterations",
                              AdjointWarning if stopped else UserWarning, stacklevel=2)
                break
            if lev == L - 1 and stopped:
                result = "adjoint_failed"
            elif lev == L - 1 and not spent:
                result = "successful"
            if ckpt is not None and (lev < L - 1 or not (spent or stopped)):
                # the level is done: a resume starts at the next (a final level that ran out
                # of evaluations keeps its own checkpoint, so that more of them continue it)
                _save(ckpt, print_, lev + 1, g_prev, [np.inf, None, None], 0, None, history,
                      levels)
    finally:
        meter.close()
    est = g_prev.astype(np.float32)
    return DensityFit(density=est, support=est > 0, history=history, levels=levels,
                      result=result, time_s=time.perf_counter() - t_start,
                      settings=settings_json, passes=passes, final_level=(loss, x))


def _lbfgs_pass(loss, x, x_cap, lev, pass_, n_steps, rtol, history, first_call, meter, done,
                total, resumed, save):
    """One L-BFGS-B run (SciPy) of a level's loss from ``x`` (log-densities, each at most
    ``x_cap``: ``log_density_cap``), at most ``n_steps`` evaluations:
    ([best loss, its x, its data and prior terms], evaluations, whether the budget ran out,
    whether it stopped because an evaluation's adjoint solve did not converge).
    ``resumed``: a checkpoint's state of this pass ({x, best, count, unit}) to go on from."""
    dt = x.dtype
    best = [np.inf, np.asarray(x), None]
    count = [0]
    # SciPy's ftol is relative to max(|f|, 1): the loss is scaled to 1 at the start, so that
    # rtol is the decrease per iteration relative to the start's loss
    unit = [None]
    if resumed is not None:  # go on from the pass's best point
        best[0], best[1], best[2] = resumed["best"], resumed["x"], resumed.get("terms")
        count[0], unit[0] = resumed["count"], resumed["unit"]
        x = jnp.asarray(resumed["x"], dt)

    def fun(xn):
        if count[0] >= n_steps:  # SciPy's maxfun is checked per iteration only
            raise _Budget
        t_s = time.perf_counter()
        (val, (data, prior, code, _)), grad = _value_and_grad(jnp.asarray(xn, dt), loss)
        val, grad = float(val), np.asarray(grad, np.float64)
        if int(code) == 0 and not np.all(np.isfinite(grad)):  # the adjoint did not converge
            history.append({"level": lev, "step": count[0], "what": "adjoint_failed",
                            "seconds": time.perf_counter() - t_s,
                            **({"pass": pass_} if pass_ else {})})
            count[0] += 1
            raise _AdjointFailed from None
        history.append({"level": lev, "step": count[0], "loss": val, "data": float(data),
                        "prior": float(prior), "light_result": int(code),
                        "seconds": time.perf_counter() - t_s, **({"pass": pass_} if pass_
                                                                 else {})})
        if first_call[0] is None:
            first_call[0] = history[-1]["seconds"]
        count[0] += 1
        if val < best[0] and int(code) == 0:
            best[0], best[1] = val, np.array(xn)
            best[2] = {"data": float(data), "prior": float(prior)}
        save(best, count[0], unit[0])
        meter.update(done + count[0], total, level=lev, loss=val)
        if unit[0] is None:
            unit[0] = val if val > 0 else 1.0
        return val / unit[0], grad / unit[0]

    spent, stopped = count[0] >= n_steps, False
    try:
        if not spent:
            import scipy.optimize  # 0.3-0.5 s to import; only a density fit needs it

            x0 = np.asarray(x, np.float64)
            scipy.optimize.minimize(fun, x0, jac=True, method="L-BFGS-B",
                                    bounds=scipy.optimize.Bounds(-np.inf, np.full(x0.shape, x_cap)),
                                    options={"maxfun": n_steps, "maxiter": n_steps,
                                             "ftol": rtol, "gtol": 0.0, "maxcor": 10})
    except _Budget:
        spent = True
    except _AdjointFailed:
        stopped = True
    return best, count[0], spent or count[0] >= n_steps, stopped


def _fingerprint(scene: Scene, tgt, start, settings, fit_settings) -> str:
    """What a checkpoint must match: the scene, targets, start and settings."""
    from ._checkpoint import digest, fingerprint

    return fingerprint(scene=repr(scene), targets={c: digest(a) for c, a in tgt.items()},
                       start=digest(np.asarray(start, np.float64)),
                       settings=dict(settings or {}), fit=fit_settings)


def _save(path: Path, fp: str, lev: int, g_prev, best, count: int, unit, history,
          levels, passes: dict | None = None) -> None:
    """The checkpoint, written atomically (a kill leaves the previous one intact).
    ``passes``: the final level's balancing state ({pass, weights, shares})."""
    from ._checkpoint import savez_atomic

    meta = json.dumps({"fingerprint": fp, "level": lev, "count": count, "unit": unit,
                       "best": None if not np.isfinite(best[0]) else best[0],
                       "terms": best[2],
                       **(passes or {}), "history": history, "levels": levels})
    arrays = {"meta": np.array(meta)}
    if g_prev is not None:
        arrays["g_prev"] = np.asarray(g_prev, np.float64)
    if best[1] is not None:
        arrays["x"] = np.asarray(best[1], np.float64)
    savez_atomic(path, **arrays)


def _load(path: Path, fp: str, n_levels: int):
    """(level, the grid before it, {x, best, count, unit} or None, history, levels)."""
    if not path.exists():
        raise DifffogError(f"resume: no checkpoint at {path}; run the fit without resume first")
    try:
        with np.load(path, allow_pickle=False) as z:
            meta = json.loads(str(z["meta"]))
            g_prev = z["g_prev"] if "g_prev" in z else None
            x = z["x"] if "x" in z else None
    except (OSError, ValueError, KeyError) as e:
        raise DifffogError(f"resume: {path} is not a density fit's checkpoint ({e}); delete "
                           f"it or run without resume") from None
    if meta.get("fingerprint") != fp:
        raise DifffogError(f"resume: the checkpoint {path} belongs to a different fit (scene, "
                           f"targets, start or settings changed); delete it or run without "
                           f"resume")
    lev = int(meta["level"])
    state = None
    if x is not None and lev < n_levels:
        state = {"x": x, "count": int(meta["count"]), "unit": meta["unit"],
                 "best": np.inf if meta["best"] is None else float(meta["best"]),
                 "terms": meta.get("terms"), "pass": int(meta.get("pass", 0)),
                 "weights": meta.get("weights"), "shares": meta.get("shares")}
    return lev, g_prev, state, meta["history"], meta["levels"]


def level_downsample(scene: Scene, tgt, resolutions) -> list[int]:
    """Each level's default image reduction: about one pixel per lattice node along the
    cameras' longest side on the coarser levels, ``FINAL_PIXELS_PER_NODE`` on the final one,
    each a divisor of every target camera's width and height."""
    longest = max(max(c.width, c.height) for c in scene.cameras if c.name in tgt)
    per_node = [1] * (len(resolutions) - 1) + [FINAL_PIXELS_PER_NODE]
    return [_divisor(scene, tgt, max(1, longest // (k * n)))
            for n, k in zip(resolutions, per_node)]


def _divisor(scene: Scene, tgt, want: int) -> int:
    """The largest k <= ``want`` that divides every target camera's width and height."""
    for k in range(max(1, want), 0, -1):
        if all(c.width % k == 0 and c.height % k == 0 for c in scene.cameras if c.name in tgt):
            return k
    return 1
