"""The sweep's light solve: prepare the lattice's static structure once, then iterate the
one-bounce operator to its fixed point and differentiate that fixed point implicitly.

``SweepSolver.prepare(scene, lattice)`` does the host-side, non-differentiable work once
(:class:`SweepGeometry`, on device); ``SweepSolver.solve(geometry, params)`` is a pure JAX
function of the parameters returning a :class:`LightField` with its result code.  One
application of K is six face sweeps (``_kernel.py``) plus the scatter/reflect step; GMRES
(``_krylov.py``) or Jacobi iterate it; the implicit function theorem (``_implicit.py``)
differentiates the fixed point with one tangent/adjoint solve, so the memory of a gradient
does not grow with the number of iterations.
"""

from __future__ import annotations

import concurrent.futures
import dataclasses
import functools
import math
import os
import warnings

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from ...geometry._blocking import segment_blocking
from ...geometry._hits import shadows_exactly, sun_visibility
from ...geometry._directions import (FACE_AXES, cosine_normalization, direction_set,
                                     face_plane_axes, sky_quadrature)
from ...geometry._lattice import FREE, SOLID, SURFACE
from ..._errors import DeviceWarning, SceneError, SolverError
from ..._numerics import FOUR_PI, safe_div
from .._camera import forward_peak_kernel
from ..._progress import AbstractProgressMeter, NoProgress, as_meter
from ..._results import RESULTS, combine
from . import _native
from ._implicit import CheckedSolver, KrylovSolver, fixed_point
from ._dsa import DiffusionPreconditioner, neighbour, on_fluence
from ._harmonics import MAX_ORDER, basis, delta_m, harmonic_moments, moment_coefficients
from ._krylov import gmres
from ._lightfield import LightField
from ._march import in_forward_mode
from ...scene._params import Params
from ._terms import TERMS, Terms, choose_terms, terms_violation
from ._uncollided import sky_uncollided, sun_transmittance
from ._kernel import (
    FaceGeometry,
    SweepConsts,
    cell_samples,
    face_consts,
    from_face,
    sky_boundary,
    KERNELS,
    kernel_for,
    sweep_face,
    sweep_face_mesh,
    sweep_face_transposed,
    sweep_face_world,
    substep_offsets,
    substep_weight_scale,
    to_face,
    substep_native_applies,
    world_native_applies,
)

METHODS = ("auto", "jacobi", "gmres")
#: phase_order="auto" for a Henyey–Greenstein fog with g ≠ 0 (measured: docs/validation.md)
DEFAULT_PHASE_ORDER = 3
PRECONDITIONERS = ("auto", "none", "diffusion")
#: precondition="auto" uses the diffusion preconditioner from this diffusive size on (the
#: lesser of the fog's optical size and its diffusion length, in mean free paths:
#: ``_optical_size``).  Measured (GMRES steps without → with it): fog-balls at N = 32, M = 3,
#: γ = 0.01: ζ = 2 (size 2) 12 → 14 (0.74 → 1.03 s), ζ = 10 (size 10) 23 → 20 (1.36 → 1.33 s),
#: ζ = 50 48 → 26 (2.8 → 1.7 s); issue 14's cube at N = 16, τ = 100: albedo 0.9 (diffusion
#: length 1.8) 8 → 13, albedo 0.99 (5.8) 19 → 16 (bench_dsa.py)
DIFFUSION_OPTICAL_SIZE = 5.0

#: the light solve's transport schemes (``SweepSolver.scheme``)
SCHEMES = ("auto", "step", "linear", "substep")
FIRST_COLLISIONS = ("beam", "deposit")
#: scheme="auto" takes the linear-source scheme where one lattice step is optically thicker
#: than this (σ_t·h·M, the scene's values at ``prepare``: where ``ThickStepWarning`` starts).
#: Measured (docs/validation.md): below it the two schemes agree (τ = 1 slabs within 0.1%,
#: cloud-plane 7.4 / 1.9% against 7.3 / 1.9%); from a step depth of 1 on the step scheme's
#: lattice diffusion h|L|/6 exceeds the true 1/(3σ_t) (τ = 16 slabs at N = 32, M = 2, a step
#: depth of 1: T +13…+53% against +0.5…+3.2%), and issue 14's thick cube at step depths of
#: 6 / 62 / 625 is +1.8 / +12.6 / +13.3% (step) against −1.2 / +2.7 / +1.3% (linear)
LINEAR_STEP_DEPTH = 1.0
#: ... and at any step depth in fog at least this many mean free paths across
#: (``optical_size``: δ-scaled σ_t at the densest node × ``fog_extent``): there the step
#: scheme's lattice diffusion shows in the light that crosses the fog, and any threshold in
#: step depth made the default's error jump where refining the lattice crossed it.  Slabs as
#: cameras read them (``benchmarks/slab_cameras.py``, T error over albedo 0.9–0.999 and three
#: lights): stop 77 took the linear scheme from a step depth of 0.5 here, after τ = 64 at a
#: depth of exactly 1 (N = 128, M = 2: step) had read +93% where N = 64 (linear) read +7.6%;
#: under that rule τ = 16 read +2.1…+12.4% at N = 64, M = 2 and +0.6…+6.0% at N = 128, M = 3
#: (step, depths 0.5 and 0.375; the linear scheme there −1.0…+3.1% and −0.5…+1.0%), and
#: τ = 64 +6.1…+22.4% at N = 256, M = 2 (step) where N = 128 (linear) read +3.4…+8.6%
#: (stop 78; docs/validation.md, "Any step depth in thick fog").  It costs +19% per
#: iteration.  Mitsuba's clouds at N = 96, M = 3 read the same to 0.1 point either way;
#: fog-balls and translucent-cube (2.3–2.5 across) stay on the step scheme at any N
LINEAR_FOG_SIZE = 5.0


class SweepGeometry(eqx.Module):
    """Static structure of a scene on its lattice, prepared once for the sweep solver."""

    faces: tuple[FaceGeometry, ...]
    consts: tuple[SweepConsts, ...]
    sky_frac: jax.Array  # (6, D) fraction of the sky radiance entering along each direction
    free: jax.Array  # (nx, ny, nz) bool
    surf: jax.Array
    solid: jax.Array
    density: jax.Array  # fog density multiplier at non-solid nodes
    material: jax.Array  # int, shape index of SURFACE/SOLID nodes (0 where none)
    cnorm: jax.Array  # cosine normalization per SURFACE node
    sun_cos: jax.Array  # max(0, N·ŝ) per SURFACE node
    normal: jax.Array  # (nx, ny, nz, 3) unit normals of SURFACE nodes (0 elsewhere)
    h: float = eqx.field(static=True)
    origin: tuple[float, float, float] = eqx.field(static=True)
    M: int = eqx.field(static=True)
    periodic_xy: bool = eqx.field(static=True)
    sun_dir: tuple[float, float, float] | None = eqx.field(static=True)
    has_surfaces: bool = eqx.field(static=True)
    warmup: int = eqx.field(static=True)
    terms: Terms = eqx.field(static=True, default=None)
    optical_size: float = eqx.field(static=True, default=0.0)  # of the scene's fog (prepare)
    order: int = eqx.field(static=True, default=0)  # δ-M order L of the phase (0: isotropic)
    linear: bool = eqx.field(static=True, default=False)  # the linear-source scheme (slopes)
    substep: bool = eqx.field(static=True, default=False)  # the sub-stepped scheme (segments
    #                                                        in one sub-step per plane)
    # order > 0 with a sun: n² unit vectors over each face direction's cell (6, D, n², 3) and
    # their weights (6, D, n²) (the cell-averaged phase of the first-collision sun)
    sun_cells: tuple[jax.Array, jax.Array] | None = None
    # the sun's visibility past the shapes, box-filtered over each node's fluid from exact
    # shadow rays (``geometry._hits.sun_visibility``), or None: the SOLID nodes block the beam
    sun_vis: jax.Array | None = None
    # the sun's direction traced (``sun.zenith_deg`` / ``sun.azimuth_deg`` as unknowns), near
    # the static ``sun_dir`` the host's parts were built for; None: ``sun_dir``
    sun_vec: jax.Array | None = None
    # the geometry of the same lattice at the direction set that carries the sun's
    # once-scattered light (``SweepSolver.once_M``), or None: the solve's own
    once: "SweepGeometry | None" = None
    # per face, the native blocked sweep's surface records (``_native.surface_records``: made
    # here once, not at every sweep) or None where it does not take them
    records: tuple[dict | None, ...] | None = None

    def sun_vector(self, dtype):
        """The unit vector towards the sun (3,) the light solve uses (traced or static)."""
        if self.sun_vec is not None:
            return self.sun_vec.astype(dtype)
        return jnp.asarray(np.asarray(self.sun_dir, np.float64), dtype)

    @property
    def n_moments(self) -> int:
        """K = (L+1)² − 1: the angular moments carried per node beyond the fluence."""
        return (self.order + 1) ** 2 - 1

    @property
    def channels(self) -> bool:
        """Whether the state's fluence part has a channel axis (the angular moments)."""
        return self.order > 0

    @property
    def fluence_shape(self) -> tuple[int, ...]:
        """Of the state's fluence part: (nx, ny, nz), with an anisotropic phase (nx, ny, nz,
        1 + K) (Λ, then its moments)."""
        return self.shape + ((1 + self.n_moments,) if self.order > 0 else ())

    def vol_range(self, face: int) -> tuple[int, int] | None:
        """Planes [lo, hi) along a face's sweep (face frame) where the fog step is needed: the
        fog's node range widened by M//2 (``segment_depth`` averages σ_t over M planes)."""
        if self.terms is None or self.terms.fog_slabs is None:
            return None
        axis, sign = FACE_AXES[face]
        n = self.shape[axis]
        lo, hi = self.terms.fog_slabs[axis]
        lo, hi = max(0, lo - self.M // 2), min(n, hi + self.M // 2)
        return (lo, hi) if sign > 0 else (n - hi, n - lo)

    @property
    def shape(self):
        return self.free.shape

    def periodic(self, face: int) -> tuple[bool, bool, bool]:
        return face_periodic(face, self.periodic_xy)

    def face_groups(self, six: bool = True) -> tuple[tuple[int, ...], ...]:
        """The faces one sweep program runs together: all six where every face frame has the
        same shape and wrapping (a cubic lattice of an open domain: every shared open
        scene's) and ``six``, else the + and − faces of each axis (always alike)."""
        pairs = tuple((FACE_AXES.index((a, 1)), FACE_AXES.index((a, -1))) for a in range(3))
        cubic = len(set(self.shape)) == 1
        alike = len({self.periodic(f) for f in range(len(FACE_AXES))}) == 1
        return (tuple(range(len(FACE_AXES))),) if six and cubic and alike else pairs


def face_periodic(face: int, periodic_xy: bool) -> tuple[bool, bool, bool]:
    """Which of a face sweep's axes (w, u, v) wrap: x and y on a laterally periodic domain."""
    axis, _ = FACE_AXES[face]
    u, v = face_plane_axes(axis)
    per = lambda a: periodic_xy and a in (0, 1)  # noqa: E731
    return per(axis), per(u), per(v)


def check_point_sun(scene) -> None:
    """The sweep's sun is a point: refuse a scene whose sun has an angular radius (the light
    solve's first collision, the shadow rays of the cameras' exact hits and the single
    scattering towards the cameras all use the sun's centre), rather than ignore it."""
    if scene.sun is not None and scene.sun.angular_radius_deg > 0:
        raise SceneError(
            f"sun.angular_radius_deg = {scene.sun.angular_radius_deg:g}: the sweep solver treats "
            f"the sun as a point (hard shadows); set it to 0 (--set sun.angular_radius_deg=0; "
            f"the real sun, 0.27°, blurs a shadow edge over ~1% of its occluder's distance) "
            f"or render with solver \"splat\", which draws the penumbra")


def prepare_sweep(scene, lattice, M: int | None = None, terms: str = "auto",
                  order: int = 0, linear: bool = False, substep: bool = False,
                  shadows: bool = True, records: bool = True) -> SweepGeometry:
    """Host-side preparation of the static geometry (once per scene and lattice); ``order``:
    the δ-M order L of the anisotropic phase (0: isotropic or δ-isotropic); ``linear``: the
    linear-source scheme (``SweepSolver.scheme``); ``shadows``: cast the sun's exact shadow
    rays where the host can (``sun_vis``; not for the once-scattered sweep's geometry, whose
    source comes from the solve's own beam); ``records``: make the native blocked sweep's
    surface records where it will read them (False: a device mesh, whose sweeps, in the face
    frame or XLA's, do not read them)."""
    check_point_sun(scene)
    M = int(M or lattice.M)
    if M > lattice.M:
        raise SceneError(
            f"directions: M = {M} exceeds the lattice's surface shell of {lattice.M} nodes; "
            f"voxelize with M >= {M} so rays cannot jump over a surface"
        )
    dirs = direction_set(M)
    harm = basis(order, M) if order > 0 else None
    nt = np.asarray(lattice.node_type)
    free, surf, solid = nt == FREE, nt == SURFACE, nt == SOLID
    normal = np.asarray(lattice.normal, dtype=np.float64)
    normal = np.where(surf[..., None], normal, 0.0)
    sun_dir = None if scene.sun is None else tuple(float(x) for x in scene.sun.direction)
    sun_cos = np.zeros(nt.shape) if sun_dir is None else np.maximum(normal @ np.array(sun_dir), 0)
    sun_cos = np.where(surf, sun_cos, 0.0)
    periodic_xy = lattice.boundary == "periodic-xy"
    normal32 = normal.astype(np.float32)
    substeps = bool(substep) and M > 1
    # Warm-up for periodic sweep axes: every non-horizontal ray must have entered through z.
    warmup = int(M * lattice.shape[2]) if periodic_xy else 0
    # the native blocked sweep's surface records, made here once (where it will take them: the
    # isotropic step scheme on a CPU; float32's layout, ignored by a float64 solve)
    records = (records and not linear and not substeps and order == 0
               and jax.default_backend() == "cpu" and _native.expected())

    def cosines():
        c = np.zeros(nt.shape)
        c[surf] = cosine_normalization(normal[surf], dirs)
        return c

    def face_arrays(face):  # the face frame's copies, made on the host (no XLA transpose
        axis, sign = FACE_AXES[face]  # compiled per shape)
        u, v = face_plane_axes(axis)
        vec = np.zeros((dirs.D, 3), np.int64)
        vec[:, axis] = sign * M
        vec[:, u], vec[:, v] = dirs.pq[:, 0], dirs.pq[:, 1]
        n_face = np.stack([normal32[..., u], normal32[..., v], sign * normal32[..., axis]], -1)
        out = dict(free=_host_face(free, axis, sign), surf=_host_face(surf, axis, sign),
                   normal=_host_face(n_face, axis, sign),
                   blocked=_host_face(segment_blocking(solid, surf, vec, periodic_xy), axis,
                                      sign))
        if (records and surf.any()
                and _native.records_apply(dirs.D, out["free"].shape)):  # (see ``records``)
            out["records"] = _native.surface_records(out["normal"], out["blocked"],
                                                     out["surf"], dirs.D)
        if substeps:  # the sub-stepped sweep's per-node renormalization (geometry only)
            out["wscale"] = substep_weight_scale(
                out["free"], out["surf"], out["blocked"], dirs.pq, substep_offsets(dirs.pq, M),
                dirs.weights[face], M=M, periodic=face_periodic(face, periodic_xy),
                warmup=warmup, surfaces=bool(surf.any()))
        return out

    # NumPy releases the GIL in its array loops: the faces and the cosine normalization on all
    # cores (fog-balls N = 128, M = 5, 2 cores: 2.7 s → 1.5 s)
    with concurrent.futures.ThreadPoolExecutor(min(7, os.cpu_count() or 1)) as pool:
        # the sun past the shapes from exact shadow rays, where there are shapes and the host
        # casts exactly (not across a periodic domain's sides)
        vis_job = (pool.submit(sun_visibility, scene, nt.shape, lattice.origin, lattice.h,
                               sun_dir)
                   if shadows and shadows_exactly(scene) else None)
        cnorm_job = pool.submit(cosines)
        built = list(pool.map(face_arrays, range(6)))
        recs = tuple(None if "records" not in arrays else
                     {k: jnp.asarray(a) for k, a in arrays.pop("records").items()}
                     for arrays in built)
        faces = [FaceGeometry(**{k: jnp.asarray(a) for k, a in arrays.items()})
                 for arrays in built]
        cnorm = cnorm_job.result()
        vis = None if vis_job is None else vis_job.result()
    f32 = lambda a: jnp.asarray(a, jnp.float32)  # noqa: E731
    material = np.where(np.asarray(lattice.material) >= 0, lattice.material, 0)
    return SweepGeometry(
        faces=tuple(faces),
        consts=tuple(face_consts(dirs, f, None if harm is None else harm.faces, linear,
                                 substep) for f in range(6)),
        sky_frac=f32(np.stack([sky_boundary(dirs, f) for f in range(6)])),
        free=jnp.asarray(free),
        surf=jnp.asarray(surf),
        solid=jnp.asarray(solid),
        density=f32(np.where(solid, 0.0, lattice.density)),
        material=jnp.asarray(material, jnp.int32),
        cnorm=f32(cnorm),
        sun_cos=f32(sun_cos),
        normal=f32(normal),
        h=float(lattice.h),
        origin=tuple(float(x) for x in lattice.origin),
        M=M,
        periodic_xy=periodic_xy,
        sun_dir=sun_dir,
        has_surfaces=bool(surf.any()),
        warmup=warmup,
        terms=choose_terms(scene, lattice, terms=terms),
        optical_size=_optical_size(scene, lattice, solid),
        order=int(order),
        linear=bool(linear),
        substep=substeps,
        sun_cells=None if harm is None or sun_dir is None else _sun_cells(dirs),
        sun_vis=None if vis is None else f32(vis),
        records=recs if any(r is not None for r in recs) else None,
    )


def _sun_cells(dirs):
    vecs, wt = [], []
    for f in range(6):
        vec, w = cell_samples(dirs, f)
        vecs.append(vec)
        wt.append(w)
    return jnp.asarray(np.stack(vecs), jnp.float32), jnp.asarray(np.stack(wt), jnp.float32)


def _host_face(x: np.ndarray, axis: int, sign: int) -> np.ndarray:
    """``to_face`` in NumPy: a contiguous (nw, nu, nv, ...) copy of a host array."""
    u, v = face_plane_axes(axis)
    y = np.moveaxis(x, (axis, u, v), (0, 1, 2))
    return np.ascontiguousarray(y[::-1] if sign < 0 else y)


def _optical_size(scene, lattice, solid) -> float:
    """``diffusive_size`` of the scene's fog on ``lattice`` (its densest non-solid node, the
    lattice's largest extent): the ``precondition="auto"`` rule."""
    if scene.fog is None:
        return 0.0
    return diffusive_size(scene.fog, lattice.peak_density, max(lattice.shape) * lattice.h)


def step_depth(scattering, absorption, g, order: int, density, h: float, M: int) -> float:
    """σ_t·h·M of one lattice step through the densest node of ``density``, σ_t = ζ(1 − f) + γ
    δ-scaled at ``order`` (f = g for order 0): what ``ThickStepWarning`` and scheme="auto"
    judge.  The values must be concrete (``float`` raises on traced ones)."""
    f = float(delta_m(float(g), order)[0])
    ext = float(scattering) * (1.0 - f) + float(absorption)
    return ext * float(np.asarray(density).max(initial=0.0)) * h * M


def optical_size(fog, density_max: float, extent: float) -> float:
    """σ_t (δ-scaled: ζ(1 − g) + γ, at ``density_max``) × ``extent``: how many mean free paths
    across ``fog`` is (its values as given)."""
    ext = fog.scattering * (1.0 - (fog.g or 0.0)) + fog.absorption
    return float(max(ext, 0.0) * max(density_max, 0.0) * extent)


def fog_extent(scene) -> float:
    """The longest side of the box the fog fills: its ``region`` within the domain, else the
    domain."""
    lo = np.asarray(scene.domain.min, np.float64)
    hi = np.asarray(scene.domain.max, np.float64)
    if scene.fog is not None and scene.fog.region is not None:
        lo = np.maximum(lo, np.asarray(scene.fog.region[0], np.float64))
        hi = np.minimum(hi, np.asarray(scene.fog.region[1], np.float64))
    return float(np.max(np.maximum(hi - lo, 0.0)))


def diffusive_size(fog, density_max: float, extent: float) -> float:
    """How many mean free paths light diffuses through in ``fog`` (its values as given): the
    lesser of ``optical_size`` and the diffusion length 1/√(3(1 − a)) in mean free paths (a:
    single-scattering albedo after δ-scaling)."""
    zeta = fog.scattering * (1.0 - (fog.g or 0.0))
    ext = zeta + fog.absorption
    if ext <= 0 or density_max <= 0:
        return 0.0
    a = zeta / ext
    size = optical_size(fog, density_max, extent)
    return float(min(size, np.inf if a >= 1 else 1.0 / math.sqrt(3.0 * (1.0 - a))))


class _Problem(eqx.Module):
    """Everything one Jacobi iteration needs: static geometry + arrays derived from Params."""

    geom: SweepGeometry
    tau_half: tuple[jax.Array, ...]  # per face, in the face frame: σ̄_t·h/2 (per unit |L|), 0 in solids
    sigma_t: jax.Array  # (ζ'+γ)·density per node
    ssa: jax.Array  # single-scattering albedo ζ'/(ζ'+γ)
    sun_fluence: jax.Array  # F·T̄_sun, T averaged over the node's segment of the beam
    sky_fluence: jax.Array  # uncollided sky Σ_k w_k sky T_k (0 if the sky goes through the lattice)
    rho: jax.Array  # albedo per node (SURFACE)
    emission: jax.Array  # emission per node (SURFACE)
    direct: jax.Array  # direct (uncollided) sun and sky irradiance on SURFACE nodes
    sky_direct: jax.Array  # its sky part (what the camera's exact hits interpolate with Λ's)
    sky: jax.Array  # sky radiance entering the lattice directions (0 with first-collision sky)
    max_iterations: int = eqx.field(static=True)
    tol: float = eqx.field(static=True)
    progress: AbstractProgressMeter = eqx.field(static=True, default_factory=NoProgress)
    mesh_shape: tuple[int, int, int] = eqx.field(static=True, default=(1, 1, 1))  # _sweep_all
    method: str = eqx.field(static=True, default="jacobi")  # "jacobi" | "gmres" (resolved)
    restart: int = eqx.field(static=True, default=30)
    precondition: str = eqx.field(static=True, default="none")  # "none" | "diffusion" (resolved)
    kernel: str = eqx.field(static=True, default="loop")  # "loop" | "batched" (resolved)
    recompute: bool = eqx.field(static=True, default=False)  # SweepSolver.sweep_residuals
    fog_mask: jax.Array | None = None  # the terms restrict the fog work: nodes whose Λ is kept
    phase_coef: jax.Array | None = None  # (K,) δ-M Legendre coefficient g'_l of each moment
    sky_moments: jax.Array | None = None  # (nx, ny, nz, K) uncollided sky Σ_k w_k T_k Ỹ(ω_k)
    sun_albedo: jax.Array | None = None  # ζ/(ζ' + γ): the first-collision sun's albedo
    sun_phase: tuple[jax.Array, ...] | None = None  # per face (D,): its cell-averaged phase
    # (kept, c, width): the share of the sun's first collision its beam keeps, and the part
    # of the phase it keeps, c·K (``_cell_phase``, ``LightField.sun_peak``)
    sun_peak: jax.Array | None = None
    # linear scheme: h∇ of the uncollided sun's (unless it has its own channel) and the
    # first-collision sky's fluence along their beams, (nx, ny, nz, 3)
    sun_slope: jax.Array | None = None
    sky_slope: jax.Array | None = None
    # the uncollided beams themselves (what the cameras and ``LightField`` get), where the
    # fields above are their box-filtered deposits (``_deposit_average``)
    sun_beam: jax.Array | None = None
    sky_beam: jax.Array | None = None
    sky_moments_beam: jax.Array | None = None
    # a guess of the light state (Λ, E) to start the iteration from (``SweepSolver.solve``'s
    # ``init``; None: from zero)
    init: tuple[jax.Array, jax.Array] | None = None
    # the sun's once-scattered light swept on the finer direction set of ``geom.once``
    # (``SweepSolver._once_scattered``): its fluence Λ₁, its anisotropic source per unit ζ'
    # in this direction set's basis (what ``phase_coef``·moments is for the state's light,
    # (nx, ny, nz, K)) and its irradiance on surfaces; a fixed part of the light, which
    # ``_sources`` adds to the state's (None: the sun's first collision is in the state's
    # own sweeps)
    once_fluence: jax.Array | None = None
    once_source: jax.Array | None = None
    once_irradiance: jax.Array | None = None


def _report(meter: AbstractProgressMeter):
    """A per-iteration progress callback for ``meter``, or None when it shows nothing."""
    if isinstance(meter, NoProgress):
        return None

    def report(k, change, err):
        meter.update(int(k), change=float(change), estimated_error=float(err))

    return report


def _mask(cond, x, value=0.0):
    """``where(cond, value, x)`` with ``cond`` (nx, ny, nz) broadcast over x's channels."""
    return jnp.where(cond[..., None] if x.ndim > cond.ndim else cond, value, x)


def _sources(state, pb: _Problem, first_collision: bool | None = None):
    """(Q, B): the step source radiance at fog nodes — (nx, ny, nz), or with an anisotropic
    phase or the linear scheme (nx, ny, nz, 1 + K [+ 1] [+ 3]): the isotropic part, then each
    moment's ζ'/σ_t'·g'_l·m_k (the collided light's and the uncollided sky's moments), then
    with a sun the first-collision sun's ζ/σ_t'·F·T̄, so that direction d's source is
    Q_0 + Σ_k Ỹ_k(d) Q_k + P_d Q_sun (P_d: the exact phase averaged over d's cell), then with
    the linear scheme the isotropic source's slope h∇Q (``_source_slope``) — and the
    radiosity B of surface nodes.  With the sun's once-scattered light swept apart
    (``once_*``, ``SweepSolver.once_M``) its fluence, source and irradiance join the state's,
    and the sun's channel is 0 unless ``first_collision`` (``source_field``'s whole source)."""
    lam, irr = state
    g = pb.geom
    # the sun's once-scattered light swept apart (``once_*``): the state holds the rest, and
    # the sun's first collision is no source of the state's sweeps (``first_collision``
    # None); ``source_field`` asks for it (True) with the once-scattered light in the state
    once = pb.once_fluence is not None
    first_collision = not once if first_collision is None else first_collision
    if once:
        irr = irr + pb.once_irradiance
    if not (g.channels or g.linear):
        q = jnp.where(g.solid, 0.0, pb.ssa * (lam + pb.sun_fluence + pb.sky_fluence) / FOUR_PI)
    else:
        lam0 = lam[..., 0] if g.channels else lam
        if once:
            lam0 = lam0 + pb.once_fluence
        sun_iso = pb.sun_fluence if pb.sun_phase is None else 0.0
        q0 = pb.ssa * (lam0 + sun_iso + pb.sky_fluence) / FOUR_PI
        parts = [q0[..., None]]
        if g.channels:
            mom = lam[..., 1:] if pb.sky_moments is None else lam[..., 1:] + pb.sky_moments
            aniso = pb.phase_coef * mom
            if once:
                aniso = aniso + pb.once_source
            parts.append(pb.ssa[..., None] * aniso)
        if pb.sun_phase is not None:
            sun_q = pb.sun_albedo * pb.sun_fluence
            parts.append((sun_q if first_collision else jnp.zeros_like(sun_q))[..., None])
        if g.linear:
            parts.append(_source_slope(lam0, pb))
        q = _mask(g.solid, jnp.concatenate(parts, axis=-1))
    b = jnp.where(g.surf, pb.emission + pb.rho / math.pi * (g.cnorm * irr + pb.direct), 0.0)
    return q, b


def _source_slope(lam, pb: _Problem):
    """h∇Q of the isotropic source (nx, ny, nz, 3) for the linear scheme: ζ'/σ_t'/4π times
    ``_fluence_slope`` (with the uncollided sun, unless it has its own channel)."""
    return pb.ssa * _fluence_slope(lam, pb, sun=pb.sun_phase is None) / FOUR_PI


def _fluence_slope(lam, pb: _Problem, sun: bool):
    """h∇ of the fluence that feeds the isotropic source, Λ + the uncollided sky [+ sun]
    (nx, ny, nz, 3): Λ by central differences between fog nodes (one-sided where a neighbour
    has no fog, 0 where neither has), the uncollided beams by their exact slopes along the
    beams (``sun_slope``, ``sky_slope``: in a thick node a beam's power is spent near its
    entry, which no difference between nodes resolves).  Linear in Λ (as the Krylov solve
    needs)."""
    g = pb.geom
    fog = (pb.sigma_t > 0) & ~g.solid  # fog of their own (not reached by the box filter only)
    comps = []
    for axis in range(3):
        periodic = g.periodic_xy and axis < 2
        nxt, f_nxt = neighbour(lam, axis, 1, periodic), neighbour(fog, axis, 1, periodic)
        prv, f_prv = neighbour(lam, axis, -1, periodic), neighbour(fog, axis, -1, periodic)
        d = jnp.where(f_nxt & f_prv, 0.5 * (nxt - prv),
                      jnp.where(f_nxt, nxt - lam, jnp.where(f_prv, lam - prv, 0.0)))
        comps.append(jnp.where(fog, d, 0.0))
    grad = jnp.stack(comps, axis=-1)
    first, mean = [], 0.0
    if pb.sky_slope is not None:
        first.append(pb.sky_slope)
        mean = mean + pb.sky_fluence
    if sun and pb.sun_slope is not None:
        first.append(pb.sun_slope)
        mean = mean + pb.sun_fluence
    if first:
        # the first collision's slope, limited so that its source stays ≥ 0 at both ends of
        # every segment (|L·G| ≤ M·‖G‖₁ ≤ 2·mean): the linear fit of e^(−u) over a node T ≫ 1
        # mean free paths deep (same mean and first moment) runs from 4/T to −2/T.  Measured
        # on collimated slabs at τ = 64, N = 32: R +9.5 → +5.1%, T −17 → −7% (a = 0.9, 0.99).
        # A fixed source, not part of the linear operator: the limiter costs no linearity.
        # Where the beams are spent (norm1 below √tiny of the dtype, 1e-19 in float32, as
        # deep in a thick cloud) the ratio's derivative would divide by norm1², which
        # underflows to 0: a NaN gradient (float32, τ = 100 at N = 16: every d/dζ was NaN).
        # There the slope is negligible and is dropped.
        first = sum(first)
        norm1 = g.M * jnp.sum(jnp.abs(first), axis=-1)
        over = norm1 > 2.0 * mean
        safe = norm1 > math.sqrt(float(jnp.finfo(norm1.dtype).tiny))
        ratio = 2.0 * mean / jnp.where(over & safe, norm1, 1.0)
        scale = jnp.where(over, jnp.where(safe, ratio, 0.0), 1.0)
        grad = grad + scale[..., None] * first
    return grad


def zero_state(geom: SweepGeometry, dtype):
    """The light state (Λ [with the moments as channels], E) of ``geom`` at zero: where the
    iteration starts without a guess (``SweepModel.zero_light_state``)."""
    return jnp.zeros(geom.fluence_shape, dtype), jnp.zeros(geom.shape, dtype)


def _zero_state(pb: _Problem):
    return zero_state(pb.geom, pb.sigma_t.dtype)


def _start_state(pb: _Problem):
    """Where the iteration starts: the problem's ``init`` guess, or zero."""
    return _zero_state(pb) if pb.init is None else pb.init


def segment_depth(sigma_t, M: int, axis: int, periodic: bool):
    """σ_t averaged over the M planes a node's two half-segments span along ``axis``.

    A lattice ray jumps M planes per step, so sampling σ_t only at the nodes would resolve a fog
    edge to M planes, differently for each of the M interleaved plane chains.  The box filter
    [w − M/2, w + M/2] (end cells half-weighted when M is even) gives every chain the same
    optical depth.  Open boundaries count as vacuum.
    """
    half = M // 2
    offsets = range(-half, half + 1)
    wts = [0.5 if (M % 2 == 0 and abs(o) == half) else 1.0 for o in offsets]
    n = sigma_t.shape[axis]
    widths = [(0, 0)] * sigma_t.ndim
    widths[axis] = (half, half)
    sp = jnp.pad(sigma_t, widths, mode="wrap" if periodic else "constant")
    acc = 0.0
    for o, wt in zip(offsets, wts):
        acc = acc + wt * jax.lax.slice_in_dim(sp, half + o, half + o + n, axis=axis)
    return acc / M


def _deposit_average(x, sigma_t, sigma_box, solid, M: int, periodic_xy: bool):
    """The uncollided beam ``x`` (nx, ny, nz[, K]) as the lattice's first-collision source
    must see it: Σ_a box_a(σ_t·x) / Σ_a box_a(σ_t), the box filters of ``segment_depth`` along
    the three axes; ``sigma_box`` is the denominator, Σ_a box_a(σ_t), which the problem's
    segment depths already hold.

    A node's beams remove light at the box-filtered σ̄ of each axis, and it re-emits what they
    remove; the uncollided sun and sky lose light at each node's own σ_t.  With the beam's own
    fluence as the source a node re-emits σ̄·x where the beam lost σ_t·x: where a thick step
    meets the sunlit face of a fog, the node outside it (σ_t = 0, σ̄ > 0) re-emitted the full
    sun and the first node inside most of it, and a sunlit slab of τ = 64 over 32 nodes
    returned 19% more light than it received (docs/validation.md).  The filters are a
    partition of unity along each axis, so with this average Σ_nodes σ̄·x equals the beam's
    own loss Σ_nodes σ_t·x: the first collision scatters what the beam loses, at every step
    optical depth (the three axes weigh alike: each face's directions carry 4π/6).  In
    uniform fog it is the beam's fluence unchanged."""
    def box(a, axis):
        return segment_depth(a, M, axis, periodic_xy and axis < 2)

    extra = x.ndim > sigma_t.ndim  # moments: (nx, ny, nz, K)
    sx = sigma_t[..., None] * x if extra else sigma_t * x
    num = sum(box(sx, axis) for axis in range(3))
    den = sigma_box[..., None] if extra else sigma_box
    avg = jnp.where(den > 0, num / jnp.where(den > 0, den, 1.0), x)
    return _mask(solid, avg)


def _sweep_all(q, b, pb: _Problem, return_exits: bool = False):
    g = pb.geom
    lam = jnp.zeros(g.fluence_shape, q.dtype)
    irr = jnp.zeros(g.shape, q.dtype)
    exits = [None] * len(FACE_AXES)

    def face_args(f):
        axis, sign = FACE_AXES[f]
        return (to_face(q, axis, sign), to_face(b, axis, sign), pb.tau_half[f],
                pb.sky * g.sky_frac[f], g.faces[f], _face_consts(pb, f))

    pl = g.terms
    kw = dict(M=g.M, warmup=g.warmup, surfaces=g.has_surfaces, kernel=pb.kernel,
              recompute=pb.recompute,
              attenuate=True if pl is None else pl.fog,
              fluence=True if pl is None else pl.volume_source)
    nf, npu, npv = pb.mesh_shape
    one = nf * npu * npv == 1
    mesh = None if one else _device_mesh(pb.mesh_shape)
    # Faces with the same shapes are independent sweeps of one program.  On one device
    # ``lax.map`` runs a group one face after the other (one sweep program to compile on a
    # cubic lattice, three otherwise, not six; the fog step over the union of the faces' fog
    # planes).  On a mesh with a "face" axis of 2 each half runs one face of an axis's pair: XLA
    # on a CPU runs one fused loop at a time per device, so this is what puts a second core to
    # work (no vol_range there); without one, each face alone.  Where the native CPU kernel
    # serves every face (one device, the loop kernel, not sub-stepped), each face is its own
    # custom call that reads q, b and writes Λ, E in the world frame: no face-frame copies of
    # the sources, no transposes back (on cloud-plane's 20 source and 16 fluence channels they
    # took about half as long as the sweeps), nothing large for XLA to compile.  The
    # sub-stepped loop runs an axis's ± pair together (three programs): it does the fog step
    # only over its group's fog slabs, and on a cubic lattice the six faces' union of them is
    # most of the planes (cloud-plane, N = 32: a light solve 11.3 s in pairs against 13.3-14.5
    # s in one group of six; the first call 22 s with the loop's one-scan cond, 27-31 s before
    # the restriction).  Where the native kernel serves the sub-stepped scheme each face is its
    # own custom call (face frame) over its own fog slabs: no stacked copies of a pair's
    # sources and geometry (fog-balls, N = 64, M = 3: an iteration 0.37 s in pairs, 0.20 s
    # alone).
    groups = g.face_groups(six=one and not (g.substep and pb.kernel == "loop"))
    native_sub = one and all(substep_native_applies(pb.kernel, g.consts[f], q.dtype)
                             for group in groups for f in group)
    if not (one or nf == 2) or native_sub:
        groups = tuple((f,) for group in groups for f in group)
    world = one and all(world_native_applies(pb.kernel, g.consts[f], q.dtype)
                        for group in groups for f in group)
    for group in groups:
        periodic = g.periodic(group[0])
        if world:  # the native kernel, each face reading q, b and writing Λ, E in the world frame
            for f in group:
                axis, sign = FACE_AXES[f]
                lf, ef, ex = sweep_face_world(
                    q, b, pb.tau_half[f], pb.sky * g.sky_frac[f], g.faces[f], _face_consts(pb, f),
                    axis=axis, sign=sign, periodic=periodic, vol_range=g.vol_range(f),
                    records=None if g.records is None else g.records[f], exits=return_exits,
                    **{k: v for k, v in kw.items() if k != "kernel"})
                lam, irr, exits[f] = lam + lf, irr + ef, ex
            continue
        if native_sub:
            lf, ef, ex = (x[None] for x in sweep_face(
                *face_args(group[0]), periodic=periodic, vol_range=g.vol_range(group[0]), **kw))
        elif one:
            sweep = functools.partial(
                sweep_face, periodic=periodic,
                vol_range=functools.reduce(_union, (g.vol_range(f) for f in group)), **kw)
            lf, ef, ex = jax.lax.map(lambda a: sweep(*a), _face_stack(face_args, group))
        elif nf == 2:  # an axis's ± pair on the mesh's two halves
            lf, ef, ex = sweep_face_mesh(_face_stack(face_args, group), mesh, stacked=True,
                                         periodic=periodic, **kw)
        else:
            lf, ef, ex = (x[None] for x in sweep_face_mesh(face_args(group[0]), mesh,
                                                           stacked=False, periodic=periodic,
                                                           **kw))
        for i, f in enumerate(group):
            axis, sign = FACE_AXES[f]
            lam = lam + from_face(lf[i], axis, sign)
            irr = irr + from_face(ef[i], axis, sign)
            exits[f] = ex[i]
    lam = _mask(g.solid, lam)
    if pb.fog_mask is not None and one:
        # Λ only where some segment has fog (τ > 0): the restricted sweeps skip the rest, and
        # it is never used there (the source is multiplied by τ; the camera by the density).
        # On a device mesh the sweeps are not restricted and the mask is applied to the result
        # only (``solve``): inside the operator it stalled the sharded adjoint's GMRES (seen on
        # fog-balls, mesh (1, 2, 2): the gradient off by 10-40x while the JVP was right).
        lam = _mask(~pb.fog_mask, lam)
    irr = jnp.where(g.surf, irr, 0.0)
    return ((lam, irr), exits) if return_exits else (lam, irr)


def _face_consts(pb: _Problem, f: int) -> SweepConsts:
    """Face ``f``'s direction constants, with the problem's first-collision sun phase where it
    has one (it depends on the traced phase parameters)."""
    consts = pb.geom.consts[f]
    if pb.sun_phase is not None:
        consts = dataclasses.replace(consts, sun_phase=pb.sun_phase[f])
    return consts


def _face_stack(face_args, faces: tuple[int, ...]):
    """The arguments of ``faces`` (same shapes) stacked on a leading axis, in that order, for
    one program over them (``lax.map`` on one device, ``shard_map`` over a mesh's "face"
    axis)."""
    return jax.tree.map(lambda *xs: jnp.stack(xs), *(face_args(f) for f in faces))


def _union(a: tuple[int, int] | None, b: tuple[int, int] | None) -> tuple[int, int] | None:
    """The plane range [lo, hi) that covers both ``a`` and ``b`` (None: every plane)."""
    if a is None or b is None:
        return None
    return min(a[0], b[0]), max(a[1], b[1])


def mesh_shape_for(devices: int) -> tuple[int, int, int]:
    """The default (faces, u, v) layout of ``devices`` devices: the ± faces of an axis on two
    halves when the count is even (no communication), the rest splitting the sweep plane as
    squarely as possible (halo exchange of M rows/columns per slab)."""
    nf = 2 if devices % 2 == 0 else 1
    rest = devices // nf
    nu = max(d for d in range(1, int(math.isqrt(rest)) + 1) if rest % d == 0)
    return (nf, rest // nu, nu)


def cpu_mesh_warning(devices: int) -> str:
    """What a device mesh costs on a CPU, where one device's native kernel already runs on every
    core: the mesh's devices share those cores (each its face's sweep, in the face frame, with
    XLA's copies of the sources and fields per face; a plane split over "u"/"v" takes XLA's
    loop), and each device holds its own copy of the light's fields and GMRES's vectors
    (fog-balls, this project's 2-core CPU, stop 74, one Jacobi iteration: 2 host devices
    1.24-1.69x one device's time at N = 64-128, M = 3-5; a render's peak at N = 128, M = 5
    6.0 GB against 2.9 GB)."""
    return (f"devices={devices} on a CPU shares its cores among {devices} host devices, each "
            "with its own copy of the light: slower and larger than one device, whose native "
            "kernel already uses every core (fog-balls: 1.2-1.7x the time per iteration, "
            "2x the memory at N = 128, M = 5); leave devices at 1 on a CPU (several devices "
            "pay off on several GPUs)")


def _device_mesh(shape: tuple[int, int, int]) -> jax.sharding.Mesh:
    """A ("face", "u", "v") mesh of the first prod(shape) devices of the default backend."""
    n = int(np.prod(shape))
    devs = jax.devices()
    if len(devs) < n:
        raise SolverError(
            f"SweepSolver(devices={n}) needs {n} JAX devices, found {len(devs)} "
            f"({devs[0].platform}); on a CPU set "
            f"XLA_FLAGS=--xla_force_host_platform_device_count={n} before JAX is imported"
        )
    return jax.sharding.Mesh(np.array(devs[:n]).reshape(shape), ("face", "u", "v"))


def _jacobi(state, pb: _Problem):
    q, b = _sources(state, pb)
    return _sweep_all(q, b, pb)


def _rel_change(new, old):
    num = sum(jnp.max(jnp.abs(a - b)) for a, b in zip(new, old))
    den = sum(jnp.max(jnp.abs(a)) for a in new)
    return safe_div(num, den)


def _iterate(pb: _Problem):
    """Forward Jacobi iteration; stops when the estimated remaining error < tol.

    The remaining error after a step with change Δ and contraction ρ = Δ_k/Δ_{k-1} is about
    Δ·ρ/(1-ρ) (geometric tail); stopping on Δ alone stops too early when ρ is near 1.
    """
    dt = pb.sigma_t.dtype
    hist0 = jnp.full((pb.max_iterations,), jnp.nan, dt)

    def cond(c):
        _, k, _, err, _ = c
        return (k < pb.max_iterations) & ((k < 2) | (err > pb.tol))

    def body(c):
        state, k, prev, _, hist = c
        new = _jacobi(state, pb)
        d = _rel_change(new, state)
        rho = jnp.clip(safe_div(d, prev), 0.0, 0.999999)
        err = jnp.where(k < 1, jnp.inf, d * rho / (1.0 - rho))
        if (report := _report(pb.progress)) is not None:
            jax.debug.callback(report, k + 1, d, err)
        return new, k + 1, d, err, hist.at[k].set(d)

    init = (_start_state(pb), jnp.asarray(0), jnp.asarray(jnp.inf, dt),
            jnp.asarray(jnp.inf, dt), hist0)
    state, k, _, err, hist = jax.lax.while_loop(cond, body, init)
    return state, (hist, k, err)


_SOURCE_FIELDS = ("sun_fluence", "sky_fluence", "emission", "direct", "sky", "sky_moments",
                  "sun_slope", "sky_slope", "once_fluence", "once_source", "once_irradiance")


def _with_sources(pb: _Problem, on) -> _Problem:
    """The same problem with its sources (emission, sun, sky) kept where ``on`` (a traced bool)
    and zeroed elsewhere: without them the Jacobi map is the linear one-bounce operator K of
    x = Kx + b."""
    fields = [f for f in _SOURCE_FIELDS if getattr(pb, f) is not None]
    return eqx.tree_at(lambda p: tuple(getattr(p, f) for f in fields), pb,
                       tuple(jnp.where(on, getattr(pb, f), 0.0) for f in fields))


def _iterate_gmres(pb: _Problem):
    """(I − K)x = b by restarted GMRES (``_krylov.gmres``), b = one Jacobi step from zero.

    The state vector holds Λ, and E only where the scene has surfaces; every application of K
    is one Jacobi iteration's six sweeps, so ``iterations`` counts the same work as Jacobi's.
    """
    dt = pb.sigma_t.dtype
    shape = pb.geom.shape
    zero_lam, zero = _zero_state(pb)
    lam_shape = zero_lam.shape
    n = math.prod(lam_shape)
    surfaces = pb.geom.has_surfaces

    def flat(state):
        lam, irr = state
        return jnp.concatenate([lam.ravel(), irr.ravel()]) if surfaces else lam.ravel()

    def unflat(v):
        return (v[:n].reshape(lam_shape), v[n:].reshape(shape) if surfaces else zero)

    def apply_k(v, with_sources):
        return flat(_jacobi(unflat(v), _with_sources(pb, with_sources)))

    precondition = None
    pre = _preconditioner(pb)
    if pre is not None:
        def precondition(v):
            lam, _ = pre.apply((v[:n].reshape(lam_shape), zero))
            return jnp.concatenate([lam.ravel(), v[n:]]) if surfaces else lam.ravel()

    size = n + (math.prod(shape) if surfaces else 0)
    x, hist, k, err = gmres(apply_k, (size,), dt, restart=pb.restart,
                            max_matvecs=pb.max_iterations, tol=pb.tol,
                            progress=_report(pb.progress), precondition=precondition,
                            x0=None if pb.init is None else flat(pb.init),
                            native=math.prod(pb.mesh_shape) == 1)
    # the fixed point as GMRES found it; ``_non_negative`` projects it after the implicit
    # function, so that the implicit derivative is taken at the fixed point itself
    return unflat(x), (hist, k, err)


def _preconditioner(pb: _Problem) -> DiffusionPreconditioner | None:
    """The light solve's GMRES preconditioner (``SweepSolver.precondition``, resolved), which
    the tangent and adjoint solves of its gradient use too (transposed for the adjoint), or
    None."""
    if pb.precondition != "diffusion" or pb.method != "gmres":
        return None
    # the transport-corrected diffusion coefficient: σ_t' − σ_s'·g'_1
    mu_bar = 0.0 if pb.geom.order == 0 else pb.phase_coef[0]
    return DiffusionPreconditioner(pb.sigma_t, pb.ssa, pb.geom.solid, mu_bar, h=pb.geom.h,
                                   periodic_xy=pb.geom.periodic_xy, M=pb.geom.M,
                                   channels=pb.geom.channels)


def _single_pass(pb: _Problem):
    """Nothing scatters or reflects (the terms): K = 0 and one pass is the solution."""
    dt = pb.sigma_t.dtype
    hist = jnp.full((pb.max_iterations,), jnp.nan, dt).at[0].set(1.0)
    return _jacobi(_zero_state(pb), pb), (hist, jnp.asarray(1), jnp.asarray(0.0, dt))


def _solve_fixed_point(pb: _Problem):
    if pb.geom.terms is not None and not pb.geom.terms.iterate:
        return _single_pass(pb)
    return _iterate_gmres(pb) if pb.method == "gmres" else _iterate(pb)


def _non_negative(root, channels: bool):
    """The light state projected onto Λ ≥ 0, E ≥ 0 (the moments of an anisotropic phase have
    either sign).  GMRES's solution can dip below 0 by its residual, and the linear scheme's
    own fixed point where a lattice step spans many mean free paths (issue 14's cube at N = 8,
    ζ = 100, ~25 mean free paths per step: Λ down to −11% of its peak at 118 of 504 fog nodes
    at stop 40, none since the first collision's slope is limited; a slab τ = 256 over 8
    nodes at M = 2, −4.5%; the step scheme's update is positive).  How far it dipped is the
    light's ``dip`` (``_dip``), and ``render`` warns above 1% of the peak.  Applied to the
    implicit function's output, not inside its solve:
    the projected state is not a fixed point, and differentiating it as one gave gradients
    0.5% from finite differences there (the derivative of the projection is 0 where it
    clips)."""
    lam, irr = root
    return on_fluence(lambda a: jnp.maximum(a, 0.0), lam, channels), jnp.maximum(irr, 0.0)


def _dip(lam, fog_mask):
    """−min(Λ)/max(Λ) before the clip of ``_non_negative`` (0 where Λ ≥ 0), over the fog."""
    lam = jax.lax.stop_gradient(lam if fog_mask is None else jnp.where(fog_mask, lam, 0.0))
    peak = jnp.max(lam)
    return jnp.where(peak > 0, jnp.maximum(-jnp.min(lam), 0.0) / jnp.where(peak > 0, peak, 1.0),
                     0.0)


def _rewrite(root, inputs):
    new = _jacobi(root, inputs)
    return jax.tree.map(lambda a, b: a - b, root, new)


#: how a tangent solve applies I − K (``SweepSolver.tangents``)
TANGENTS = ("matrix-free", "linearised")
#: how a gradient's adjoint solve applies (I − K)ᵀ (``SweepSolver.adjoint``)
ADJOINTS = ("auto", "transposed", "linearised")
#: what a linearised sweep keeps (``SweepSolver.sweep_residuals``)
SWEEP_RESIDUALS = ("auto", "keep", "recompute")
#: sweep_residuals="auto" recomputes where the kept residuals would exceed this
#: (``difffog._cost.linearised_sweep_bytes``)
RECOMPUTE_ABOVE_BYTES = 2**30


def sweep_residuals_for(setting: str, nodes: int, M: int, linear: bool, K: int,
                        substep: bool = False) -> str:
    """What ``SweepSolver.sweep_residuals`` = ``setting`` stands for on a lattice of ``nodes``
    nodes with half-width M, the linear scheme or not and K moments ("auto": "recompute" where
    the kept residuals of one linearised Jacobi step would take more than
    ``RECOMPUTE_ABOVE_BYTES``)."""
    if setting != "auto":
        return setting
    from ..._cost import linearised_sweep_bytes

    kept = linearised_sweep_bytes(nodes, M, linear, K, "keep", substep)
    return "recompute" if kept > RECOMPUTE_ABOVE_BYTES else "keep"


def _rewrite_linear(v, inputs):
    """∂``_rewrite``/∂root·v = (I − K)v: one Jacobi step with the sources zeroed (``_rewrite``
    is affine in the root, as the forward GMRES relies on too)."""
    new = _jacobi(v, _with_sources(inputs, False))
    return jax.tree.map(lambda a, b: a - b, v, new)


def _rewrite_linear_transposed(v, inputs):
    """(∂``_rewrite``/∂root)ᵀ·v = (I − K)ᵀv with hand-written transposed face sweeps
    (``_kernel.sweep_face_transposed``): a gradient's adjoint product without linearising the
    sweep (``transposable`` says where it applies)."""
    new = _jacobi_transposed(v, _with_sources(inputs, False))
    return jax.tree.map(lambda a, b: a - b, v, new)


def transposable(pb: "_Problem") -> bool:
    """Whether ``_rewrite_linear_transposed`` serves ``pb``: the step or sub-stepped scheme (not
    the linear-source scheme's slopes) on one device."""
    g = pb.geom
    return not g.linear and int(np.prod(pb.mesh_shape)) == 1


def _jacobi_transposed(v, pb: "_Problem"):
    """Kᵀv for the Jacobi map K = ``_sweep_all`` ∘ ``_sources`` of ``pb`` with its sources
    zeroed (linear in the state): the masks ``_sweep_all`` applies, each face's transposed
    sweep (from_face's transpose is to_face), then ``_sources``' transpose (pointwise, by
    ``jax.vjp``)."""
    g = pb.geom
    lam_bar, irr_bar = v
    lam_bar = _mask(g.solid, lam_bar)
    if pb.fog_mask is not None:
        lam_bar = _mask(~pb.fog_mask, lam_bar)
    irr_bar = jnp.where(g.surf, irr_bar, 0.0)
    zero = _zero_state(pb)
    (q_sd, b_sd), vjp = jax.vjp(lambda s: _sources(s, pb), zero)
    nq = q_sd.shape[-1] if q_sd.ndim == 4 else 0
    pl = g.terms
    fluence = True if pl is None else pl.volume_source
    q_bar = jnp.zeros(q_sd.shape, q_sd.dtype)
    b_bar = jnp.zeros(b_sd.shape, b_sd.dtype)

    def face_args(f):
        axis, sign = FACE_AXES[f]
        return (to_face(lam_bar, axis, sign), to_face(irr_bar, axis, sign), pb.tau_half[f],
                g.faces[f], _face_consts(pb, f))

    # faces alike in one program, as in ``_sweep_all`` (the sub-stepped scheme's ± pairs: its
    # transpose, like its loop, moves the rays only outside the group's fog slabs)
    for group in g.face_groups(six=not g.substep):
        vol_range = (functools.reduce(_union, (g.vol_range(f) for f in group)) if g.substep
                     else None)
        sweep = functools.partial(sweep_face_transposed, M=g.M, periodic=g.periodic(group[0]),
                                  warmup=g.warmup, surfaces=g.has_surfaces, fluence=fluence,
                                  q_channels=nq, vol_range=vol_range,
                                  attenuate=True if pl is None else pl.fog)
        qf, bf = jax.lax.map(lambda a: sweep(*a), _face_stack(face_args, group))
        for i, f in enumerate(group):
            axis, sign = FACE_AXES[f]
            q_bar = q_bar + from_face(qf[i], axis, sign)
            b_bar = b_bar + from_face(bf[i], axis, sign)
    return vjp((q_bar, b_bar))[0]


class SweepSolver(eqx.Module):
    """The sweep's light solve: Langer–Breton–Zucker coordinate evolution on the lattice
    (six face sweeps = one bounce), iterated to its fixed point by GMRES or Jacobi and
    differentiated implicitly.  A frozen configuration (every field static); the work is in
    :meth:`prepare` (host, once per lattice) and :meth:`solve` (JAX, per parameter set).

    M: direction half-width: (2M+1)² integer directions per cube face; the lattice's surface
        shell must be at least M nodes thick.
    max_iterations: cap on applications of the one-bounce operator K (a Jacobi iteration or a
        GMRES step: six sweeps each).
    tol: stop when the estimated remaining relative error (max norm over Λ and E) is below
        it; 0 runs exactly ``max_iterations`` (and counts as converged).
    adjoint_rtol: relative tolerance of the tangent/adjoint GMRES solves (gradients).
    throw: what an unconverged tangent/adjoint solve does: raise at run time (True) or warn
        with :class:`difffog.AdjointWarning` (False).  (The forward solve's own result is in
        ``LightField.result``; ``model.images(throw=...)`` decides about it.)
    sky_quadrature: (n_μ, n_φ) directions of the first-collision sky (Gauss–Legendre in μ ×
        uniform φ), swept instead of the lattice's, which resolve near-grazing sky light
        poorly; (0, 0) sends the sky through the lattice.  None (default): (8, 16) for open
        domains, (0, 0) for laterally periodic ones, where horizontal lattice rays never leave
        and the missing horizontal sky offsets that (thin slabs: R within 0.4-5.6% at M = 2
        against 4-10% with the first-collision sky).
    progress: a progress meter (``difffog.TextProgress()``; True for one) updated at every
        iteration with the change and the estimated error; default: nothing.
    devices: JAX devices that run the sweeps (default 1).  They form a ("face", "u", "v")
        mesh (``mesh``, default :func:`mesh_shape_for`): faces = 2 runs the + and − sweeps of
        each axis at once on two halves; u × v devices split each sweep's plane into blocks
        that exchange M-wide halos every slab (``ppermute``, toroidal on periodic sides).
        Results equal one device's.  On a CPU, N host devices need
        ``XLA_FLAGS=--xla_force_host_platform_device_count=N`` before JAX starts.
    mesh: (faces, u, v) with faces in {1, 2} and faces·u·v = devices.
    method: "gmres" solves (I − K)x = b by restarted GMRES with the sweeps as the
        matrix-free operator (``_krylov.py``); "jacobi" iterates x ← Kx + b; "auto" (default)
        = "gmres", the faster in every case measured (3.5-94× on the furnace at albedo
        0.5-0.999, 1.2-27× on thick fog; ``benchmarks/bench_krylov.py``).
    restart: GMRES's Krylov steps per cycle (memory: restart + 1 state vectors).
    terms: "auto" (default) builds only what the scene needs (``_terms.py``: no fog → no fog
        step, no sky → no sky pass, fog in a sub-box → fog work only there, ...); "all" builds
        every term, which a fit that starts a parameter from exactly 0 needs.
    precondition: GMRES's preconditioner: "diffusion" (diffusion synthetic acceleration,
        ``_dsa.py``: a diffusion solve on the lattice per step, which keeps the step count
        nearly flat as albedo → 1 and the fog thickens), "none", or "auto" (default):
        "diffusion" when the scene's fog is optically thick (σ_t × the lattice's extent ≥
        ``DIFFUSION_OPTICAL_SIZE``, judged from the scene's values at ``prepare``), else
        "none".  Jacobi ignores it.
    kernel: the program of a face sweep (``_kernel.KERNELS``): "loop" (cache-tiled loops over
        row tiles and directions: 2-3x faster on a CPU), "batched" (all directions of a slab
        in one array: 130x faster than "loop" on an H100, measured), "pallas" (the batched
        program with each slab step as one Pallas kernel, one pass over the carried radiance
        instead of about four: Triton on a GPU, where its speed is not yet measured;
        interpreted, slowly, on a CPU; the sub-stepped scheme and a device mesh run
        "batched"), or
        "auto" (default): the one for JAX's default backend (``kernel_for``: "loop" on a CPU,
        "batched" elsewhere).  Same values and derivatives.
    phase_order: the order L of the Henyey–Greenstein phase in the light solve (δ-M scaling,
        ``_harmonics.py``): each fog node carries (L+1)² angular moments of its radiance and
        each direction's in-scatter source is rebuilt from them; the forward peak g^(L+1) is
        treated as unscattered.  0 is the δ-isotropic scaling (one moment, the fluence: what
        an isotropic fog needs).  "auto" (default): 0 for an isotropic fog (g = 0 at
        ``prepare``), else ``DEFAULT_PHASE_ORDER``.  The cameras' single scattering of the sun
        always uses the exact phase.  Cost: about K = (L+1)² − 1 more multiply-adds per node
        and direction, and K more numbers per node in the solve's vectors.
    scheme: the transport along a lattice segment.  "step": each node's source is constant
        over its segment.  "linear": the isotropic source varies linearly along the
        segment, with the slope h∇Q from central differences of the collided source between
        fog nodes and the uncollided sun's and sky's exact slopes along their beams
        (``_source_slope``, ``_kernel._linear_node``).  The slope integrates to zero over a
        segment, so energy is conserved as with "step"; deep in optically thick fog the
        radiance leaving a segment is then Q − ∂Q/∂τ, which gives the true diffusion
        coefficient 1/(3σ_t) where "step" gives h|L|/6 (light spreads through thick fog too
        easily: slab transmittance ×5-80 at 2 mean free paths per node).  The cameras then
        read each node's source slope too (``LatticeFields.j_slope``).  "substep": the step
        scheme with each segment (it spans M planes) crossed in M sub-steps, one per plane,
        each with the extinction and source of the node nearest to where the ray crosses
        that plane, which also receives the light it removes (``_kernel._sweep_face_substep``):
        the transport resolves the spacing h, not the segment's M·h, and energy is conserved
        exactly in fog away from shapes (the conservative slab to 1e-7; the furnace's
        radiance 10 at every node).  Measured at N = 32, M = 3 (docs/validation.md): cloud-tomo from Mitsuba 1.84 → 1.17%, its skin's collided light
        +8% → −1.7%, cloud-plane's oblique view 8.6 → 6.7%, issue 14's cube (ζ = 100, N = 32,
        M = 2) +8.3% → −3.0% against its Monte Carlo value; fog-balls 2.1 → 2.6% (its walls
        and balls: a crossing inside a shape does not count); slower (M − 1 more reads and
        deposits per direction and node; on a CPU a direction loop like "step"'s,
        ``_kernel._sweep_face_substep_loop``).  Opt-in.
        "auto" (default):
        "linear" where one lattice step is optically thicker than ``LINEAR_STEP_DEPTH``, and
        throughout fog ``LINEAR_FOG_SIZE`` or more mean free paths across (the scene's values
        at ``prepare``), else "step" (``resolved_scheme``).  Measured
        (docs/validation.md): equal to "step" in thin fog (τ = 1 slabs: 0.1%), far closer in
        T at τ = 16-64, issue 14's thick cube within 2.7% at step depths of 6 to 625 (step:
        +1.8 to +13.3%); cloud-plane unchanged; +19% per iteration.
    tangents: how a tangent light solve (forward mode: a fit's Jacobian, ``jax.jvp``) applies
        I − K.  "matrix-free" (default): one Jacobi step with the sources zeroed per product,
        on the same face-sweep program as the light solve, keeping nothing between products.
        "linearised": ``lx.linearise`` of the Jacobi step once, whose residuals (~1-2 KB per
        lattice node and direction) stay for the whole solve.  A gradient's adjoint solve
        (reverse mode): see ``adjoint``.  Same values (to rounding).
    block_tangents: a fit's Jacobian (its tangent light solves, one per unknown, vmapped) by
        one block GMRES over all of them (True, default: ``_krylov.block_gmres``, one Krylov
        space shared by the unknowns) or one GMRES each in lockstep (False; always on a device
        mesh, where the block's QR would gather the sharded state).  The same Jacobian to
        ``adjoint_rtol``.  Measured (the README example's fit, ``benchmarks/block_tangents.py``):
        23-25% fewer products from zero, 0-12% from the last step's tangents, 45 Krylov
        vectors against 123 for 3 unknowns.
    adjoint: how a gradient's adjoint solve (reverse mode: ``jax.grad``, the density fit)
        applies (I − K)ᵀ.  "transposed": hand-written transposed face sweeps
        (``_kernel.sweep_face_transposed``: the slabs in reverse, a direction loop like the
        CPU's forward program), nothing kept between products; the step and sub-stepped
        schemes on one device, with tangents="matrix-free".
        "linearised": JAX's transpose of the batched program linearised once (its residuals
        as ``sweep_residuals`` says).  "auto" (default): "transposed" where it applies, the
        kernel is "loop" (a CPU) and the phase is isotropic (with moments the loop's sums
        over them cost more than the batched contractions), else "linearised".  Same values
        (to rounding).  Measured (value and gradient of an image loss, float32, this 2-core
        CPU, stop 49): fog-balls N = 32 3.88 → 2.37 s, cloud-tomo N = 32 (step) 3.17 → 1.72 s,
        the same XLA temporaries (the parameters' cotangent still linearises one step);
        cloud-plane N = 24, L = 3: 4.14 → 5.71 s, so "auto" keeps "linearised" there
        (``benchmarks/bench_adjoint_route.py``).
    sweep_residuals: what a linearised sweep (a gradient's adjoint solve, or tangents
        "linearised") keeps: "keep" every coefficient of its slab steps, ~0.8-2 KB per lattice
        node and direction, or "recompute" only each slab step's inputs (``jax.checkpoint``),
        recomputing the step in every product: 4-4.5× less (0.2-0.6 KB), for 0-18% more time
        per gradient (measured: cloud-plane N = 24, fog-balls and cloud-tomo N = 32).  "auto"
        (default): "recompute" where the kept residuals would exceed
        ``RECOMPUTE_ABOVE_BYTES`` (1 GiB), else "keep".  Same values.
    first_collision: what the fog's first collision of the uncollided sun and sky scatters
        into the lattice.  "beam" (default): the beam's fluence averaged over each node's own
        segment, re-emitted at the node's box-filtered σ̄ (``segment_depth``), so that where
        one step spans mean free paths the nodes at a sunlit face re-emit more than the beam
        loses there (a sunlit slab of τ = 64 over 32 nodes returns up to 19% more light than
        it receives).  "deposit": the beams' box-filtered deposit (``_deposit_average``):
        the first collision scatters exactly what the beams lose, at any step optical depth
        (that slab: within 2.5%).  Measured (docs/validation.md): cloud-tomo-b 2.04 → 1.69%
        and cloud-plane's oblique view 8.6 → 7.7% from Mitsuba at N = 32; issue 14's thick
        cube against its own image (a float64 Monte Carlo, ``THICK_CUBE_REFERENCE``) at
        N = 32: −2.8% at ζ = 100 but −13% at ζ = 1000, where one node spans 60 mean free
        paths, against "beam"'s +5.1% and +3.5%.  The same in thin fog.  The linear scheme's
        first-collision slope stays the beam's own.
    once_M: a Henyey–Greenstein fog under a sun: sweep the sun's once-scattered light (its
        first collision, with the exact phase averaged over each direction's cell) on the
        finer direction set of half-width ``once_M`` instead of the solve's M, once per light
        solve (sub-stepped: its segments span once_M planes), and give the solve its fluence
        and its δ-M source (degree by degree, in the M basis) as a fixed part of the light
        (``_once_scattered``); every later order stays on M.  The sun's forward lobe (g =
        0.85: half its peak within 7°) is narrower than M = 3's directions (18° apart at a
        face's centre), which read a thin sunlit slab's R 2-4% high.  Ignored (0) for an
        isotropic fog or without a sun (``resolved_once_M``); the lattice's surface shell and
        margin follow the larger set (``lattice_M``).  None (default): off.  Measured
        (docs/validation.md, "The once-scattered light on a finer direction set"): see there.
    """

    M: int = eqx.field(static=True, default=3)
    max_iterations: int = eqx.field(static=True, default=200)
    tol: float = eqx.field(static=True, default=1e-4)
    adjoint_rtol: float = eqx.field(static=True, default=1e-6)
    sky_quadrature: tuple[int, int] | None = eqx.field(static=True, default=None)
    progress: AbstractProgressMeter = eqx.field(static=True, default_factory=NoProgress,
                                                converter=as_meter)
    throw: bool = eqx.field(static=True, default=True)
    devices: int = eqx.field(static=True, default=1)
    mesh: tuple[int, int, int] | None = eqx.field(static=True, default=None)
    method: str = eqx.field(static=True, default="auto")
    restart: int = eqx.field(static=True, default=30)
    terms: str = eqx.field(static=True, default="auto")
    precondition: str = eqx.field(static=True, default="auto")
    kernel: str = eqx.field(static=True, default="auto")
    phase_order: int | str = eqx.field(static=True, default="auto")
    scheme: str = eqx.field(static=True, default="auto")
    tangents: str = eqx.field(static=True, default="matrix-free")
    block_tangents: bool = eqx.field(static=True, default=True)
    sweep_residuals: str = eqx.field(static=True, default="auto")
    first_collision: str = eqx.field(static=True, default="beam")
    adjoint: str = eqx.field(static=True, default="auto")
    once_M: int | None = eqx.field(static=True, default=None)

    def layout(self) -> tuple[int, int, int]:
        """The (faces, u, v) device mesh the sweeps run on."""
        return tuple(self.mesh) if self.mesh is not None else mesh_shape_for(self.devices)

    def __check_init__(self):
        if not isinstance(self.M, int) or self.M < 1:
            raise SceneError(f"SweepSolver: M must be an integer >= 1, got {self.M!r}")
        if not isinstance(self.max_iterations, int) or self.max_iterations < 1:
            raise SceneError(
                f"SweepSolver: max_iterations must be an integer >= 1, got {self.max_iterations!r}"
            )
        if not (self.tol >= 0):
            raise SceneError(f"SweepSolver: tol must be >= 0, got {self.tol!r}")
        if isinstance(self.devices, bool) or not isinstance(self.devices, int) or self.devices < 1:
            raise SceneError(f"SweepSolver: devices must be an integer >= 1, got {self.devices!r}")
        if self.mesh is not None:
            ok = (len(self.mesh) == 3 and all(isinstance(n, int) and n >= 1 for n in self.mesh)
                  and self.mesh[0] in (1, 2))
            if not ok or int(np.prod(self.mesh)) != self.devices:
                raise SceneError(
                    f"SweepSolver: mesh must be (faces, u, v) with faces 1 or 2 and "
                    f"faces*u*v = devices = {self.devices}, got {self.mesh!r}"
                )
        for name, allowed in (("method", METHODS), ("terms", TERMS),
                              ("precondition", PRECONDITIONERS), ("kernel", KERNELS),
                              ("sweep_residuals", SWEEP_RESIDUALS), ("tangents", TANGENTS),
                              ("first_collision", FIRST_COLLISIONS), ("adjoint", ADJOINTS)):
            value = getattr(self, name)
            if value not in allowed:
                raise SceneError(f"SweepSolver: {name} must be one of {', '.join(allowed)}, "
                                 f"got {value!r}")
        po = self.phase_order
        if po != "auto" and (isinstance(po, bool) or not isinstance(po, int)
                             or not 0 <= po <= MAX_ORDER):
            raise SceneError(f"SweepSolver: phase_order must be \"auto\" or an integer in "
                             f"[0, {MAX_ORDER}], got {po!r}")
        if self.scheme not in SCHEMES:
            raise SceneError(f"SweepSolver: scheme must be one of {', '.join(SCHEMES)}, "
                             f"got {self.scheme!r}")
        if not isinstance(self.block_tangents, bool):
            raise SceneError(f"SweepSolver: block_tangents must be True or False, "
                             f"got {self.block_tangents!r}")
        if self.adjoint == "transposed" and self.tangents != "matrix-free":
            raise SceneError("SweepSolver: adjoint=\"transposed\" needs tangents=\"matrix-free\" "
                             "(the default)")
        if self.scheme == "substep" and (self.devices > 1 or self.mesh is not None):
            raise SceneError("SweepSolver: scheme=\"substep\" runs on one device; use "
                             "devices=1 (or another scheme on a device mesh)")
        om = self.once_M
        if om is not None and (isinstance(om, bool) or not isinstance(om, int) or om < 1):
            raise SceneError(f"SweepSolver: once_M must be None or an integer >= 1, got {om!r}")
        if om is not None and (self.devices > 1 or self.mesh is not None):
            raise SceneError("SweepSolver: once_M (a sub-stepped sweep) runs on one device; use "
                             "devices=1 or leave once_M unset")
        if not isinstance(self.restart, int) or self.restart < 2:
            raise SceneError(f"SweepSolver: restart must be an integer >= 2, got {self.restart!r}")
        if self.kernel == "pallas":
            from ._pallas import interpret_mode  # (imported only where it is asked for)

            if interpret_mode():
                warnings.warn(
                    f"SweepSolver: kernel=\"pallas\" on the {jax.default_backend()} backend runs "
                    f"Pallas's interpret mode (it compiles for GPUs only): the same values, "
                    f"3-10x slower than kernel=\"batched\"; kernel=\"auto\" takes the fast one",
                    stacklevel=3)

    def resolved_method(self, geom: "SweepGeometry | None" = None) -> str:
        """The iteration ``method`` stands for ("auto" → the measured faster one)."""
        return "gmres" if self.method == "auto" else self.method

    def resolved_precondition(self, geom: "SweepGeometry | None" = None) -> str:
        """The GMRES preconditioner ``precondition`` stands for."""
        if self.precondition != "auto":
            return self.precondition
        thick = geom is not None and geom.optical_size >= DIFFUSION_OPTICAL_SIZE
        return "diffusion" if thick and self.resolved_method(geom) == "gmres" else "none"

    def resolved_adjoint(self, pb: "_Problem") -> str:
        """The adjoint route ``adjoint`` stands for on ``pb`` ("auto": "transposed" where the
        face sweeps run the CPU's loop program, ``transposable`` holds and the phase is
        isotropic or the sub-stepped scheme's native kernel serves, else "linearised")."""
        if self.adjoint == "transposed" and not transposable(pb):
            raise SceneError("SweepSolver: adjoint=\"transposed\" has the step and sub-stepped "
                             "schemes on one device only; use adjoint=\"auto\"")
        if self.adjoint != "auto" or self.tangents != "matrix-free":
            return "linearised" if self.tangents != "matrix-free" else self.adjoint
        # with moments the XLA loop's per-direction sums over them (K = 15 at L = 3) cost more
        # than the batched program's contractions: cloud-plane N = 24, L = 3, a value and
        # gradient 5.71 s transposed against 4.14 s linearised (isotropic: 1.72 against 3.17
        # s); the sub-stepped scheme's native transpose (stop 70) does them in its pass: 6.58
        # against 14.72 s there (``bench_adjoint_route.py --scheme substep --cases
        # cloud-plane:24:3``)
        iso = not pb.geom.channels
        native = pb.geom.substep and substep_native_applies(pb.kernel, pb.geom.consts[0],
                                                            pb.sigma_t.dtype)
        return ("transposed" if pb.kernel == "loop" and transposable(pb) and (iso or native)
                else "linearised")

    def resolved_kernel(self) -> str:
        """The face-sweep program ``kernel`` stands for on JAX's default backend."""
        return kernel_for() if self.kernel == "auto" else self.kernel

    def resolved_phase_order(self, scene=None) -> int:
        """The δ-M order ``phase_order`` stands for in ``scene``."""
        if self.phase_order != "auto":
            return int(self.phase_order)
        g = 0.0 if scene is None or scene.fog is None else float(scene.fog.g or 0.0)
        return 0 if g == 0.0 else DEFAULT_PHASE_ORDER

    def resolved_sweep_residuals(self, geom: "SweepGeometry") -> str:
        """What ``sweep_residuals`` stands for on ``geom``'s lattice."""
        return sweep_residuals_for(self.sweep_residuals, math.prod(geom.shape), geom.M,
                                   geom.linear, geom.n_moments, geom.substep)

    def resolved_scheme(self, scene=None, lattice=None) -> str:
        """The transport scheme ``scheme`` stands for in ``scene`` on ``lattice`` ("auto":
        "linear" where one lattice step is optically thicker than ``LINEAR_STEP_DEPTH``, and at
        any step depth in fog at least ``LINEAR_FOG_SIZE`` mean free paths across
        (``optical_size``), at the scene's values; else "step")."""
        if self.scheme != "auto":
            return self.scheme
        if scene is None or lattice is None or scene.fog is None:
            return "step"
        fog = scene.fog
        depth = step_depth(fog.scattering, fog.absorption, fog.g or 0.0,
                           self.resolved_phase_order(scene), lattice.peak_density, lattice.h,
                           self.M)
        if depth > LINEAR_STEP_DEPTH:
            return "linear"
        if depth > 0 and optical_size(fog, lattice.peak_density,
                                      fog_extent(scene)) >= LINEAR_FOG_SIZE:
            return "linear"
        return "step"

    def resolved_once_M(self, scene=None) -> int:
        """The direction set (half-width) that carries the sun's once-scattered light in
        ``scene``: ``once_M`` where the scene has a sun and an anisotropic phase in the solve
        (what the finer set resolves: the exact phase's forward lobe), else 0 (the solve's own
        M, nothing swept apart)."""
        om = self.once_M
        if om is None or om == self.M or scene is None or scene.sun is None:
            return 0
        return int(om) if self.resolved_phase_order(scene) > 0 else 0

    def lattice_M(self, scene=None) -> int:
        """The surface shell (and vacuum margin) the lattice needs: the largest direction
        set swept on it."""
        return max(self.M, self.resolved_once_M(scene))

    def prepare(self, scene, lattice) -> SweepGeometry:
        """The static structure of ``scene`` on ``lattice`` (host, once)."""
        scheme = self.resolved_scheme(scene, lattice)
        order = self.resolved_phase_order(scene)
        devices = math.prod(self.layout())
        if devices > 1 and jax.default_backend() == "cpu" and _native.expected():
            warnings.warn(cpu_mesh_warning(devices), DeviceWarning, stacklevel=3)
        geom = prepare_sweep(scene, lattice, self.M, self.terms, order,
                             linear=scheme == "linear", substep=scheme == "substep",
                             records=devices == 1)
        if once_M := self.resolved_once_M(scene):
            # the sub-stepped scheme, whatever the solve's: its segments span once_M planes,
            # longer than the solve's, and the sun's first collision falls off along them as
            # e^(−τ/μ₀) (g = 0.85 slabs at N = 32 under a zenith sun, τ = 16: R +12.5%, T
            # +23% with the step scheme's constant source per segment at once_M = 6; +1.1%,
            # +1.3% sub-stepped)
            once = prepare_sweep(scene, lattice, once_M, self.terms, order, substep=True,
                                 shadows=False)
            geom = eqx.tree_at(lambda g: g.once, geom, once, is_leaf=lambda x: x is None)
        return geom

    def problem(self, geom: SweepGeometry, params: Params) -> _Problem:
        dt = params.scattering.dtype
        # δ-M scaling of the HG phase at the geometry's order (order 0: δ-isotropic, f = g;
        # exact for g = 0): the forward peak f is unscattered, ζ' = ζ(1 − f)
        f, phase_coef = moment_coefficients(params.g, geom.order, geom.M, jnp)
        zeta = params.scattering * (1.0 - f)
        ext = zeta + params.absorption
        sigma_t = ext * geom.density.astype(dt)
        sun_albedo = sun_phase = None
        sun_peak = once_phase = None
        if geom.sun_dir is not None and geom.order > 0:
            # the first collision of the sun with the exact phase averaged over each
            # direction's cell, less the forward peak that the direction set cannot resolve
            # (``unresolved_peak``), taken from within a cell and a half of the sun's own
            # direction (``_cell_phase``): that share stays in the beam, along the sun's exact
            # direction, as every later order's δ-M peak does; the lattice's nearest
            # directions would carry it up to half a cell (~6° at M = 3) off course, and
            # ~unattenuated by the δ-scaled fog: a g = 0.999 fog cast a shadow where clear air
            # casts none (test_as_g_approaches_1_the_fog_stops_scattering)
            cells = geom if geom.once is None else geom.once  # the first collision's cells
            phase, kept, c = _cell_phase(cells, params.g, dt, unresolved_peak(params.g, cells.M))
            if geom.once is not None:
                once_phase = phase
                sun_phase = _cell_phase(geom, params.g, dt, c=c, width=peak_width(cells.M))[0]
            else:
                sun_phase = phase
            sun_peak = jnp.stack([kept, c, jnp.asarray(peak_width(cells.M), dt)])
            zeta_sun = params.scattering * (1.0 - kept)
            sigma_sun = (zeta_sun + params.absorption) * geom.density.astype(dt)
            # ζ(1 − peak)/σ_t' per unit density, like ``ssa``: a node without fog of its own
            # whose segments reach into fog must re-emit what they take (energy)
            sun_albedo = safe_div(zeta_sun, ext)
        else:
            sigma_sun = sigma_t
        sun_slope = sky_slope = None
        if geom.sun_dir is not None:
            # the point value lights surfaces; the segment average feeds the fog's source
            # (and with the linear scheme its slope, where the sun is in the isotropic source)
            # the shapes' shadow: exact (``sun_vis``, the fog's beam through no solid), or the
            # SOLID nodes
            opaque = geom.solid if geom.sun_vis is None else jnp.zeros_like(geom.solid)
            t_sun, t_sun_avg, *t_grad = sun_transmittance(
                sigma_sun, opaque, np.array(geom.sun_dir), geom.h, geom.periodic_xy,
                average=True, slope=geom.linear and sun_phase is None,
                vec=None if geom.sun_vec is None else geom.sun_vec.astype(dt))
            if geom.sun_vis is not None:
                vis = geom.sun_vis.astype(dt)
                t_sun, t_sun_avg = vis * t_sun, vis * t_sun_avg
                t_grad = [vis[..., None] * g for g in t_grad]
            sun_point = params.sun_irradiance * t_sun
            sun_fluence = params.sun_irradiance * t_sun_avg
            if t_grad:
                sun_slope = _mask(geom.solid, params.sun_irradiance * t_grad[0])
        else:
            sun_point = sun_fluence = jnp.zeros(geom.shape, dt)
        n_mu, n_phi = self.sky_quadrature or ((0, 0) if geom.periodic_xy else (8, 16))
        no_sky = geom.terms is not None and geom.terms.sky == "none"
        sky_moments = None
        if no_sky:  # the terms: no [sky], no sky pass
            sky_fluence = jnp.zeros(geom.shape, dt)
            sky_direct = jnp.zeros(geom.shape, dt)
            lattice_sky = jnp.zeros_like(params.sky_radiance)
        elif n_mu > 0 and n_phi > 0:
            sdirs, swts = sky_quadrature(n_mu, n_phi)
            harm = (basis(geom.order, geom.M).evaluate(-np.asarray(sdirs)) if geom.order > 0
                    else None)  # the sky light's propagation directions
            flu, irr, *more = sky_uncollided(sigma_t, geom.solid, geom.normal, sdirs, swts,
                                             geom.h, geom.periodic_xy, harm=harm,
                                             slope=geom.linear)
            sky_fluence = jnp.where(geom.solid, 0.0, params.sky_radiance * flu)
            if harm is not None:
                sky_moments = _mask(geom.solid, params.sky_radiance * more[0])
            if geom.linear:
                sky_slope = _mask(geom.solid, params.sky_radiance * more[-1])
            sky_direct = jnp.where(geom.surf, params.sky_radiance * irr, 0.0)
            lattice_sky = jnp.zeros_like(params.sky_radiance)
        else:
            sky_fluence = jnp.zeros(geom.shape, dt)
            sky_direct = jnp.zeros(geom.shape, dt)
            lattice_sky = params.sky_radiance
        rho = jnp.where(geom.surf, params.albedo[geom.material], 0.0) if params.albedo.size else (
            jnp.zeros(geom.shape, dt))
        emis = jnp.where(geom.surf, params.emission[geom.material], 0.0) if params.emission.size \
            else jnp.zeros(geom.shape, dt)
        # the sub-stepped scheme takes each node's own σ_t (its segments cross every plane);
        # the others its box filter over the M planes a segment spans
        tau_world = [
            jnp.where(geom.solid, 0.0,
                      sigma_t if geom.substep else
                      segment_depth(sigma_t, geom.M, axis, geom.periodic_xy and axis < 2))
            * (geom.h / 2.0)
            for axis, _ in FACE_AXES
        ]
        fog_mask = None
        if geom.terms is not None and geom.terms.fog_slabs is not None:
            fog_mask = sum(tau_world) > 0
        sun_fluence = jnp.where(geom.solid, 0.0, sun_fluence)
        sun_beam, sky_beam, sky_moments_beam = sun_fluence, sky_fluence, sky_moments
        # (the sub-stepped scheme re-emits at each node's own σ_t, as the beams lose it: its
        # beam is its deposit)
        if self.first_collision == "deposit" and not geom.substep:
            # Σ_a box_a(σ_t), from the + faces' σ̄·h/2 (0 in solids, where the average is 0)
            sigma_box = sum(tau_world[FACE_AXES.index((a, 1))] for a in range(3)) / (geom.h / 2)

            def dep(x):
                return _deposit_average(x, sigma_t, sigma_box, geom.solid, geom.M,
                                        geom.periodic_xy)

            sun_fluence = dep(sun_beam)
            sky_fluence = dep(sky_fluence)
            if sky_moments is not None:
                sky_moments = dep(sky_moments)
        once = (None, None, None)
        if geom.once is not None and sun_phase is not None:
            once = self._once_scattered(geom, params, sigma_t, sun_albedo * sun_beam,
                                        once_phase)
        return _Problem(
            once_fluence=once[0],
            once_source=once[1],
            once_irradiance=once[2],
            geom=geom,
            tau_half=tuple(to_face(t, axis, sign) for t, (axis, sign) in zip(tau_world, FACE_AXES)),
            fog_mask=fog_mask,
            sigma_t=sigma_t,
            ssa=safe_div(zeta, ext),
            sun_fluence=sun_fluence,
            sky_fluence=sky_fluence,
            rho=rho,
            emission=emis,
            direct=sun_point * geom.sun_cos.astype(dt) + sky_direct,
            sky_direct=sky_direct,
            sky=lattice_sky,
            phase_coef=None if geom.order == 0 else phase_coef.astype(dt),
            sky_moments=sky_moments,
            sun_albedo=sun_albedo,
            sun_phase=sun_phase,
            sun_peak=sun_peak,
            sun_slope=sun_slope,
            sky_slope=sky_slope,
            sun_beam=sun_beam,
            sky_beam=sky_beam,
            sky_moments_beam=sky_moments_beam,
            max_iterations=self.max_iterations,
            tol=self.tol,
            progress=self.progress,
            mesh_shape=self.layout(),
            method=self.resolved_method(geom),
            restart=self.restart,
            precondition=self.resolved_precondition(geom),
            kernel=self.resolved_kernel(),
            recompute=self.resolved_sweep_residuals(geom) == "recompute",
        )

    def _once_scattered(self, geom: SweepGeometry, params: Params, sigma_t, sun_source,
                        phase):
        """(Λ₁, S₁, E₁): the sun's first collision (``sun_source``, ζ/σ_t'·F·T̄ per node) with
        the exact phase averaged over each direction's cell (``phase``, ``_cell_phase``'s on
        ``geom.once``), swept once on the direction set
        of ``geom.once`` (half-width ``once_M``): the once-scattered light's fluence Λ₁, its
        anisotropic source per unit ζ' and its irradiance E₁ on surfaces.  S₁ is the δ-M
        phase applied to the light's harmonic moments degree by degree, Σ_l g'_l Σ_m a_lm
        (Y_lm − μ_lm) with a = T_M₁⁻¹·m₁ (``harmonic_moments``), in ``geom``'s basis: T_M⁻¹·(g'
        ⊙ a).  (Its moments carried over to that basis and weighted there by the solve's
        per-function g'_k, which its orthonormalization mixes across degrees, read a sunlit
        slab's R 4.5% high instead of 2.1%.)  A strongly forward-scattering phase
        concentrates this light within ~(1 − g) rad of the sun's direction, which the solve's
        own M = 3 directions sample coarsely (thin g = 0.85 slabs read R 2-4% high; the
        direction sets compared in ``benchmarks/slab_directions.py``); every later order of
        scattering is smoother and stays on ``geom``'s directions."""
        g1 = geom.once
        dt = sigma_t.dtype
        tau1 = [jnp.where(g1.solid, 0.0, sigma_t) * (g1.h / 2.0) for _ in FACE_AXES]
        # (sub-stepped: each node re-emits at its own σ_t, as the beam loses it, so the beam's
        # fluence is its deposit, whatever ``first_collision`` says)
        src = jnp.where(g1.solid, 0.0, sun_source)
        zero = jnp.zeros(g1.shape, dt)
        # the channels of the solve's anisotropic source: none but the sun's
        q = jnp.concatenate([jnp.zeros(g1.shape + (1 + g1.n_moments,), dt), src[..., None]],
                            axis=-1)
        # (no fog mask: the solve's own decides where Λ is kept, and a step scheme's nodes
        # beside the fog, whose box-filtered segments reach into it, use it)
        pb1 = _Problem(
            geom=g1, tau_half=tuple(to_face(t, a, sg) for t, (a, sg) in zip(tau1, FACE_AXES)),
            sigma_t=sigma_t, ssa=zero, sun_fluence=zero, sky_fluence=zero, rho=zero,
            emission=zero, direct=zero, sky_direct=zero,
            sky=jnp.zeros((), dt), sun_phase=phase,
            max_iterations=1, tol=0.0, mesh_shape=self.layout(), kernel=self.resolved_kernel(),
            recompute=self.resolved_sweep_residuals(g1) == "recompute")
        lam1, irr1 = _sweep_all(q, jnp.zeros(g1.shape, dt), pb1)
        L = geom.order
        a = lam1[..., 1:] @ jnp.asarray(harmonic_moments(L, g1.M), dt)
        coef = delta_m(params.g, L, jnp)[1][basis(L, geom.M).degree - 1]
        src = (coef * a) @ jnp.asarray(harmonic_moments(L, geom.M), dt)
        return lam1[..., 0], _mask(g1.solid, src), irr1

    def solve(self, geom: SweepGeometry, params: Params, init=None) -> LightField:
        """The converged light field (differentiable in ``params``), with its result code:
        ``RESULTS.successful`` when the estimated error reached ``tol`` (or ``tol`` = 0 and the
        iterations ran), else ``max_iterations_reached``, ``stagnated`` or ``nonfinite``.
        ``init``: a light state to start from (``LightField.state`` of a solve on the same
        geometry, at nearby parameters), else zero; the answer is the same to ``tol``, and
        its derivatives do not depend on it (it is a constant of the solve).  Traced inside
        ``forward_mode()``, ``init``'s tangent is where the tangent solve starts (a guess of
        the state's tangent: a fit's last step's), and ``state`` keeps its tangent."""
        terms_code = None if geom.terms is None else _check_terms(geom.terms, params)
        pb = self.problem(geom, params)
        guess = None
        if init is not None:
            want = (tuple(geom.fluence_shape), tuple(geom.shape))
            got = tuple(tuple(jnp.shape(a)) for a in init)
            if got != want:
                raise SolverError(f"init: a light state of shapes {want} (LightField.state of "
                                  f"a solve on this model), got {got}")
            dt = pb.sigma_t.dtype
            init = tuple(a.astype(dt) for a in init)
            if in_forward_mode():  # init's tangent: where the tangent solve starts
                guess = init
            pb = eqx.tree_at(lambda p: p.init, pb, jax.tree.map(jax.lax.stop_gradient, init),
                             is_leaf=lambda x: x is None)
        # The adjoint has the forward's spectrum: budget it like the forward (2 ×
        # max_iterations products, at least 4 cycles of 40); the sweep's own GMRES stops at
        # the product where it has converged (lineax's ran every cycle to its end: 41
        # products for an adjoint that needs a handful).  A device mesh once got 20 cycles
        # (lineax's GMRES there reached 8e-7 in 20 where one device reached 1e-10 in 4); with
        # this GMRES the adjoint takes the same 26 products to 1e-10 on one device and on the
        # meshes (2,1,1), (1,2,1), (1,2,2) (fog-balls N = 11, float64, stop 62;
        # ``benchmarks/mesh_solves.py``), so the budget is the same everywhere.
        cycles = 4
        one_device = math.prod(self.layout()) == 1
        linear_solver = CheckedSolver(KrylovSolver(
            rtol=self.adjoint_rtol, restart=40,
            max_matvecs=max(40 * cycles, 2 * self.max_iterations) + 2,
            native=one_device, block=self.block_tangents and one_device), throw=self.throw)
        matrix_free = self.tangents == "matrix-free"
        root, (hist, k, err) = fixed_point(
            _solve_fixed_point, _rewrite, pb, linear_solver, precondition=_preconditioner,
            linear=_rewrite_linear if matrix_free else None,
            transposed=(_rewrite_linear_transposed
                        if matrix_free and self.resolved_adjoint(pb) == "transposed" else None),
            guess=guess)
        dip = _dip(root[0][..., 0] if geom.channels else root[0], pb.fog_mask)
        # a constant of the solve, except under forward_mode(), where its tangent is what a
        # later tangent solve may start from
        root_state = root if in_forward_mode() else jax.tree.map(jax.lax.stop_gradient, root)
        root = _non_negative(root, geom.channels)
        q, b = _sources(root, pb)
        if pb.once_fluence is not None:  # the light: the state's and the once-scattered sun's
            lam0 = root[0][..., 0] + pb.once_fluence
            root = (jnp.concatenate([lam0[..., None], root[0][..., 1:]], axis=-1),
                    root[1] + pb.once_irradiance)
        irradiance = jnp.where(geom.surf, geom.cnorm * root[1] + pb.sky_direct, 0.0)
        lam = root[0] if pb.fog_mask is None else _mask(~pb.fog_mask, root[0])
        moments = q_slope = f_slope = None
        if geom.linear:
            q_slope = q[..., -3:]
            f_slope = _fluence_slope(lam[..., 0] if geom.channels else lam, pb, sun=False)
        if geom.channels:
            lam, moments = lam[..., 0], lam[..., 1:]
        code = _result_code(root, k, err, self.tol, self.max_iterations)
        if terms_code is not None:  # the terms' violation first: it is why the solve failed
            code = combine(terms_code, code)
        if geom.channels or geom.linear:
            q = q[..., 0]  # the isotropic part (with the sun's, as if it scattered isotropically)
            if pb.sun_phase is not None:
                q = q + pb.sun_albedo * pb.sun_fluence / FOUR_PI
        return LightField(
            fluence=lam,
            moments=moments,
            sky_moments=pb.sky_moments_beam,
            once_source=pb.once_source,
            source_slope=q_slope,
            fluence_slope=f_slope,
            sun_fluence=pb.sun_beam,
            sky_fluence=pb.sky_beam,
            radiosity=b,
            irradiance=irradiance,
            source=q,
            residuals=hist,
            iterations=k,
            error_estimate=err,
            result=code,
            dip=dip,
            sun_peak=pb.sun_peak,
            state=root_state,
            origin=geom.origin,
            h=geom.h,
        )


def source_field(pb: _Problem, light: LightField, sun: bool = True):
    """The converged step source Q of ``light``: (nx, ny, nz), or with an anisotropic phase
    (nx, ny, nz, 1 + K [+ 1]) (see ``_sources``).  ``sun=False``: without the uncollided sun's
    part (what a camera replaces by the exact phase function's single scattering; no sun
    channel)."""
    g = pb.geom
    if not (g.channels or g.linear) and sun:
        return light.source
    if pb.once_fluence is not None:  # ``light``'s fluence holds the once-scattered light's
        pb = eqx.tree_at(lambda p: (p.once_fluence, p.once_irradiance), pb,
                         (jnp.zeros_like(pb.once_fluence), jnp.zeros_like(pb.once_irradiance)))
    if not sun:
        pb = eqx.tree_at(lambda p: p.sun_fluence, pb, jnp.zeros_like(pb.sun_fluence))
    lam = light.fluence if not g.channels else jnp.concatenate(
        [light.fluence[..., None], light.moments], axis=-1)
    q = _sources((lam, jnp.zeros(g.shape, lam.dtype)), pb, first_collision=True)[0]
    if g.channels and not sun and pb.sun_phase is not None:  # drop the sun's channel
        q = jnp.delete(q, 1 + g.n_moments, axis=-1)
    return q


def unresolved_peak(g, M: int):
    """The forward peak of a Henyey–Greenstein phase that the direction set of half-width M
    cannot resolve: g^(L_M + 1), δ-M's peak at the largest order L_M whose (L_M + 1)²
    harmonics the set's 6(2M + 1)² directions can carry (L_M = 16 at M = 3: 0.06 of the
    first collision at g = 0.85, 0.42 at 0.95, 0.84 at 0.99)."""
    L = int(math.floor(math.sqrt(6.0) * (2 * M + 1))) - 1
    return g ** (L + 1)


def peak_width(M: int) -> float:
    """1 − cos θ_w of the window the unresolved peak is taken from (``forward_peak_kernel``):
    θ_w = 1.5/M rad, a cell and a half of the direction set of half-width M around the sun."""
    return 1.0 - math.cos(1.5 / M)


def _cell_phase(geom: SweepGeometry, g, dt, peak=0.0, c=None, width=None):
    """(per face (D,) phase, kept share, c): the Henyey–Greenstein phase p of the sun's light
    averaged over each direction's cell, less the part c·K·p that its beam keeps (K
    ``forward_peak_kernel`` around the sun's direction, of ``width`` (default
    ``peak_width(geom.M)``)), normalized so that Σ_d w_d P_d = 1 over all faces (the first
    collision re-emits exactly what its beam loses).  c = min(1, ``peak``/∫K·p), or the ``c``
    given: the share kept is ``peak`` where the window holds that much of the lobe, else all
    of K·p; p(1 − c·K) ≥ 0 everywhere, and everything is continuous in the sun's direction
    and in g.  The cameras scatter the beam with the same p(1 − c·K)
    (``LatticeFields.sun_window``)."""
    vec, wt = geom.sun_cells
    s = -geom.sun_vector(dt)  # the sun's light propagates along −sun_dir
    cos, wt = vec.astype(dt) @ s, wt.astype(dt)
    p = wt * (1.0 - g * g) / (FOUR_PI * (1.0 + g * g - 2.0 * g * cos) ** 1.5)  # (6, D, n²)
    w = jnp.stack([c_.weight.astype(dt) for c_ in geom.consts])
    total = (w * p.sum(-1)).sum()
    kp = p * forward_peak_kernel(cos, peak_width(geom.M) if width is None else width)
    near = (w * kp.sum(-1)).sum() / total
    if c is None:
        c = jnp.minimum(1.0, safe_div(jnp.asarray(peak, dt), near))
    kept = c * near
    P = (p - c * kp).sum(-1) / (total * (1.0 - kept))
    return tuple(P[f] for f in range(6)), kept, c


def _result_code(root, k, err, tol: float, max_iterations: int):
    """The RESULTS code of a finished iteration (see ``SweepSolver.solve``)."""
    finite = jnp.all(jnp.isfinite(root[0])) & jnp.all(jnp.isfinite(root[1]))
    reached = (err <= tol) | (tol == 0)
    failed = jnp.where(k >= max_iterations, RESULTS.max_iterations_reached, RESULTS.stagnated)
    code = jnp.where(reached, RESULTS.successful, failed)
    return jnp.where(finite, code, RESULTS.nonfinite).astype(jnp.int32)


def _check_terms(p: Terms, params: Params):
    """Parameters that need a term the terms dropped, or a cavity with no steady state: a
    SolverError for concrete values; inside a trace, the light solve's result code (int32:
    ``RESULTS.terms_dropped`` or ``no_steady_state`` where one holds, else successful; None
    where no check applies), which ``render`` and a throwing model raise with, and a fit reads
    as a failed light solve.  (Until stop 79 it was an ``eqx.error_if``, whose host callback
    kept XLA's persistent cache from storing ring-box's light program.)"""
    v = {f.name: getattr(params, f.name) for f in dataclasses.fields(params)}
    if not any(isinstance(x, jax.core.Tracer) for x in jax.tree.leaves(params)):
        msg = terms_violation(p, {k: np.asarray(a) for k, a in v.items()})
        if msg:
            raise SolverError(msg)
        return None
    conds = terms_violation(p, v, xp=jnp)
    if not conds:
        return None
    code = jnp.asarray(RESULTS.successful, jnp.int32)
    for cond, _, c in reversed(conds):  # the first that holds
        code = jnp.where(cond, jnp.int32(c), code)
    return code


def net_flux(geom: SweepGeometry, pb: _Problem, light: LightField, axis: int = 2):
    """Net radiative flux Σ_L w_L L̂_axis R(x, L) at every non-SOLID node (W/m², + along the axis).

    One more set of sweeps with the converged sources, accumulating the first angular moment
    instead of Λ (a diagnostic: energy balance, fluxes through a plane).
    """
    world = direction_set(geom.M).vectors[..., axis]
    consts = tuple(eqx.tree_at(lambda k: k.weight, c, c.weight * jnp.asarray(world[f], c.weight.dtype))
                   for f, c in enumerate(geom.consts))
    pb_m = eqx.tree_at(lambda p: p.geom.consts, pb, consts)
    if geom.terms is not None and not geom.terms.volume_source:  # the moment needs accumulating
        full = dataclasses.replace(geom.terms, volume_source=True, fog_slabs=None)
        pb_m = eqx.tree_at(lambda p: p.geom, pb_m, dataclasses.replace(pb_m.geom, terms=full))
    flux, _ = _sweep_all(source_field(pb, light), light.radiosity, pb_m)
    return flux if not geom.channels else flux[..., 0]
