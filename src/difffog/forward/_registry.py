"""The registry of forward models: one name → its class, its settings and its presets.

Every caller that picks a solver by name (the command line, :func:`difffog.fit`, the
speed–accuracy study, the notebooks) goes through :func:`forward_model`; nobody else compares
solver names.

Accuracy presets (``--accuracy draft|default|high``, ``accuracy=``) are chosen from the
speed–accuracy study (``difffog bench``; figures in ``docs/speed-accuracy.md`` and
``benchmarks/results/bench/``), not guessed:

* sweep: the lattice resolution N and direction half-width M set the model error; the
  iteration tolerance only needs to sit well below it (1e-3 changes images by < 0.1%).
  draft = N 32, M 2 (0.7 s warm, 16% mean error against Mitsuba over the four benchmark
  scenes); default = N 64, M 3 (2.3 s, 11%); high = N 96, M 4 (18 s, 9%).
* splat: the resolution of the splatted voxels and the sheet count.  Its error against the
  references hardly moves with either (23-25% averaged over the four scenes: the light model
  dominates), so the presets trade detail for time: draft = N 32 (0.10 s), default = N 64
  with 34 sheets (0.11 s, the lowest error measured, 21.9%; one sheet per voxel was 23.2% in
  0.24 s), high = N 128 with a sheet per voxel (1.1 s: sharper shadows and edges, not a lower
  error).

A fit solves 1 + (number of unknowns) light problems per step, so it has its own defaults
(``fit_defaults``): the sweep at N = 32, M = 3 with a tight light tolerance (the residual's
noise floor) and a looser adjoint.
"""

from __future__ import annotations

import inspect
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field

from .._cache import release_if_crowded
from .._cost import EDGE_SAMPLES, estimate_splat, estimate_sweep
from .._errors import DifffogError
from ..scene._description import Scene
from ._model import AbstractForwardModel

LEVELS = ("draft", "default", "high")


@dataclass(frozen=True)
class SolverEntry:
    """One forward model in the registry.

    name: what users type ("sweep", "splat").
    summary: one line for help texts.
    build: (scene, *, cameras, **settings) → the model.
    presets: accuracy level → settings.
    fit_defaults: the settings a fit uses unless told otherwise.
    study: the settings ``difffog bench`` measures, cheapest first; quick: its smoke test.
    estimate: (scene, *, cameras, **settings) → its :class:`difffog.CostEstimate` (``_cost.py``).
    traces_density: whether its model takes ``fog.density`` as a traced parameter
        (``difffog.with_density``; density tomography).
    traces_sun: whether its model can take the sun's angles as traced parameters
        (``sun.zenith_deg``, ``sun.azimuth_deg``; ``SweepModel.with_sun_derivatives``).
    brightness_floor: how far (relative) its images' brightness is not vouched for by its
        validation against independent truth even on a fine lattice: a fit with
        ``model_error="refine"`` counts a bias of this size in each camera's images into
        each estimate's model error (``fit``'s ``model_floor``).
    """

    name: str
    summary: str
    build: Callable[..., AbstractForwardModel]
    presets: Mapping[str, Mapping]
    fit_defaults: Mapping = field(default_factory=dict)
    study: tuple[Mapping, ...] = ()
    quick: tuple[Mapping, ...] = ()
    estimate: Callable | None = None
    traces_density: bool = False
    traces_sun: bool = False
    brightness_floor: float = 0.0

    @property
    def settings(self) -> tuple[str, ...]:
        """The keyword settings ``build`` takes (besides the scene and the cameras)."""
        ps = inspect.signature(self.build).parameters
        return tuple(k for k, p in ps.items()
                     if p.kind == p.KEYWORD_ONLY and k not in ("cameras",))


def _build_sweep(scene, *, cameras=None, resolution: int = 64, M: int = 3, tol: float = 1e-4,
                 max_iterations: int = 500, method: str = "auto", devices: int = 1,
                 mesh=None, adjoint_rtol: float = 1e-6, terms: str = "auto",
                 sky_quadrature=None, restart: int = 30, progress=None, throw: bool = True,
                 supersample: int = 2, precondition: str = "auto", kernel: str = "auto",
                 phase_order="auto", scheme: str = "auto", tangents: str = "matrix-free",
                 block_tangents: bool = True, sweep_residuals: str = "auto",
                 first_collision: str = "beam", adjoint: str = "auto", edge_samples: int = EDGE_SAMPLES,
                 once_M: int | None = None):
    from .sweep._model import SweepModel
    from .sweep._solver import SweepSolver

    solver = SweepSolver(M=M, tol=tol, max_iterations=max_iterations, method=method,
                         devices=devices, mesh=mesh, adjoint_rtol=adjoint_rtol, terms=terms,
                         sky_quadrature=sky_quadrature, restart=restart, progress=progress,
                         throw=throw, precondition=precondition, kernel=kernel,
                         phase_order=phase_order, scheme=scheme, tangents=tangents,
                         block_tangents=block_tangents,
                         sweep_residuals=sweep_residuals, first_collision=first_collision,
                         adjoint=adjoint, once_M=once_M)
    return SweepModel(scene, resolution=resolution, solver=solver, supersample=supersample,
                      cameras=cameras, edge_samples=edge_samples)


def _build_splat(scene, *, cameras=None, resolution: int = 64, sheets: int | None = None,
                 supersample: int = 1, forward_scatter: bool = True, back_scatter: bool = True,
                 soft_shadows: bool = True, back_window: int = 6, shadow_texel=None,
                 quadrature: int = 2, kernel_radius: int = 3, occluder_thickness: str = "paper",
                 thickness_scale: float = 4.0, scattered_phase: str = "hg",
                 similarity: bool = True):
    from .splat._model import SplatModel

    return SplatModel(scene, cameras=cameras, resolution=resolution, sheets=sheets,
                      supersample=supersample, forward_scatter=forward_scatter,
                      back_scatter=back_scatter, soft_shadows=soft_shadows,
                      back_window=back_window, shadow_texel=shadow_texel, quadrature=quadrature,
                      kernel_radius=kernel_radius, occluder_thickness=occluder_thickness,
                      thickness_scale=thickness_scale, scattered_phase=scattered_phase,
                      similarity=similarity)


SOLVERS: dict[str, SolverEntry] = {
    "sweep": SolverEntry(
        name="sweep",
        summary="discrete ordinates on the lattice (Langer, Breton & Zucker): multiple "
                "scattering and interreflection, converged, exact gradients",
        build=_build_sweep,
        presets={"draft": dict(resolution=32, M=2, tol=1e-3),
                 "default": dict(resolution=64, M=3, tol=1e-4),
                 "high": dict(resolution=96, M=4, tol=1e-4)},
        fit_defaults=dict(resolution=32, M=3, tol=1e-5, max_iterations=1000,
                          adjoint_rtol=1e-4, supersample=2),
        study=(dict(resolution=32, M=2, tol=1e-3), dict(resolution=48, M=3, tol=1e-3),
               dict(resolution=64, M=3, tol=1e-4), dict(resolution=96, M=4, tol=1e-4)),
        quick=(dict(resolution=16, M=2, tol=1e-3),),
        estimate=estimate_sweep,
        traces_density=True,
        traces_sun=True,
        # the image means of a fine render (N = 64, M = 3) against the Mitsuba 3 references:
        # +0.5 / +0.6% (fog-balls), −0.2 / +0.3% (ring-box), +0.1 / +0.2% (translucent-cube),
        # 0.0% (furnace); docs/fitting.md, the model error's "brightness" part
        brightness_floor=0.005,
    ),
    "splat": SolverEntry(
        name="splat",
        summary="sheet-based splatting (Zhang & Crawfis): one pass per camera, fast and "
                "approximate; needs a [sun] and an open domain",
        build=_build_splat,
        presets={"draft": dict(resolution=32, sheets=None),
                 "default": dict(resolution=64, sheets=34),
                 "high": dict(resolution=128, sheets=None)},
        fit_defaults=dict(resolution=32, supersample=2),
        study=(dict(resolution=32, sheets=None), dict(resolution=64, sheets=34),
               dict(resolution=64, sheets=None), dict(resolution=128, sheets=None)),
        quick=(dict(resolution=16, sheets=None),),
        estimate=estimate_splat,
        # its image means against the Mitsuba 3 references at N = 64, best light model:
        # −1 to −24% (benchmarks/results/splat_references.md)
        brightness_floor=0.25,
    ),
}


def solver_names() -> tuple[str, ...]:
    return tuple(SOLVERS)


def solver_entry(solver: str) -> SolverEntry:
    """The registry entry of ``solver``, or a one-line error listing the known ones."""
    if solver not in SOLVERS:
        raise DifffogError(f"unknown solver {solver!r}: choose {' or '.join(SOLVERS)}")
    return SOLVERS[solver]


def preset(solver: str, accuracy: str = "default") -> dict:
    """The settings of ``solver`` at ``accuracy`` (a copy)."""
    entry = solver_entry(solver)
    if accuracy not in LEVELS:
        raise DifffogError(f"unknown accuracy {accuracy!r}: choose {', '.join(LEVELS)}")
    return dict(entry.presets[accuracy])


def check_settings(solver: str, settings: Mapping, what: str = "forward_model") -> None:
    """A one-line error for settings ``solver`` does not take."""
    entry = solver_entry(solver)
    unknown = sorted(set(settings) - set(entry.settings))
    if unknown:
        raise DifffogError(f"{what}: {', '.join(unknown)} {'is not a setting' if len(unknown) == 1 else 'are not settings'} "
                           f"of the {solver} solver; it takes {', '.join(entry.settings)}")


def forward_model(scene: Scene, solver: str = "sweep", accuracy: str | None = "default", *,
                  cameras=None, force: bool = False, **settings) -> AbstractForwardModel:
    """A forward model of ``scene``: ``model(params)`` → {camera: (H, W) image}.

    scene: a :class:`difffog.Scene` (``difffog.load_scene(...)`` or built in Python).
    solver: "sweep" (accurate: multiple scattering, interreflection) or "splat" (fast,
        approximate; see ``difffog.SOLVERS`` for what each does).
    accuracy: "draft", "default" or "high": a preset of the solver's settings from the
        measured speed–accuracy study; None starts from the solver's own defaults.
    cameras: names of the cameras to render (default: all).
    settings: single settings that override the preset (None values are ignored), e.g.
        ``resolution=48``, ``M=4``, ``tol=1e-5``, ``devices=2`` (sweep), ``sheets=64``
        (splat).  A setting the solver does not take is a one-line error.
    force: build it even when its estimated peak memory (:func:`difffog.estimate`) exceeds
        what the machine has; otherwise that is a :class:`difffog.ResourceError` before
        anything is allocated (and above half of it a :class:`difffog.MemoryWarning`).
    """
    if not isinstance(scene, Scene):
        raise DifffogError(f"forward_model: expected a difffog.Scene, got {type(scene).__name__}"
                           "; load one with difffog.load_scene(name or path)")
    entry = solver_entry(solver)
    settings = {k: v for k, v in settings.items() if v is not None}
    check_settings(solver, settings)
    base = {} if accuracy is None else preset(solver, accuracy)
    full = {**base, **settings}
    guard(scene, solver, cameras=cameras, force=force, **full)
    return entry.build(scene, cameras=cameras, **full)


def model_estimate(scene: Scene, solver: str, *, cameras=None, **settings):
    """The :class:`difffog.CostEstimate` of ``forward_model(scene, solver, ...)`` with these
    settings (the solver's own defaults where a setting is not given)."""
    entry = solver_entry(solver)
    ps = inspect.signature(entry.build).parameters
    defaults = {k: p.default for k, p in ps.items()
                if p.kind == p.KEYWORD_ONLY and k != "cameras"
                and p.default is not inspect.Parameter.empty}
    return entry.estimate(scene, cameras=cameras, **{**defaults, **settings})


def guard(scene: Scene, solver: str, *, cameras=None, force: bool = False, what=None,
          **settings):
    """Refuse (ResourceError) or warn (MemoryWarning) before building a model that will not
    fit, and drop JAX's compiled programs first where the process nears its limit on memory
    mappings (``_cache.release_if_crowded``); returns the estimate."""
    import warnings

    from .._cost import check_fits
    from .._errors import MemoryWarning

    est = model_estimate(scene, solver, cameras=cameras, **settings)
    size = settings.get("resolution")
    label = what or f"the {solver} at resolution {size}" + (
        f", M = {settings['M']}" if "M" in settings else "")
    note = check_fits(est, force=force, what=label)
    if note:
        warnings.warn(note, MemoryWarning, stacklevel=3)
    release_if_crowded()
    return est
