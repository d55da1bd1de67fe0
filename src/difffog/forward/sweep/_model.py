"""The sweep forward model: scene → lattice → light solve → images of every camera.

Host work once (voxelization, the solver's static geometry, the camera extension maps), then
per parameter set only JAX: the light solve (:class:`SweepSolver`) and a ray march of every
camera through the solved lattice (``_march.py``).  One light solve serves every camera.
"""

from __future__ import annotations

import math
import time

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from scipy import ndimage

from ..._numerics import FOUR_PI
from ...geometry._hits import casts_exactly
from ..._errors import SceneError
from ...geometry._lattice import (SOLID, SURFACE, VACUUM_MARGIN, Lattice, apply_density_map,
                                 voxelize)
from ...scene._description import Camera, Scene, sun_vector
from ...scene._params import SUN_PATHS, Params, get_param, sun_direction_of
from .._model import AbstractForwardModel, HostInfo, select_cameras
from ._lightfield import LightField
from ._harmonics import moment_coefficients
from ._march import (EDGE_SAMPLES, LatticeFields, RayHits, _flat_table, _interp, camera_hits,
                     edge_pixels, march_lanes, march_step, render_cameras, step_count)
from ._solver import SweepGeometry, SweepSolver, check_point_sun, step_depth, zero_state
from ._uncollided import NO_SUN_PATH, sun_path
from ._terms import check_terms

#: median vertical optical depth of a fog layer across a periodic domain below which render
#: warns (ThinLayerWarning): a haze of albedo 0.999 under an overhead sun, N = 32, M = 2,
#: renders +1.6% at 0.5, +4.1% at 0.3, +10.3% at 0.1 (and −0.3% at 1, albedo 0.9)
THIN_LAYER = 0.5

#: step optical depth σ_t·h·M above which render and fit warn (ThickStepWarning): measured on
#: slabs (docs/validation.md), a step depth of 1 keeps R within 1.5% at albedo ≥ 0.99 and 4.3%
#: at 0.9; a depth of 4 loses 4-29%
THICK_STEP = 1.0


def _nearest_index(mask: np.ndarray) -> np.ndarray:
    """For every node, the flat index of the nearest node where ``mask`` is True."""
    if not mask.any():
        return np.zeros(mask.shape, np.int64)
    idx = ndimage.distance_transform_edt(~mask, return_distances=False, return_indices=True)
    return np.ravel_multi_index(tuple(idx), mask.shape)


def _resample(lam, irr, src, dst):
    """``SweepModel.resampled_state`` on the host: Λ (with any channels) trilinear between the
    fluid nodes of lattice ``src`` (SOLID corners weigh 0, the rest renormalised; a node with
    no fluid corner takes the nearest fluid node), E from ``src``'s surface node nearest to
    each of ``dst``'s SURFACE nodes (0 elsewhere).  The lattices are axis-aligned, so each
    axis's corners and weights are 1-D; a periodic-xy lattice wraps in x and y, any other is
    continued by its edge nodes."""
    nt = np.asarray(src.node_type)
    fluid = (nt != SOLID).astype(np.float64)
    lo, cells = [], []
    for a in range(3):
        n = nt.shape[a]
        # dst's node centres in src's index coordinates, the offset apart: a lattice onto
        # itself (or onto one with the same spacing whole nodes apart) lands on integers
        # exactly, not a rounding off them that mixes in a neighbour
        x = ((float(dst.origin[a]) - float(src.origin[a])) / src.h
             + (np.arange(dst.shape[a]) + 0.5) * (dst.h / src.h) - 0.5)
        if src.boundary == "periodic-xy" and a < 2:
            i0 = np.floor(x).astype(np.int64)
            lo.append((i0 % n, (i0 + 1) % n, x - i0))
            cells.append(np.rint(x).astype(np.int64) % n)
            continue
        x = np.clip(x, 0, n - 1)
        i0 = np.clip(np.floor(x).astype(np.int64), 0, max(n - 2, 0))
        lo.append((i0, np.minimum(i0 + 1, n - 1), x - i0))
        cells.append(np.clip(np.rint(x).astype(np.int64), 0, n - 1))
    extra = lam.shape[3:]
    num = np.zeros(tuple(dst.shape) + extra)
    den = np.zeros(tuple(dst.shape))
    for d in np.ndindex(2, 2, 2):
        idx = [lo[a][d[a]] for a in range(3)]
        w = [lo[a][2] if d[a] else 1.0 - lo[a][2] for a in range(3)]
        wf = (w[0][:, None, None] * w[1][None, :, None] * w[2][None, None, :]
              * fluid[np.ix_(*idx)])
        den += wf
        num += wf.reshape(wf.shape + (1,) * len(extra)) * lam[np.ix_(*idx)]
    out = num / np.maximum(den, 1e-30).reshape(den.shape + (1,) * len(extra))
    none = den <= 0
    near = np.ix_(*cells)
    if none.any():
        flat = _nearest_index(nt != SOLID)[near][none]
        out[none] = lam.reshape((-1,) + extra)[flat]
    e = np.zeros(tuple(dst.shape))
    surf = np.asarray(dst.node_type) == SURFACE
    if surf.any() and (nt == SURFACE).any():
        e = np.where(surf, irr.reshape(-1)[_nearest_index(nt == SURFACE)[near]], 0.0)
    return out, e


def _fog_support(scene: Scene, lattice):
    """The box with all the fog ((lo, hi), the fog's region within the domain; x, y of the
    lattice's box for a periodic-xy domain) and per axis the index range of the nodes inside
    it, or None (no fog, or no node inside)."""
    if scene.fog is None:
        return None
    dmin = np.asarray(scene.domain.min, float)
    dmax = np.asarray(scene.domain.max, float)
    lo, hi = dmin.copy(), dmax.copy()
    if scene.fog.region is not None:
        lo = np.maximum(lo, np.asarray(scene.fog.region[0], float))
        hi = np.minimum(hi, np.asarray(scene.fog.region[1], float))
    box_lo = np.asarray(lattice.origin, float)
    box_hi = box_lo + lattice.h * np.asarray(lattice.shape, float)
    ranges = []
    for a in range(3):
        if lattice.boundary == "periodic-xy" and a < 2:
            lo[a], hi[a] = box_lo[a], box_hi[a]
        x = box_lo[a] + (np.arange(lattice.shape[a]) + 0.5) * lattice.h
        inside = np.flatnonzero((x >= lo[a]) & (x <= hi[a]))
        if not len(inside):
            return None
        ranges.append((int(inside[0]), int(inside[-1])))
    return (tuple(lo.tolist()), tuple(hi.tolist())), ranges


def _clamped_index(shape, ranges) -> np.ndarray:
    """For every node the flat index of the node with each index clamped into ``ranges``."""
    idx = np.meshgrid(*[np.clip(np.arange(n), r[0], r[1]) for n, r in zip(shape, ranges)],
                      indexing="ij")
    return np.ravel_multi_index(tuple(idx), shape)


def _sun_path(scene: Scene, lattice, fog_box, ranges, sun_dir=None) -> np.ndarray:
    """∫ density ds from every node towards the sun, solids ignored, continued linearly outside
    the fog's box from its last two nodes along each axis (so that a camera's trilinear lookup
    between the last node inside and the first outside is the path from the point itself: 0 on
    a face the sun enters by).  Inside, a uniform fog: exactly, the distance to the box's face
    towards the sun; a density grid: :func:`sun_path` through the lattice's density
    (trapezoids, resampled sheet by sheet).  ``sun_dir``: towards the sun (default the
    scene's)."""
    s = np.asarray(scene.sun.direction if sun_dir is None else sun_dir, float)
    if scene.fog.density is None:  # uniform (density 1 in the box): t of the box's exit
        inside = [np.clip(np.arange(n), *r) for n, r in zip(lattice.shape, ranges)]
        P = np.moveaxis(lattice.node_positions()[np.ix_(*inside)], -1, 0)  # at clamped nodes
        path = np.full(lattice.shape, np.inf)
        axes = (2,) if lattice.boundary == "periodic-xy" else (0, 1, 2)
        for a in axes:
            if s[a] != 0:
                face = fog_box[1][a] if s[a] > 0 else fog_box[0][a]
                path = np.minimum(path, np.maximum((face - P[a]) / s[a], 0.0))
        path = np.where(np.isfinite(path), path, NO_SUN_PATH)  # no face towards the sun
    else:
        path = np.asarray(sun_path(jnp.asarray(lattice.fog_density, jnp.float32), s, lattice.h,
                                   lattice.boundary == "periodic-xy"), np.float64)
    return _continue_past_box(path, ranges, np)


def _camera_visibility(vis, near_fluid, sharp) -> np.ndarray:
    """The light solve's sun visibility at the nodes (nx, ny, nz) as the cameras read it:
    extended into solids from the nearest fluid node, then past the fog's box (``sharp``)."""
    v = np.asarray(vis).reshape(-1)[np.asarray(near_fluid)].reshape(-1)
    return v[np.asarray(sharp)].reshape(np.shape(vis))


def _continue_past_box(path, ranges, xp):
    """``path`` continued linearly past the fog's box (node index ``ranges`` per axis) from its
    last two nodes inside, axis by axis (NumPy or jax.numpy)."""
    for a, (i0, i1) in enumerate(ranges):
        n = path.shape[a]
        i = np.arange(n)
        take = lambda k: xp.take(path, np.full(n, k), axis=a)  # noqa: E731
        lo_slope = take(i0) - take(min(i0 + 1, i1))
        hi_slope = take(i1) - take(max(i1 - 1, i0))
        shape = [1, 1, 1]
        shape[a] = n
        below = np.clip(i0 - i, 0, None).reshape(shape)
        above = np.clip(i - i1, 0, None).reshape(shape)
        path = (xp.take(path, np.clip(i, i0, i1), axis=a) + below * lo_slope
                + above * hi_slope)
    return path


class CameraGeometry(eqx.Module):
    """Static maps that extend solver fields to every node for trilinear camera lookups."""

    near_fluid: jax.Array  # flat index of the nearest non-SOLID node
    fog_density: jax.Array | None  # exact hits: the density ignoring solids (Lattice.fog_density)
    near_surface: jax.Array  # flat index of the nearest SURFACE node
    normal: jax.Array  # (nx, ny, nz, 3) unit normals at SURFACE nodes, 0 elsewhere
    sdf: jax.Array
    origin: tuple[float, float, float] = eqx.field(static=True)
    h: float = eqx.field(static=True)
    sun_dir: tuple[float, float, float] | None = eqx.field(static=True)
    periodic_xy: bool = eqx.field(static=True)
    has_surfaces: bool = eqx.field(static=True)
    M: int = eqx.field(static=True, default=0)  # the light solve's direction half-width
    # exact hits with fog (``_fog_support``): the fog's box, and for every node the flat index
    # of the nearest node inside it (the fields are extended so that the fog ends sharply at
    # the box's face, where the march stops)
    fog_box: tuple | None = eqx.field(static=True, default=None)
    support_index: jax.Array | None = None
    # exact hits with fog and a sun: ∫ density ds towards the sun from every node (solids
    # ignored, continued linearly outside the fog's box) and the sun's visibility past the
    # solids (the light solve's: exact shadow rays box-filtered over each node's fluid, 1
    # without shapes; extended into solids from the nearest fluid node)
    sun_path: jax.Array | None = None
    sun_vis: jax.Array | None = None
    # the node index ranges of the fog's box per axis (``_fog_support``), for a traced density's
    # ``sun_path``; None without ``fog_box``
    support_ranges: tuple | None = eqx.field(static=True, default=None)
    # the sun's direction traced (an unknown; ``SweepModel.with_sun_derivatives``), near
    # ``sun_dir``; None: ``sun_dir``
    sun_vec: jax.Array | None = None

    @classmethod
    def build(cls, scene: Scene, lattice, exact_hits: bool = False,
              M: int = 0, visibility=None) -> "CameraGeometry":
        nt = np.asarray(lattice.node_type)
        periodic = lattice.boundary == "periodic-xy"
        surf = nt == SURFACE
        near_fluid = _nearest_index(nt != SOLID)
        # with exact hits the march may stop at the fog's face as it stops at a surface's; then
        # the sun's path is interpolated consistently with the fog's extinction there (with
        # the lattice's hits the fog fades over the last spacing, and the node-mean sun stays)
        support = (_fog_support(scene, lattice) if exact_hits and lattice.fog_density is not None
                   else None)
        fog_box = support_index = sun_path = sun_vis = ranges = None
        if support is not None:
            fog_box, ranges = support
            sharp = _clamped_index(lattice.shape, ranges)
            support_index = jnp.asarray(sharp)
            if scene.sun is not None:
                sun_path = jnp.asarray(_sun_path(scene, lattice, fog_box, ranges), jnp.float32)
                # the light solve's (``SweepGeometry.sun_vis``); None only without shapes (exact
                # hits exist only where the host casts exactly), where nothing shadows
                vis = np.ones(nt.shape) if visibility is None else np.asarray(visibility)
                sun_vis = jnp.asarray(_camera_visibility(vis, near_fluid, sharp))
        return cls(
            fog_box=fog_box, support_index=support_index, sun_path=sun_path, sun_vis=sun_vis,
            support_ranges=None if ranges is None else tuple(
                (int(a), int(b)) for a, b in ranges),
            near_fluid=jnp.asarray(near_fluid),
            fog_density=(jnp.asarray(lattice.fog_density, jnp.float32) if exact_hits
                         and lattice.fog_density is not None else None),
            near_surface=jnp.asarray(_nearest_index(surf)),
            sdf=jnp.asarray(lattice.sdf, jnp.float32),
            normal=jnp.asarray(np.where(surf[..., None], lattice.normal, 0.0), jnp.float32),
            origin=tuple(float(x) for x in lattice.origin),
            h=float(lattice.h),
            sun_dir=None if scene.sun is None else tuple(float(x) for x in scene.sun.direction),
            periodic_xy=periodic,
            has_surfaces=bool(surf.any()),
            M=int(M),
        )


def side_slopes(slope, sigma_t, periodic_xy: bool):
    """A node's source slope (nx, ny, nz, 3) towards each side (nx, ny, nz, 6: upper x, y, z,
    then lower), scaled by min(1, σ_t(neighbour)/σ_t(node)) on that side.

    A node's linear profile describes its own cell.  Where the neighbour holds as much fog the
    two profiles blend into one linear field between them, and the scale is 1; where it holds
    none (a cloud's top in a density grid) the fog the camera finds between them is the node's
    own — the density ramps to 0 over the spacing — and the node's extrapolation beyond its
    cell (towards the escaping surface) would read a source that is not there: its mean holds,
    as it does at a sharp face (the fog's box, whose extension copies the node and cancels the
    slope).  The ratio keeps it continuous as the neighbour's density goes to 0 (measured:
    issue 14's half-space whose density grid drops to 0 above z = 1 was +10–17% brighter than
    the same fog ending at a sharp face, `benchmarks/thick_top.py`).  Outside the lattice the
    neighbour is the node itself (1); periodic x, y wrap."""
    has = sigma_t > 0
    safe = jnp.where(has, sigma_t, 1.0)
    out_hi, out_lo = [], []
    for a in range(3):
        if periodic_xy and a < 2:
            up, dn = jnp.roll(sigma_t, -1, axis=a), jnp.roll(sigma_t, 1, axis=a)
        else:
            pad = [(0, 0)] * 3
            pad[a] = (1, 1)
            ext = jnp.pad(sigma_t, pad, mode="edge")
            n = sigma_t.shape[a]
            up = jax.lax.slice_in_dim(ext, 2, n + 2, axis=a)
            dn = jax.lax.slice_in_dim(ext, 0, n, axis=a)
        f_up = jnp.where(has, jnp.clip(up / safe, 0.0, 1.0), 1.0)
        f_dn = jnp.where(has, jnp.clip(dn / safe, 0.0, 1.0), 1.0)
        out_hi.append(slope[..., a] * f_up)
        out_lo.append(slope[..., a] * f_dn)
    return jnp.stack(out_hi + out_lo, axis=-1)


def _on_support(a, index):
    """A node field (nx, ny, nz) continued past the fog's box: each node takes the value of the
    node ``index`` names (``CameraGeometry.support_index``)."""
    return a.reshape(-1)[index].reshape(a.shape)


def camera_fields(cam: CameraGeometry, density, light: LightField, params: Params) -> LatticeFields:
    """The node fields a camera marches through, from a converged light field.

    Extinction and the multiply scattered source use the solver's δ-M scaling ζ' = ζ(1 − f)
    (``SweepSolver.phase_order`` L: f = g^(L+1); L = 0 is the δ-isotropic ζ(1 − g), exact for
    g = 0), with the source's angular part from the light's moments when L > 0; the sun's
    single scattering uses the full ζ with the Henyey–Greenstein phase (for L > 0 the
    uncollided sun is attenuated as the solve's beam is: the true extinction less the forward
    peak that the beam keeps, ``LightField.sun_peak``).
    Values are extended from the nearest fluid node into solids and from the nearest SURFACE
    node for the radiosity, so that trilinear interpolation near a surface stays sensible.
    With exact hits the density is the fog's own, ignoring solids (``cam.fog_density``): the
    march stops at the exact surface, and the fog reaches it.
    """
    dt = params.scattering.dtype
    ext = lambda a, idx: a.reshape(-1)[idx]  # noqa: E731
    if cam.fog_density is not None:
        dens = cam.fog_density.astype(dt)
    else:
        dens = ext(density.astype(dt), cam.near_fluid)
    K = 0 if light.moments is None else light.moments.shape[-1]
    order = math.isqrt(K + 1) - 1
    f, coef = moment_coefficients(params.g, order, cam.M, jnp)
    zeta_r = params.scattering * (1.0 - f)
    sigma_t = (zeta_r + params.absorption) * dens
    j_iso = zeta_r * dens * ext(light.fluence + light.sky_fluence, cam.near_fluid) / FOUR_PI
    # the sun's beam loses what scatters out of it: δ-scaled as the light solve's first
    # collision is (order 0), else all but the forward peak the solve's beam keeps
    # (``LightField.sun_peak``)
    peak = 0.0 if light.sun_peak is None else light.sun_peak[0].astype(dt)
    sun_extinction = (zeta_r if order == 0 else params.scattering * (1.0 - peak)
                      ) + params.absorption
    sun_depth = None
    if cam.sun_path is not None:  # the march attenuates the sun itself, along its own profile
        j_sun = params.scattering * dens * params.sun_irradiance * cam.sun_vis.astype(dt)
        sun_depth = sun_extinction * cam.sun_path.astype(dt)
    else:
        j_sun = params.scattering * dens * ext(light.sun_fluence, cam.near_fluid)
    j_slope = None
    if light.fluence_slope is not None:  # the linear scheme: each node's source changes within it
        j_slope = (zeta_r * dens / FOUR_PI)[..., None] * jax.vmap(
            lambda a: ext(a, cam.near_fluid), in_axes=-1, out_axes=-1)(light.fluence_slope)
    j_aniso = None
    if order > 0:
        mom = light.moments if light.sky_moments is None else light.moments + light.sky_moments
        aniso = coef * mom
        if light.once_source is not None:  # the once-scattered sun's (``SweepSolver.once_M``)
            aniso = aniso + light.once_source
        aniso = jax.vmap(lambda a: ext(a, cam.near_fluid), in_axes=-1, out_axes=-1)(aniso)
        j_aniso = (zeta_r * dens)[..., None] * aniso
    if cam.support_index is not None:  # the fog ends sharply at its box: extend it there
        sup = lambda a: _on_support(a, cam.support_index)  # noqa: E731
        sup_k = jax.vmap(sup, in_axes=-1, out_axes=-1)
        sigma_t, j_iso, j_sun = sup(sigma_t), sup(j_iso), sup(j_sun)
        j_slope = None if j_slope is None else sup_k(j_slope)
        j_aniso = None if j_aniso is None else sup_k(j_aniso)
    if j_slope is not None:
        j_slope = side_slopes(j_slope, sigma_t, cam.periodic_xy)
    if cam.has_surfaces:
        rad = ext(light.radiosity, cam.near_surface)
        irr = ext(light.irradiance, cam.near_surface)
    else:
        rad = irr = jnp.zeros_like(sigma_t)
    return LatticeFields(
        sigma_t=sigma_t,
        j_iso=j_iso,
        j_sun=j_sun,
        radiosity_ext=rad,
        sdf=cam.sdf.astype(dt),
        origin=cam.origin,
        h=cam.h,
        g=params.g,
        sun_dir=cam.sun_dir,
        sky=params.sky_radiance,
        periodic_xy=cam.periodic_xy,
        surface_normal=cam.normal.astype(dt) if cam.has_surfaces else None,
        irradiance=irr if cam.has_surfaces else None,
        albedo=params.albedo,
        emission=params.emission,
        sun_irradiance=params.sun_irradiance,
        sun_extinction=sun_extinction,
        sun_window=None if light.sun_peak is None else light.sun_peak[1:].astype(dt),
        j_aniso=j_aniso,
        harmonics=None if order == 0 else (order, cam.M),
        j_slope=j_slope,
        sun_depth=sun_depth,
        fog_box=cam.fog_box,
        sun_vec=cam.sun_vec,
    )


def _with_static(module: eqx.Module, **fields) -> eqx.Module:
    """A copy of ``module`` with these fields (static ones too, which ``eqx.tree_at`` cannot
    reach) replaced, without running its ``__init__`` (a ``SweepModel``'s builds the lattice)."""
    out = jax.tree_util.tree_map(lambda x: x, module)  # a new instance, unflattened
    for k, v in fields.items():
        object.__setattr__(out, k, v)
    return out


def _pad_rays(a, pad: int):
    """(N, ...) per-ray ``a`` with ``pad`` copies of its first ray appended."""
    if pad <= 0:
        return a
    h = np.asarray(a)  # on the host: eager device ops would compile for every new count
    return jnp.asarray(np.concatenate([h, np.broadcast_to(h[:1], (pad,) + h.shape[1:])]))


def _pad_hits(hits: RayHits, pad: int) -> RayHits:
    """``hits`` with ``pad`` copies of its first ray of weight 0 appended (finite values that
    add nothing to its pixel, nor to any derivative)."""
    if pad <= 0:
        return hits
    out = jax.tree_util.tree_map(lambda a: _pad_rays(a, pad), hits)
    w = np.array(out.weight)
    w[-pad:] = 0.0
    return eqx.tree_at(lambda r: r.weight, out, jnp.asarray(w))


def _same_march(a: float | None, b: float | None, h: float) -> bool:
    """Whether two cameras' longest fog segments give the march the same step count at its
    default step (``_march.march_steps``)."""
    if a is None or b is None:
        return a is None and b is None
    step = march_step(h)
    return step_count(a, step) == step_count(b, step)


def _hit_points(hits: RayHits) -> tuple[np.ndarray, np.ndarray]:
    """(points (R, 3) where each ray meets a shape (its origin where it meets none), the rays
    that meet one (R,) bool), on the host in float64."""
    t = np.asarray(hits.t, np.float64)
    m = np.isfinite(t)
    p = (np.asarray(hits.origins, np.float64)
         + np.where(m, t, 0.0)[:, None] * np.asarray(hits.directions, np.float64))
    return p, m


class HitSunPlan(eqx.Module):
    """One camera's exact hits: the samples of their path towards the sun
    (``geometry._hits.sun_depth_plan``), for a traced density."""

    start: jax.Array  # (R, 3)
    j0: jax.Array  # (R,) int32
    count: jax.Array  # (R,) int32
    t_end: jax.Array  # (R,) the path's length in steps
    steps: int = eqx.field(static=True)  # the largest count
    ds: float = eqx.field(static=True)


class DensityOperators(eqx.Module):
    """What a traced density grid (``Params.density``) needs on the device: the lattice's
    ``DensityMap`` (its fields as device arrays) and, per camera with exact hits, the samples of
    each hit's path towards the sun (the same midpoint rule as the host's
    ``geometry._hits.sun_depth``, through the traced density: the same values at the scene's
    grid, and exact gradients).  A traced grid must be 0 where the scene's grid is 0 (the
    samples are those that can meet fog)."""

    at_node: tuple[jax.Array, jax.Array, jax.Array]
    in_cell: tuple[jax.Array, jax.Array, jax.Array]
    keep: jax.Array
    src: jax.Array
    dst: jax.Array
    moved: jax.Array
    hit_plans: tuple[HitSunPlan, ...] | None
    grid_shape: tuple[int, int, int] = eqx.field(static=True)

    @classmethod
    def build(cls, lattice, hits, sun_dir, fog_box, fog) -> "DensityOperators":
        """``fog``: the density the host's hits integrate (the fog's own, continued past its
        box), at the scene's grid."""
        from ...geometry._hits import sun_depth_plan

        m = lattice.density_map
        plans = None
        if hits is not None and sun_dir is not None:
            plans = []
            for h in hits:
                p, _ = _hit_points(h)
                q, j0, n, te = sun_depth_plan(p, np.asarray(h.sun_cos) > 0, sun_dir, fog,
                                              lattice.origin, lattice.h, box=fog_box)
                plans.append(HitSunPlan(start=jnp.asarray(q), j0=jnp.asarray(j0, jnp.int32),
                                        count=jnp.asarray(n, jnp.int32), t_end=jnp.asarray(te),
                                        steps=int(n.max(initial=0)), ds=0.5 * lattice.h))
            plans = tuple(plans)
        dev = lambda a: tuple(jnp.asarray(x) for x in a)  # noqa: E731
        return cls(at_node=dev(m.at_node), in_cell=dev(m.in_cell), keep=jnp.asarray(m.keep),
                   src=jnp.asarray(m.src, jnp.int32), dst=jnp.asarray(m.dst, jnp.int32),
                   moved=jnp.asarray(m.moved), hit_plans=plans, grid_shape=tuple(m.grid_shape))


def _hit_sun_depth(fog, plan: HitSunPlan, sun_dir, origin, h: float, periodic_xy: bool):
    """∫ fog ds towards the sun from each hit (``HitSunPlan``): the midpoint rule through the
    trilinear field, one sample of every ray per step (rematerialized in reverse mode: the
    gradient keeps one (R,) vector per step, not the stencils)."""
    dt = fog.dtype
    R = plan.start.shape[0]
    if plan.steps == 0:
        return jnp.zeros(R, dt)
    table = _flat_table([fog], dt)
    geo = (np.asarray(origin, np.float64), h, tuple(fog.shape), periodic_xy)
    s = jnp.asarray(np.asarray(sun_dir, np.float64) / np.linalg.norm(sun_dir), dt)
    start, te = plan.start.astype(dt), plan.t_end.astype(dt)

    @jax.checkpoint
    def body(acc, k):
        j = plan.j0 + k
        x = start + ((j.astype(dt) + 0.5) * plan.ds)[:, None] * s
        w = jnp.where(k < plan.count, jnp.clip(te - j.astype(dt), 0.0, 1.0), 0.0)
        return acc + w * _interp(table, x, geo)[:, 0], None

    acc, _ = jax.lax.scan(body, jnp.zeros(R, dt), jnp.arange(plan.steps))
    return acc * plan.ds


#: the sun's angles' step (degrees) of the central differences that linearize the host's sun
#: quantities (``SweepModel.with_sun_derivatives``): a shadow edge moves by ~1/60 of the
#: occluder's height per degree, so that at the fits' pixel sizes a few rays change sides
SUN_STEP_DEG = 1.0


class SunLinearization(eqx.Module):
    """The sun's quantities the host computes (from exact shadow rays and the fog's geometry),
    linearized in the sun's angles about the model's own sun: their derivatives by zenith and
    azimuth (per degree, central differences of ±``step`` degrees), each a pair (d/dzenith,
    d/dazimuth) of arrays shaped like the quantity, or None where the model has none."""

    vis: tuple[jax.Array, jax.Array] | None  # the light solve's sun_vis (nodes)
    cam_vis: tuple[jax.Array, jax.Array] | None  # the cameras' sun_vis
    cam_path: tuple[jax.Array, jax.Array] | None  # the cameras' sun_path
    hit_cos: tuple[tuple[jax.Array, jax.Array], ...] | None  # per camera: RayHits.sun_cos
    hit_depth: tuple[tuple[jax.Array, jax.Array], ...] | None  # per camera: RayHits.sun_depth
    # the angles it is linearized about and the differences' step (degrees), as arrays, not
    # static: a model rebuilt at another sun then runs the programs compiled for the first
    # (``traced_sun_form``)
    zenith: jax.Array
    azimuth: jax.Array
    step: jax.Array


class SweepModel(AbstractForwardModel):
    """The sweep's forward model (final): a scene prepared for repeated, differentiable renders.

    Build it with :func:`difffog.forward_model` (``solver="sweep"``) or directly:

    scene: the scene.
    resolution: lattice nodes along the longest domain axis.
    solver: the light solve's configuration (default ``SweepSolver(M=3)``).
    supersample: s×s stratified rays per pixel (box filter).
    cameras: names of the cameras to render (default: all), or Camera objects (e.g. reduced).
    edge_samples: rays of a pixel that straddles an edge (Hammersley points, default 16): its
        coverage of each side is right to ~1/(2·edge_samples) of the pixel's width.  A fit
        that reduces its cameras k-fold uses 16·k, so that a reduced pixel's edges are placed
        as finely as a full pixel's.

    Camera rays meet the shapes exactly (``hits``: cast on the host once per camera, see
    ``_march.RayHits``); only a periodic-xy domain with shapes (which the host caster does not
    repeat across the periodic sides) finds its hits on the lattice's signed distance instead.
    """

    scene: Scene = eqx.field(static=True)
    cameras: tuple[Camera, ...] = eqx.field(static=True)
    solver: SweepSolver
    geometry: SweepGeometry
    camera_geometry: CameraGeometry
    density: jax.Array
    hits: tuple[RayHits, ...] | None
    density_ops: DensityOperators | None  # a density grid's linear maps (``Params.density``)
    sun_lin: SunLinearization | None  # the sun as an unknown (``with_sun_derivatives``)
    resolution: int = eqx.field(static=True)
    supersample: int = eqx.field(static=True)
    edge_samples: int = eqx.field(static=True)
    host: HostInfo = eqx.field(static=True)
    # the cameras' marches (``render_cameras``' lanes): None, the backend's choice (one on a
    # CPU, one per camera on a GPU; ``march_lanes``); a benchmark may ask for more
    march_lanes: int | None = eqx.field(static=True)

    def __init__(self, scene: Scene, *, resolution: int = 64, solver: SweepSolver | None = None,
                 supersample: int = 2, cameras=None, edge_samples: int = EDGE_SAMPLES):
        check_point_sun(scene)  # before any work
        self.scene = scene
        self.solver = solver if solver is not None else SweepSolver()
        self.supersample = int(supersample)
        self.edge_samples = int(edge_samples)
        if self.edge_samples < 1:
            raise SceneError(f"edge_samples={edge_samples!r}: give a positive number of rays "
                             f"for a pixel that straddles an edge (default {EDGE_SAMPLES})")
        self.resolution = int(resolution)
        self.cameras = select_cameras(scene, cameras)
        t = time.perf_counter()
        M = self.solver.M
        shell = self.solver.lattice_M(scene)
        lattice = voxelize(scene, resolution, shell, margin=VACUUM_MARGIN)
        voxelize_s = time.perf_counter() - t
        t = time.perf_counter()
        self.geometry = self.solver.prepare(scene, lattice)
        periodic = lattice.boundary == "periodic-xy"
        exact = casts_exactly(scene)
        self.camera_geometry = CameraGeometry.build(scene, lattice, exact, M,
                                                    visibility=self.geometry.sun_vis)
        # what the cameras sample: the fog's own density (0 in solids), not the cells' volume
        # bookkeeping of ``lattice.density`` (larger beside surfaces)
        own = lattice.density if lattice.fog_density is None else np.where(
            lattice.node_type == SOLID, 0.0, lattice.fog_density)
        self.density = jnp.asarray(own, jnp.float32)
        prepare_s = time.perf_counter() - t
        t = time.perf_counter()
        hit_fog = None  # the density the hits' sun depth integrates
        if exact:
            fog = lattice.fog_density if lattice.fog_density is not None else lattice.density
            # the sun's depth at the hits: through the fog's box exactly, the fog continued to
            # its faces from the outer nodes (the camera geometry's support, as its march sees it)
            cg, sun_box = self.camera_geometry, None
            if cg.support_index is not None:
                sharp = np.asarray(cg.support_index)
                fog, sun_box = np.asarray(fog).reshape(-1)[sharp].reshape(sharp.shape), cg.fog_box
            self.hits = tuple(
                camera_hits(scene, c, self.supersample, fog, lattice.origin, lattice.h,
                            lattice.shape, periodic, edge_samples=self.edge_samples,
                            sun_box=sun_box) for c in self.cameras)
            hit_fog = np.asarray(fog)
        else:
            self.hits = None
        self.density_ops = (None if lattice.density_map is None else DensityOperators.build(
            lattice, self.hits, self.camera_geometry.sun_dir, self.camera_geometry.fog_box,
            hit_fog))
        self.sun_lin = None
        self.march_lanes = None
        self.host = HostInfo(lattice=lattice, hit_fog=hit_fog, setup_s={
            "voxelize_s": voxelize_s, "prepare_s": prepare_s,
            "camera_hits_s": time.perf_counter() - t})

    def at_resolution(self, resolution: int) -> "SweepModel":
        """The same model (scene, cameras, solver, supersampling) on another lattice."""
        return self.with_solver(self.solver, resolution)

    def with_solver(self, solver: SweepSolver, resolution: int | None = None) -> "SweepModel":
        """The same model (scene, cameras, supersampling; its lattice resolution unless
        ``resolution`` is given) with another light solve, e.g. another direction set M (the
        lattice is built anew: its surface shell follows M)."""
        out = SweepModel(self.scene, resolution=self.resolution if resolution is None
                         else resolution, solver=solver, supersample=self.supersample,
                         cameras=self.cameras, edge_samples=self.edge_samples)
        return out if self.sun_lin is None else out.with_sun_derivatives(
            float(self.sun_lin.step))

    def at_sun(self, zenith_deg: float, azimuth_deg: float, step_deg: float | None = None
               ) -> "SweepModel":
        """The same model built with its scene's sun at these angles, and the sun's derivatives
        where this model has them (with ``step_deg``, default this model's step)."""
        import dataclasses

        if self.scene.sun is None:
            raise SceneError("at_sun: the scene has no [sun]")
        scene = self.scene.replace(sun=dataclasses.replace(
            self.scene.sun, zenith_deg=float(zenith_deg), azimuth_deg=float(azimuth_deg)))
        out = SweepModel(scene, resolution=self.resolution, solver=self.solver,
                         supersample=self.supersample, cameras=self.cameras,
                         edge_samples=self.edge_samples)
        if self.sun_lin is None and step_deg is None:
            return out
        return out.with_sun_derivatives(float(self.sun_lin.step) if step_deg is None
                                        else step_deg)

    def with_sun_derivatives(self, step_deg: float = SUN_STEP_DEG) -> "SweepModel":
        """This model with the sun's angles as parameters it can trace (``sun.zenith_deg``,
        ``sun.azimuth_deg``; :func:`difffog.set_param`).  The light solve's beam, the surfaces'
        cosines and the sun's phase follow the traced direction exactly; what the host computes
        from the scene's geometry (the shapes' shadows from exact rays, the fog's path towards
        the sun) is linearized about the model's own sun by central differences of
        ±``step_deg`` degrees (four more host passes).  Exact at the model's sun, first order
        near it (a shadow's edge is where its rays change sides, so its derivative is a
        difference, not a derivative of a smooth function): build the model again at the
        estimated sun to render it exactly there (``difffog.fit`` does)."""
        sun = self.scene.sun
        if sun is None:
            raise SceneError("sun.zenith_deg / sun.azimuth_deg: the scene has no [sun] to "
                             "move; add one (its angles are the start)")
        step = float(step_deg)
        if not 0.0 < step <= 10.0:
            raise SceneError(f"with_sun_derivatives: step_deg={step_deg!r} must lie in (0, 10] "
                             f"degrees (default {SUN_STEP_DEG:g})")
        from ...geometry._hits import sun_depth, sun_visibility

        lat, geom, cg = self.lattice, self.geometry, self.camera_geometry
        ranges = cg.support_ranges

        def quantities(s):
            out = {}
            if geom.sun_vis is not None:
                vis = sun_visibility(self.scene, lat.shape, lat.origin, lat.h, s)
                out["vis"] = vis
                if cg.sun_vis is not None:
                    out["cam_vis"] = _camera_visibility(vis, cg.near_fluid, cg.support_index)
            elif cg.sun_vis is not None:
                out["cam_vis"] = np.asarray(cg.sun_vis)  # no shapes: nothing shadows
            if cg.sun_path is not None:
                out["cam_path"] = _sun_path(self.scene, lat, cg.fog_box, ranges, s)
            if self.hits is not None:
                cos, depth = [], []
                for h in self.hits:
                    p, m = _hit_points(h)
                    c, d = np.zeros(len(m)), np.zeros(len(m))
                    if m.any():
                        c[m], d[m] = sun_depth(self.scene, p[m],
                                               np.asarray(h.normal, np.float64)[m], s,
                                               self.host.hit_fog, lat.origin, lat.h,
                                               box=cg.fog_box)
                    cos.append(c)
                    depth.append(d)
                out["hit_cos"], out["hit_depth"] = cos, depth
            return out

        z, a = float(sun.zenith_deg), float(sun.azimuth_deg)
        q = {k: quantities(sun_vector(z + dz, a + da))
             for k, (dz, da) in {"z+": (step, 0), "z-": (-step, 0), "a+": (0, step),
                                 "a-": (0, -step)}.items()}

        def deriv(key, i=None):
            if key not in q["z+"]:
                return None
            pick = (lambda d: d[key]) if i is None else (lambda d: d[key][i])  # noqa: E731
            f32 = lambda x: jnp.asarray(np.asarray(x, np.float64), jnp.float32)  # noqa: E731
            return (f32((pick(q["z+"]) - pick(q["z-"])) / (2 * step)),
                    f32((pick(q["a+"]) - pick(q["a-"])) / (2 * step)))

        n_cam = len(self.hits) if self.hits is not None else 0
        lin = SunLinearization(
            vis=deriv("vis"), cam_vis=deriv("cam_vis"), cam_path=deriv("cam_path"),
            hit_cos=tuple(deriv("hit_cos", i) for i in range(n_cam)) if n_cam else None,
            hit_depth=tuple(deriv("hit_depth", i) for i in range(n_cam)) if n_cam else None,
            zenith=jnp.asarray(z), azimuth=jnp.asarray(a), step=jnp.asarray(step))
        return eqx.tree_at(lambda m: m.sun_lin, self, lin, is_leaf=lambda x: x is None)

    def _with_sun(self, params: Params, geom, cg, hits):
        """(solver geometry, camera geometry, hits) at ``params``' sun (the host's when its
        angles are not traced): the traced direction where the device computes with it, the
        host's quantities moved along their derivatives (``with_sun_derivatives``)."""
        s = sun_direction_of(params, self.scene)
        if s is None:
            return geom, cg, hits
        lin = self.sun_lin
        if lin is None:
            raise SceneError("sun.zenith_deg / sun.azimuth_deg are traced, but this model was "
                             "built without the sun's derivatives: use "
                             "model.with_sun_derivatives() (difffog.fit does)")
        if params.density is not None:
            raise SceneError("the sun's angles and fog.density cannot be traced together yet: "
                             "fit the density under a known sun, or the sun with the scene's "
                             "density")
        dt = params.scattering.dtype
        dz = get_param(params, self.scene, "sun.zenith_deg").astype(dt) - lin.zenith.astype(dt)
        da = get_param(params, self.scene, "sun.azimuth_deg").astype(dt) - lin.azimuth.astype(dt)

        def moved(v, d, clip=True):  # a visibility or a cosine stays in [0, 1]; a path not
            # (the cameras' is continued linearly past the fog's box, negative beyond a face)
            out = v.astype(dt) + d[0].astype(dt) * dz + d[1].astype(dt) * da
            return jnp.clip(out, 0.0, 1.0) if clip else out

        normal = geom.normal.astype(dt)
        cos = jnp.where(geom.surf, jnp.maximum(normal @ s, 0.0), 0.0)
        geom = eqx.tree_at(lambda g: (g.sun_cos, g.sun_vec), geom, (cos, s),
                           is_leaf=lambda x: x is None)
        if geom.once is not None:  # the once-scattered sweep's phase follows the sun too
            geom = eqx.tree_at(lambda g: g.once.sun_vec, geom, s, is_leaf=lambda x: x is None)
        if lin.vis is not None:
            geom = eqx.tree_at(lambda g: g.sun_vis, geom, moved(geom.sun_vis, lin.vis))
        cg = eqx.tree_at(lambda c: c.sun_vec, cg, s, is_leaf=lambda x: x is None)
        if lin.cam_vis is not None:
            cg = eqx.tree_at(lambda c: c.sun_vis, cg, moved(cg.sun_vis, lin.cam_vis))
        if lin.cam_path is not None:
            cg = eqx.tree_at(lambda c: c.sun_path, cg, moved(cg.sun_path, lin.cam_path, False))
        if hits is not None and lin.hit_cos is not None:
            hits = tuple(eqx.tree_at(lambda r: (r.sun_cos, r.sun_depth), h,
                                     (moved(h.sun_cos, dc), moved(h.sun_depth, dd, False)))
                         for h, dc, dd in zip(hits, lin.hit_cos, lin.hit_depth))
        return geom, cg, hits

    def traced_sun_form(self, paths, like: "SweepModel | None" = None) -> "SweepModel":
        """This model for programs that trace the sun's angles ``paths`` (a fit's): the same
        images and derivatives wherever those angles are traced, shaped to share the programs
        compiled for ``like`` (the form of this model built at another sun: a fit's last
        round).

        What a model holds static about its own sun (the scene's traced angles, the beam's
        direction) enters a traced-sun program only through the beam's sheet order
        (``_uncollided.beam_frame_key``), so where that agrees with ``like``'s, ``like``'s
        stand in for them; the cameras' exact rays are padded to ``like``'s counts with rays
        of weight 0 (or, without ``like``, by a sixteenth, so that a later round whose edge
        pixels moved still fits).  Where they do not agree (the sun crossed a sheet order, a
        camera gained more rays than the padding holds) the form differs and compiles anew:
        slower, never wrong."""
        import dataclasses

        from ._uncollided import beam_frame_key

        if self.sun_lin is None:
            raise SceneError("traced_sun_form: this model has no sun derivatives "
                             "(with_sun_derivatives)")
        out = self
        if self.hits is not None:
            hits, cos, depth = [], [], []
            lin = self.sun_lin
            for i, h in enumerate(self.hits):
                n = int(h.weight.shape[0])
                want = n + max(16, -(-n // 16))
                max_length = h.max_length
                if like is not None and like.hits is not None and len(like.hits) == len(self.hits):
                    other = like.hits[i]
                    if int(other.weight.shape[0]) >= n:
                        want = int(other.weight.shape[0])
                    if _same_march(h.max_length, other.max_length, self.camera_geometry.h):
                        max_length = other.max_length
                hits.append(_with_static(_pad_hits(h, want - n), max_length=max_length))
                if lin.hit_cos is not None:
                    cos.append(tuple(_pad_rays(d, want - n) for d in lin.hit_cos[i]))
                    depth.append(tuple(_pad_rays(d, want - n) for d in lin.hit_depth[i]))
            out = eqx.tree_at(lambda m: m.hits, out, tuple(hits))
            if lin.hit_cos is not None:
                out = eqx.tree_at(lambda m: (m.sun_lin.hit_cos, m.sun_lin.hit_depth), out,
                                  (tuple(cos), tuple(depth)))
        if like is None or like.scene.sun is None:
            return out
        periodic = self.geometry.periodic_xy
        if beam_frame_key(self.geometry.sun_dir, periodic) != beam_frame_key(
                like.geometry.sun_dir, periodic):
            return out
        attrs = [SUN_PATHS[p][1] for p in paths if p in SUN_PATHS]  # the Sun's attribute
        sun = dataclasses.replace(self.scene.sun,
                                  **{a: getattr(like.scene.sun, a) for a in attrs})
        return _with_static(
            out, scene=self.scene.replace(sun=sun),
            geometry=_with_static(out.geometry, sun_dir=like.geometry.sun_dir),
            camera_geometry=_with_static(out.camera_geometry,
                                         sun_dir=like.camera_geometry.sun_dir))

    @property
    def lattice(self) -> Lattice:
        """The voxelized scene (host NumPy arrays)."""
        return self.host.lattice

    def check(self, params: Params) -> None:
        if self.geometry.terms is not None:
            check_terms(self.geometry.terms, params)

    def zero_light_state(self, dtype):
        """(Λ, E) zeros, the shape of ``LightField.state``: where ``light(params, init=...)``
        starts when it starts from nothing."""
        return zero_state(self.geometry, dtype)

    def resampled_state(self, state, source: "SweepModel"):
        """``source``'s light state (``LightField.state`` of a solve with ``source``) carried
        onto this model's lattice: a guess to start this model's light solve from
        (``light(params, init=...)``) when it renders the same scene at the same parameters
        on another lattice or direction set (a fit's model error renders finer models at
        the estimate).  Λ (and its moments) trilinear between the source's fluid nodes, E
        from the source's nearest surface node.  The solve's answer does not depend on the
        guess (only its iterations do).  None where the states do not correspond (another
        number of moments)."""
        src, dst = source.lattice, self.lattice
        if tuple(source.geometry.fluence_shape[3:]) != tuple(self.geometry.fluence_shape[3:]):
            return None
        lam, irr = (np.asarray(a, np.float64) for a in state)
        out, e = _resample(lam, irr, src, dst)
        return (jnp.asarray(out, state[0].dtype), jnp.asarray(e, state[1].dtype))

    def edge_pixels(self) -> dict[str, np.ndarray] | None:
        """{camera: (H, W) bool}: pixels that straddle a geometric or a shadow edge, from the
        cameras' exact hits (``_march.edge_pixels``); None where the cameras find their hits
        on the lattice (a periodic-xy domain with shapes)."""
        if self.hits is None:
            return None
        return {c.name: edge_pixels(h, c.height, c.width) for c, h in zip(self.cameras, self.hits)}

    def step_warning(self, params: Params) -> str | None:
        """Warn above a step optical depth σ_t·h·M of 1 (``THICK_STEP``)."""
        lat = self.lattice
        try:
            peak = lat.peak_density if params.density is None else float(jnp.max(params.density))
            # (the solve's M: the lattice's is the once-scattered sweep's K where that is
            # larger, for its margin, and that sweep is sub-stepped)
            depth = step_depth(params.scattering, params.absorption, params.g,
                               self.geometry.order, peak, lat.h, self.geometry.M)
        except (TypeError, jax.errors.ConcretizationTypeError):  # traced or batched: no check
            return None
        if depth <= THICK_STEP:
            return None
        need = math.ceil(self.resolution * depth / THICK_STEP)
        if self.geometry.substep:
            how = ("with sub-stepped segments a thick cube of fog 32 nodes across reads 2-3% "
                   "dark")
        elif self.solver.first_collision == "beam":
            how = ("a sunlit one gains light, which first_collision=deposit conserves, and "
                   "scheme=\"substep\" (slower) resolves")
        else:
            how = "a sunlit one reads dark; scheme=\"substep\" (slower) resolves it"
        shown = f"{depth:.3g}" if float(f"{depth:.3g}") > THICK_STEP else f"{depth:.6g}"
        return (f"one lattice step is optically thick (σ_t·h·M = {shown} > {THICK_STEP:g} at "
                f"resolution {self.resolution}, M = {self.solver.M}): the light is coarse inside "
                f"the fog: thick fog's lit surface can read 5-30% off ({how}) and the light "
                f"through it (a cloud's base, its shadow) several times off (docs/validation.md, "
                f"\"Slabs as cameras see them\"); resolution >= {need} (or a smaller M) brings "
                f"the step to {THICK_STEP:g}")

    def layer_warning(self, params: Params) -> str | None:
        """Warn when the fog is a thin layer across a periodic domain: fog in at least half of
        the lattice's columns, their median vertical optical depth (δ-scaled, as the step
        depth) below ``THIN_LAYER``."""
        lat = self.lattice
        if getattr(lat, "boundary", "open") != "periodic-xy" or params.density is not None:
            return None
        try:
            sigma = step_depth(params.scattering, params.absorption, params.g,
                               self.geometry.order, 1.0, 1.0, 1)
        except (TypeError, jax.errors.ConcretizationTypeError):  # traced or batched: no check
            return None
        col = sigma * lat.h * np.asarray(lat.density, np.float64).sum(-1)  # 0 at SOLID nodes
        fog = col > 0
        if fog.sum() < 0.5 * fog.size:
            return None
        tau = float(np.median(col[fog]))
        if tau >= THIN_LAYER:
            return None
        return (f"the fog is a thin layer across the periodic domain (median vertical optical "
                f"depth {tau:.2g} < {THIN_LAYER:g}): the lattice's horizontal directions never "
                f"leave it, so its multiply scattered light is overestimated (a haze of optical "
                f"depth 0.1 renders +10% at M = 2, +6% at M = 3, +3% at M = 5; "
                f"docs/validation.md); a larger M (now {self.solver.M}) lowers it")

    def _with_density(self, params: Params, cameras: bool = True):
        """(solver geometry, camera geometry, the cameras' density, hits) for ``params``: the
        host's, or with ``params.density`` (a traced grid) mapped onto the lattice (without
        ``cameras``, the cameras' three are the host's: the light solve needs none of them)."""
        if params.density is None:
            return self.geometry, self.camera_geometry, self.density, self.hits
        ops = self.density_ops
        if ops is None:
            raise SceneError(
                "fog.density: this model's scene has a uniform fog, so its density is not a "
                "grid it can trace; give the scene's fog a density grid (e.g. "
                "scene.replace(fog=dataclasses.replace(scene.fog, density=np.ones((16,) * 3))))")
        dt = params.scattering.dtype
        fog, dens = apply_density_map(ops, params.density.astype(dt), jnp)
        solid = self.geometry.solid
        geom = eqx.tree_at(lambda g: g.density, self.geometry, jnp.where(solid, 0.0, dens))
        cg, hits = self.camera_geometry, self.hits
        if not cameras:
            return geom, cg, self.density, hits
        if cg.fog_density is not None:
            cg = eqx.tree_at(lambda c: c.fog_density, cg, fog)
        if cg.sun_path is not None:
            path = _continue_past_box(sun_path(fog, cg.sun_dir, cg.h, cg.periodic_xy),
                                      cg.support_ranges, jnp)
            cg = eqx.tree_at(lambda c: c.sun_path, cg, path)
        if hits is not None and ops.hit_plans is not None:
            ext = fog if cg.support_index is None else _on_support(fog, cg.support_index)
            hits = tuple(
                eqx.tree_at(lambda r: r.sun_depth, h, _hit_sun_depth(
                    ext, plan, cg.sun_dir, cg.origin, cg.h, cg.periodic_xy))
                for h, plan in zip(hits, ops.hit_plans))
        return geom, cg, jnp.where(solid, 0.0, fog), hits

    def light(self, params: Params, init=None) -> LightField:
        """The light field at ``params``; ``init``: a light state to start the iteration from
        (``LightField.state`` of a solve on this model at nearby parameters: a fit's last
        step), else zero."""
        geom, cg, _, hits = self._with_density(params, cameras=False)
        geom, *_ = self._with_sun(params, geom, cg, None)
        return self.solver.solve(geom, params, init)

    def images_from(self, light: LightField, params: Params) -> dict[str, jax.Array]:
        geom, cg, density, hits = self._with_density(params)
        _, cg, hits = self._with_sun(params, geom, cg, hits)
        f = camera_fields(cg, density, light, params)
        images = render_cameras(f, self.cameras, supersample=self.supersample, hits=hits,
                                lanes=self.march_lanes)
        return {c.name: img for c, img in zip(self.cameras, images)}

    def settings(self) -> dict:
        lat = self.lattice
        s = self.solver
        return {
            "scene": self.scene.title,
            "solver": "sweep",
            "solver_options": {"M": s.M, "method": s.method, "max_iterations": s.max_iterations,
                               "tol": s.tol, "sky_quadrature": s.sky_quadrature,
                               "terms": s.terms, "devices": s.devices,
                               "precondition": s.resolved_precondition(self.geometry),
                               "phase_order": self.geometry.order,
                               "scheme": ("linear" if self.geometry.linear else
                                          "substep" if self.geometry.substep else "step"),
                               "first_collision": s.first_collision,
                               "once_M": (None if self.geometry.once is None
                                          else self.geometry.once.M),
                               "adjoint": s.adjoint,
                               "kernel": s.resolved_kernel()},
            "resolution": self.resolution,
            "lattice_shape": list(lat.shape),  # includes the vacuum margin around open sides
            "voxel_size": lat.h,
            "node_counts": lat.counts(),
            "supersample": self.supersample,
            "edge_samples": self.edge_samples,
            # the cameras' marches as ``render_cameras`` groups them (``march_lanes``)
            "march_lanes": len(march_lanes([1.0] * len(self.cameras), self.march_lanes)),
            "sun_derivative_step_deg": (None if self.sun_lin is None
                                        else float(self.sun_lin.step)),
            "cameras": [c.name for c in self.cameras],
            "dtype": str(jnp.result_type(float)),
            "terms": ([] if self.geometry.terms is None
                      else self.geometry.terms.lines(lat.shape)),
            "setup_s": dict(self.host.setup_s),
        }
