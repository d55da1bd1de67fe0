"""The sweep's cameras: a differentiable ray march through a solved lattice.

The light has already been solved on a regular lattice (node ``(i, j, k)`` at
``origin + (idx + 0.5)·h``).  A camera ray is clipped to the lattice box and marched with fixed
steps (a loop over each chunk's own step count, the longest of its rays', up to a static
count, vectorised over rays, ``lax.map`` over chunks of rays) through trilinearly
interpolated fields, integrating

    dL/ds = -σ_t L + j_iso + j_sun · p_HG(cos θ)

with the step formula that is exact for coefficients constant over the step (they are taken as
the mean of the samples at the two step ends).  The first point
where the interpolated signed distance becomes ≤ 0 ends the march (sub-step location by linear
interpolation of the sdf) and adds the transmitted Lambertian radiosity of the surface there;
a ray that leaves the box without a hit adds the transmitted sky if it points upwards.

Conventions: see ``forward/_camera.py``.

Gradients: the march has a custom VJP (``_march``) — a reverse loop that re-gathers each step's
samples, applies the step's hand-written adjoint and scatter-adds into one table accumulator —
because JAX's transpose of a gather inside a scan adds a dense table-sized cotangent per step.
It is checked against JAX's autodiff of the plain scan (``every_step``) in the tests.  A custom
VJP has no forward mode: marches traced inside :func:`forward_mode` (a fit's Jacobian columns,
one ``jax.jvp`` per unknown) run the plain loop, which ``jax.jvp`` differentiates as it goes,
keeping nothing (until stop 60 those columns were the transpose of the VJP: three of them
took 7× a forward render).
"""

from __future__ import annotations

import contextlib
import contextvars
import dataclasses
import math
from functools import partial
from typing import NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Bool, Float, Int

# EDGE_SAMPLES: rays in a pixel that an edge crosses (Hammersley points, see camera_hits),
# defined with the cost model, which counts them
from ..._cost import EDGE_SAMPLES
from ..._numerics import one_minus_exp_over
from ...scene._description import Camera
from .._camera import camera_rays, forward_peak_kernel, hg_phase
from ._harmonics import basis

__all__ = [
    "LatticeFields",
    "RayHits",
    "TraceResult",
    "march_steps",
    "camera_hits",
    "forward_mode",
    "in_forward_mode",
    "render_camera",
    "render_rays",
    "trace_rays",
]

#: how far (in units of h) the surface lookup point is moved back along -d from the hit
HIT_BACKOFF = 1e-2
# the linear scheme's slope channels: x, y, z towards a node's upper neighbours, then towards
# its lower ones (``LatticeFields.j_slope``)
SLOPE_CHANNELS = 6
# The cameras' rays are marched in one lane on a CPU (``march_lanes``): all cameras' rays
# together, each 4096-ray chunk for its own step count.  Stop 80 grouped them into a march per
# core, which XLA ran side by side; at 4096-ray chunks one lane runs within 11% of two
# (images, a fit's Jacobian columns, a gradient) and compiles in half the time (fog-balls'
# gradient 3.6 against 8.3 s, cloud-tomo's 6.5 against 12.1 s, stop 81,
# ``benchmarks/results/stop81_speed/chunks*.md``; a whole fit before and after, stop 82,
# ``benchmarks/results/stop82_lanes/``).  ``lanes=`` still groups them in more.
# Elsewhere (a GPU) each camera keeps its own march over its static step count, as before
# stop 80: a loop whose trip count only the device knows makes the host wait on each step's
# test there, which no GPU has yet measured (``_chunk_steps``)
#: rays marched together (a chunk; ``lax.map`` over the chunks) on a CPU and elsewhere
#: (``march_chunk``).  On a CPU a chunk's per-ray state at each step (its rays, hits, radiance,
#: transmittance, tangents) should stay in a core's L2 cache (1 MiB here; the likely cause of
#: what follows, not profiled): fog-balls' images
#: in one process, runs interleaved (stop 81, ``benchmarks/results/stop81_speed/chunks.md``),
#: 0.325 / 0.344 s in chunks of 4096 / 8192 rays against 0.879 s in chunks of 16384 (one
#: lane), translucent-cube 0.179 against 0.267 s; cloud-tomo and cloud-plane, whose time
#: goes to their long paths through the lattice's tables, within 3% in one lane (in two,
#: cloud-plane 2.52 against 2.29 s, cloud-tomo 1.63 against 1.42 s).  A GPU keeps large
#: chunks (its parallelism is within a step).
MARCH_CHUNK_CPU = 4096
MARCH_CHUNK_GPU = 16384
#: longest march in a periodic-xy domain, in domain diagonals, unless ``max_length`` is given
PERIODIC_MAX_DIAGONALS = 8.0

_FORWARD_MODE = contextvars.ContextVar("difffog_march_forward_mode", default=False)


@contextlib.contextmanager
def forward_mode():
    """Within this context, camera marches that are traced (``trace_rays`` and what calls it)
    are differentiable by forward mode (``jax.jvp``) and not by reverse mode: they run the
    plain loop instead of the march with its hand-written reverse pass, which has no JVP.
    The choice is made when a march is traced (a static argument of its compiled program),
    so a function compiled inside the context keeps it.  Light solves traced inside it
    (``SweepSolver.solve``) keep their ``init``'s tangent as where their tangent solve starts,
    and their ``LightField.state`` carries its tangent (a fit's Jacobian starts each column's
    solve from the last step's)."""
    token = _FORWARD_MODE.set(True)
    try:
        yield
    finally:
        _FORWARD_MODE.reset(token)


def in_forward_mode() -> bool:
    """Whether what is traced now is inside :func:`forward_mode`."""
    return _FORWARD_MODE.get()


# --------------------------------------------------------------------------------------------
# the fields
# --------------------------------------------------------------------------------------------
def _as_vec3(v) -> tuple[float, float, float]:
    t = tuple(float(x) for x in np.asarray(v, np.float64).reshape(-1))
    if len(t) != 3:
        raise ValueError(f"expected 3 components, got {v!r}")
    return t  # type: ignore[return-value]


def _as_sun_dir(v) -> tuple[float, float, float] | None:
    if v is None:
        return None
    d = np.asarray(_as_vec3(v))
    n = np.linalg.norm(d)
    if not n > 0:
        raise ValueError(f"sun_dir must be a non-zero vector, got {v!r}")
    return _as_vec3(d / n)


class LatticeFields(eqx.Module):
    """Node-centred fields of a solved lattice, all (nx, ny, nz), node (i, j, k) at
    ``origin + (idx + 0.5)·h`` (cubic voxels); the lattice box is [origin, origin + shape·h].

    sigma_t: extinction per unit length.
    j_iso: isotropic source, radiance gained per unit length along any ray (σ_s·J).
    j_sun: sun single-scattering coefficient: radiance gained per unit length is
        ``j_sun · p_HG(cos θ)`` with ``cos θ = dot(sun_dir, d)`` for a camera ray d.
    radiosity_ext: Lambertian exitant radiance of the surface, extended to nodes near it.
    sdf: signed distance to solids (scene units), negative inside.
    g: HG asymmetry (a leaf: may be traced).  sky: uniform sky radiance of the upper
    hemisphere (a leaf: may be traced).  origin, h, shape, sun_dir (unit, towards the sun, or
    None for no sun), periodic_xy: static.  ``shape`` defaults to ``sigma_t.shape``.
    All values must be finite (use a large positive sdf where there are no solids).
    """

    sigma_t: Float[Array, "nx ny nz"] = eqx.field(converter=jnp.asarray)
    j_iso: Float[Array, "nx ny nz"] = eqx.field(converter=jnp.asarray)
    j_sun: Float[Array, "nx ny nz"] = eqx.field(converter=jnp.asarray)
    radiosity_ext: Float[Array, "nx ny nz"] = eqx.field(converter=jnp.asarray)
    sdf: Float[Array, "nx ny nz"] = eqx.field(converter=jnp.asarray)
    origin: tuple[float, float, float] = eqx.field(static=True, converter=_as_vec3)
    h: float = eqx.field(static=True, converter=float)
    shape: tuple[int, int, int] | None = eqx.field(static=True, default=None)
    g: Float[Array, ""] = eqx.field(default=0.0, converter=jnp.asarray)
    sun_dir: tuple[float, float, float] | None = eqx.field(
        static=True, default=None, converter=_as_sun_dir)
    sky: Float[Array, ""] = eqx.field(default=0.0, converter=jnp.asarray)
    periodic_xy: bool = eqx.field(static=True, default=False, converter=bool)
    # optional: unit normals (nx, ny, nz, 3) of the surface nodes, zero elsewhere.  When given,
    # the radiosity at a hit is interpolated over surface nodes only, each weighted by how much
    # it faces the viewer, instead of from radiosity_ext (which mixes in the far side of thin
    # walls and edges).
    surface_normal: Float[Array, "nx ny nz 3"] | None = None
    # optional, for exact hits (``RayHits``): the surface's diffuse irradiance (everything but
    # the direct sun: the scattered light, the other surfaces, the uncollided sky) at SURFACE
    # nodes, extended to the nodes near them; with surface_normal.  And what the hit radiance
    # needs besides: per shape albedo and emission (S,), the sun's irradiance, and the
    # extinction per unit density path (the sun at a hit is sun_irradiance·cos·exp(-σ·depth)).
    irradiance: Float[Array, "nx ny nz"] | None = None
    albedo: Float[Array, " S"] | None = None
    emission: Float[Array, " S"] | None = None
    sun_irradiance: Float[Array, ""] = eqx.field(default=0.0, converter=jnp.asarray)
    sun_extinction: Float[Array, ""] = eqx.field(default=0.0, converter=jnp.asarray)
    # optional: (c, width) of the forward peak the sun's beam keeps (``LightField.sun_peak``):
    # the beam's single scattering towards a camera is p·(1 − c·K(cos Θ, width))
    sun_window: Float[Array, "2"] | None = None
    # optional, for an anisotropic phase in the light solve (``SweepSolver.phase_order`` L > 0):
    # the in-scatter source's angular part, (nx, ny, nz, K): radiance gained per unit length
    # towards a camera ray d is j_iso + Σ_k Ỹ_k(−d)·j_aniso[..., k] (``_harmonics.basis(L, M)``,
    # ``harmonics`` = (L, M), static)
    j_aniso: Float[Array, "nx ny nz K"] | None = None
    harmonics: tuple[int, int] | None = eqx.field(static=True, default=None)
    # optional, the linear scheme (``SweepSolver.scheme``): each node's source change per
    # lattice spacing along x, y, z, towards
    # the node's upper neighbours (channels 0-2) and towards its lower ones (3-5); the march
    # blends the nodes' own linear extrapolations j + j_slope·(x − x_node)/h with the
    # trilinear weights, each offset reading its side's channel (``SLOPE_CHANNELS``)
    j_slope: Float[Array, "nx ny nz 6"] | None = None
    # optional, the sun's own profile along the march (with a sun): the optical depth towards
    # the sun at each node, u = σ_sun·∫ density ds (solids ignored; their shadow is in j_sun).
    # When given, j_sun is the *unattenuated* single-scattering coefficient (σ_s·F·visibility)
    # and each step integrates j_sun·p_HG·e^(−u) with u linear along the step, exactly: a
    # node's mean sun would be 1/τ of the light at its top in fog τ mean free paths per node.
    sun_depth: Float[Array, "nx ny nz"] | None = None
    # optional: the box (lo, hi) outside which there is no fog (z only when periodic_xy); the
    # march is clipped to it, so the fog ends sharply at its face instead of fading over the
    # last spacing (the fields must be extended to the nodes just outside it)
    fog_box: tuple[tuple[float, float, float], tuple[float, float, float]] | None = eqx.field(
        static=True, default=None)
    # optional: the sun's direction traced (the sun as an unknown), near ``sun_dir``, for the
    # sun's phase towards the camera (None: ``sun_dir``)
    sun_vec: Float[Array, "3"] | None = None

    def __post_init__(self):
        if self.shape is None:
            self.shape = tuple(int(n) for n in self.sigma_t.shape)
        else:
            self.shape = tuple(int(n) for n in self.shape)

    def __check_init__(self):
        if len(self.shape) != 3:
            raise ValueError(f"LatticeFields: shape must be (nx, ny, nz), got {self.shape}")
        for name in ("sigma_t", "j_iso", "j_sun", "radiosity_ext", "sdf"):
            a = getattr(self, name)
            if tuple(a.shape) != self.shape:
                raise ValueError(f"LatticeFields: {name} has shape {tuple(a.shape)}, "
                                 f"expected {self.shape}")
        if not self.h > 0:
            raise ValueError(f"LatticeFields: h must be positive, got {self.h}")
        if jnp.shape(self.g) != () or jnp.shape(self.sky) != ():
            raise ValueError("LatticeFields: g and sky must be scalars")
        if (self.j_aniso is None) != (self.harmonics is None):
            raise ValueError("LatticeFields: j_aniso and harmonics go together")
        if self.sun_depth is not None and tuple(self.sun_depth.shape) != self.shape:
            raise ValueError(f"LatticeFields: sun_depth has shape {tuple(self.sun_depth.shape)}, "
                             f"expected {self.shape}")
        if self.j_aniso is not None:
            K = (self.harmonics[0] + 1) ** 2 - 1
            if tuple(self.j_aniso.shape) != self.shape + (K,):
                raise ValueError(f"LatticeFields: j_aniso has shape {tuple(self.j_aniso.shape)}, "
                                 f"expected {self.shape + (K,)}")

    @property
    def lo(self) -> np.ndarray:
        """Lower corner of the lattice box, float64 (3,)."""
        return np.asarray(self.origin, np.float64)

    @property
    def hi(self) -> np.ndarray:
        """Upper corner of the lattice box, float64 (3,)."""
        return self.lo + self.h * np.asarray(self.shape, np.float64)


class RayHits(eqx.Module):
    """A camera's sample rays with their exact first hits against the scene's shapes, cast on
    the host once (``geometry._hits``, :func:`camera_hits`), and what the sun needs there; all
    (N,) per ray.

    origins, directions: (N, 3) the rays (unit directions).  pixel: (N,) the flat pixel
    (row·W + column) each ray belongs to; weight: (N,) its share of that pixel (1 / the
    pixel's sample count).  t: distance to the hit along the unit ray (inf: none).  normal: (N, 3) the shape's unit
    normal facing the ray.  shape: index into the scene's shapes (-1: none).  sun_cos:
    max(0, normal·sun) where no shape blocks the sun, else 0.  sun_depth: ∫ density ds from the
    hit towards the sun.  max_length: the longest fog segment of these rays (static: it sets the
    march's step count; None: from the rays and the box, as without hits).
    """

    origins: Float[Array, "N 3"] = eqx.field(converter=jnp.asarray)
    directions: Float[Array, "N 3"] = eqx.field(converter=jnp.asarray)
    pixel: Int[Array, " N"] = eqx.field(converter=jnp.asarray)
    weight: Float[Array, " N"] = eqx.field(converter=jnp.asarray)
    t: Float[Array, " N"] = eqx.field(converter=jnp.asarray)
    normal: Float[Array, "N 3"] = eqx.field(converter=jnp.asarray)
    shape: Int[Array, " N"] = eqx.field(converter=jnp.asarray)
    sun_cos: Float[Array, " N"] = eqx.field(converter=jnp.asarray)
    sun_depth: Float[Array, " N"] = eqx.field(converter=jnp.asarray)
    max_length: float | None = eqx.field(static=True, default=None)


#: how far (in units of h) off the surface, along its normal, the hit's irradiance is looked up:
#: the trilinear cell around that point then has its lower nodes at most one spacing from the
#: surface on the hit's side (for an axis-aligned surface: exactly the first layer of SURFACE
#: nodes), never on the far side of a thin quad, whose SOLID band is up to ‖n‖₁·h/2 wide
HIT_LOOKUP_OFFSET = 1.0
#: weight of the nearest-surface extension in the hit's irradiance, against trilinear weights
#: × normal agreement of order 1: it only decides where no surface node faces the hit
EXTENSION_WEIGHT = 1e-3


# --------------------------------------------------------------------------------------------
# the march (JAX)
# --------------------------------------------------------------------------------------------
class TraceResult(NamedTuple):
    """Per-ray results of :func:`trace_rays`, all (N,).

    radiance: radiance arriving at the ray origin along -d.
    transmittance: transmittance from the origin to the hit / the domain exit.
    hit: whether the ray hit a surface inside the lattice box.
    depth: distance along the ray to the hit (scene units; +inf where no hit).
    """

    radiance: Float[Array, " N"]
    transmittance: Float[Array, " N"]
    hit: Bool[Array, " N"]
    depth: Float[Array, " N"]


def _clip(lo, hi, o, d, periodic_xy: bool, xp):
    """Slab test: (t0, t1) of the rays' segment inside the box (z only when periodic_xy).

    t0 ≥ 0 (a ray starting inside starts at its origin); empty where t1 ≤ t0.  ``xp`` is
    numpy or jax.numpy.
    """
    t0 = xp.zeros(o.shape[:-1], o.dtype)
    t1 = xp.full(o.shape[:-1], xp.inf, o.dtype)
    for a in ((2,) if periodic_xy else (0, 1, 2)):
        oa, da = o[..., a], d[..., a]
        flat = da == 0
        inside = (oa >= lo[a]) & (oa <= hi[a])
        ds = xp.where(flat, 1.0, da)
        ta, tb = (lo[a] - oa) / ds, (hi[a] - oa) / ds
        t0 = xp.maximum(t0, xp.where(flat, xp.where(inside, -xp.inf, xp.inf), xp.minimum(ta, tb)))
        t1 = xp.minimum(t1, xp.where(flat, xp.where(inside, xp.inf, -xp.inf), xp.maximum(ta, tb)))
    return t0, t1


def march_steps(fields: LatticeFields, step: float, origins=None, directions=None,
                max_length: float | None = None) -> int:
    """Static number of march steps: ceil(longest in-box path / step) + 1.

    The longest path is ``max_length`` if given; else, when concrete rays are given, the
    longest clipped path among them (never more than the box diagonal, or
    PERIODIC_MAX_DIAGONALS diagonals for periodic_xy); else the box diagonal (periodic_xy:
    PERIODIC_MAX_DIAGONALS diagonals, since grazing rays through a periodic slab are
    unbounded).
    """
    diag = float(np.linalg.norm(fields.hi - fields.lo))
    cap = diag * (PERIODIC_MAX_DIAGONALS if fields.periodic_xy else 1.0)
    if max_length is None:
        max_length = cap
        o = d = None
        if origins is not None and directions is not None:
            try:
                o = np.asarray(origins, np.float64).reshape(-1, 3)
                d = np.asarray(directions, np.float64).reshape(-1, 3)
            except (jax.errors.TracerArrayConversionError, jax.errors.ConcretizationTypeError):
                o = d = None  # traced rays: fall back to the box
        if o is not None and len(o):
            d = d / np.linalg.norm(d, axis=-1, keepdims=True)
            t0, t1 = _clip(fields.lo, fields.hi, o, d, fields.periodic_xy, np)
            path = np.where(t1 > t0, t1 - t0, 0.0)
            max_length = min(cap, float(path.max(initial=0.0)))
    return step_count(max_length, step)


def march_step(h: float, step: float | None = None) -> float:
    """The march's step length: ``step``, by default half the lattice spacing ``h``."""
    return float(h / 2.0 if step is None else step)


def step_count(max_length: float, step: float) -> int:
    """The march's static number of steps for a longest path ``max_length``."""
    return int(math.ceil(float(max_length) / step)) + 1


def _padded_z(shape) -> int:
    """Row length of the flat node tables: nz, or nz + 1 when nz is even.

    Power-of-two strides make neighbouring nodes alias in the CPU caches: a scatter-add of
    march-like updates into a 64³ table ran 5x slower with them (XLA:CPU).
    """
    return shape[2] + (1 - shape[2] % 2)


def _flat_table(arrays, dtype):
    """Stack (nx, ny, nz) arrays into a flat node table (nx·ny·nz', C), rows padded to nz'."""
    a = jnp.stack(arrays, axis=-1).astype(dtype)
    nzp = _padded_z(a.shape[:3])
    if nzp != a.shape[2]:
        a = jnp.pad(a, ((0, 0), (0, 0), (0, nzp - a.shape[2]), (0, 0)), mode="edge")
    return a.reshape(-1, a.shape[-1])


def _coords(p, geo):
    """Lattice coordinates (R, 3) of points p (R, 3): node (i, j, k) sits at (i, j, k)."""
    lo, h = geo[0], geo[1]
    return (p - jnp.asarray(lo, p.dtype)) / h - 0.5


def _stencil(p, lo, h: float, shape, periodic_xy: bool, offsets: bool = False):
    """Trilinear stencil at points p (R, 3): 8 pairs (flat index (R,) int32 into a table made
    by ``_flat_table``, weight (R,)).  Outside the node centres the value is clamped (wrapped
    in x, y when periodic_xy).  ``offsets``: triples, with the point's offset from each corner
    node in spacings, (R, 3) (for the linear scheme's slopes, ``_interp``)."""
    return _stencil_at(_coords(p, (lo, h)), shape, periodic_xy, offsets)


def _stencil_at(uvw, shape, periodic_xy: bool, offsets: bool = False):
    """``_stencil`` at lattice coordinates ``uvw`` (R, 3) (``_coords``).

    Which nodes a point reads (floor) and its weights and offsets (the fraction) must come from
    one value of its coordinates.  XLA recomputes an elementwise producer inside each fusion
    that consumes it, and on CPU LLVM contracts a·b + c into one FMA in some of those copies
    and not in others, so a point that lies on a node plane (an orthographic camera's march
    points do, every few steps) could get its node from one rounding and its fraction from the
    other: its slope channels then read a whole spacing's offset (measured: a top-down march
    through a linear-scheme cloud, 149 of 365 rays up to 7% off, and its gradients 2-11% off
    central differences, from the jitted march against the same march op by op).  Callers that
    matter pass coordinates that are materialised (the march carries them through its scan),
    and everything below is exact or continuous in them."""
    nzp = _padded_z(shape)
    strides = (shape[1] * nzp, nzp, 1)
    corners = []  # per axis: ((flat offset, weight) at the lower node, ... at the upper node)
    for a in range(3):
        n = shape[a]
        u = uvw[:, a]
        if periodic_xy and a < 2:
            fl = jnp.floor(u)
            f = u - fl
            i0 = jnp.mod(fl.astype(jnp.int32), n)
            i1 = jnp.mod(i0 + 1, n)
        else:
            u = jnp.clip(u, 0.0, n - 1.0)
            i0 = jnp.clip(jnp.floor(u), 0, max(n - 2, 0)).astype(jnp.int32)
            f = u - i0
            i1 = jnp.minimum(i0 + 1, n - 1)
        corners.append(((i0 * strides[a], 1.0 - f, f), (i1 * strides[a], f, f - 1.0)))
    out = []
    for ox, wx, dx in corners[0]:
        for oy, wy, dy in corners[1]:
            for oz, wz, dz in corners[2]:
                if offsets:
                    out.append((ox + oy + oz, wx * wy * wz, jnp.stack([dx, dy, dz], -1)))
                else:
                    out.append((ox + oy + oz, wx * wy * wz))
    return out


def _weights(uvw, geo, slope_at: int | None, n_chan: int):
    """The stencil of ``_interp`` at lattice coordinates ``uvw`` (``_coords``) as (flat index
    (R,), weight (R, C)) pairs: the trilinear weight for every channel, times the point's offset
    from the corner node along x, y, z for the ``SLOPE_CHANNELS`` slope channels from
    ``slope_at`` on (each node's own linear extrapolation of the source, blended trilinearly):
    a positive offset (the point lies on the corner node's upper side) reads channels 0-2, a
    negative one channels 3-5."""
    shape, periodic_xy = geo[2], geo[3]
    if slope_at is None:
        return [(i, w[:, None]) for i, w in _stencil_at(uvw, shape, periodic_xy)]
    out = []
    R = uvw.shape[0]
    one = jnp.ones((R, 1), uvw.dtype)
    for i, w, off in _stencil_at(uvw, shape, periodic_xy, offsets=True):
        mult = jnp.concatenate([jnp.broadcast_to(one, (R, slope_at)),
                                jnp.maximum(off, 0.0), jnp.minimum(off, 0.0),
                                jnp.broadcast_to(one, (R, n_chan - slope_at - SLOPE_CHANNELS))],
                               -1)
        out.append((i, w[:, None] * mult))
    return out


def _interp(table, p, geo, slope_at: int | None = None):
    """Trilinear samples of a flat node table (``_flat_table``) at points p (R, 3) → (R, C).

    ``geo`` = (lo, h, shape, periodic_xy), static.  ``slope_at``: the first of the slope
    channels (``_weights``), or None.
    """
    return _interp_at(table, _coords(p, geo), geo, slope_at)


def _interp_at(table, uvw, geo, slope_at: int | None = None):
    """``_interp`` at lattice coordinates ``uvw`` (R, 3) (``_coords``).  Eight separate (R, C)
    gathers: on XLA:CPU this is ~3x faster than one (R, 8, C) gather and a contraction."""
    out = 0.0
    for i, w in _weights(uvw, geo, slope_at, table.shape[-1]):
        out = out + w * table.at[i].get(mode="promise_in_bounds")
    return out


def _phi(sigma, ds):
    """(1 - exp(-σ ds)) / σ, NaN-free with the right value and gradient as σ → 0."""
    return ds * one_minus_exp_over(sigma * ds)


class _MarchConfig(NamedTuple):
    """Static configuration of a march (hashable)."""

    geo: tuple  # (lo (3 floats), h, shape, periodic_xy), as _stencil takes them
    n_coef: int  # per-ray source coefficients (the sun's phase value, the basis Ỹ_k(−d))
    n_steps: int
    step: float
    has_sdf: bool = True  # False: the hits are given (exact), the table has no sdf channel
    slopes: bool = False  # the linear scheme: SLOPE_CHANNELS after the coefficients'
    sun_exp: bool = False  # coefficient 0 is the sun's, attenuated along the step by e^(−u)

    @property
    def slope_at(self) -> int | None:
        return 2 + self.n_coef if self.slopes else None

    @property
    def u_at(self) -> int:
        """The channel of the optical depth towards the sun (with ``sun_exp``)."""
        return 2 + self.n_coef + (SLOPE_CHANNELS if self.slopes else 0)


def _mix(c, coef, cfg: _MarchConfig):
    """(σ_t, source, sdf, sun, u) from table samples c (..., C) — channels σ_t, j_iso, then
    one per per-ray coefficient, [then the slope channels, already weighted by the
    point's offsets (``_weights``),] [then u, the optical depth towards the sun,] then the sdf
    — and the per-ray coefficients (R, J): source = j_iso + Σ_j coef_j·c_(2+j) [+ the
    slopes']; the sdf is 1 (never a crossing) when the table has none.  With ``sun_exp`` the
    sun's term coef_0·c_2 is not in the source but returned apart (``sun``), with ``u``; else
    both are None."""
    src = c[..., 1]
    first = 1 if cfg.sun_exp else 0
    for j in range(first, cfg.n_coef):
        src = src + coef[:, j] * c[..., 2 + j]
    if cfg.slopes:
        k = 2 + cfg.n_coef
        src = src + sum(c[..., k + a] for a in range(SLOPE_CHANNELS))
    sdf = c[..., -1] if cfg.has_sdf else jnp.ones_like(c[..., 0])
    if cfg.sun_exp:
        return c[..., 0], src, sdf, coef[:, 0] * c[..., 2], c[..., cfg.u_at]
    return c[..., 0], src, sdf, None, None


def _sun_integral(u_a, y, ds):
    """∫₀^ds e^(−u_a − y·t/ds) dt: the sun's attenuation e^(−u) over a step along which the
    optical depth towards the sun *and* the one back to the step's start grow linearly by y
    in all (y < 0: the ray runs towards the sun faster than the fog dims it), written so that
    it neither overflows nor cancels: ds·e^(−u_a − min(y, 0))·(1 − e^(−|y|))/|y|.  The
    exponent −max(u_a, u_b + σ_t·ds) is ≤ 0 for optical depths u ≥ 0; where the lattice's
    linear continuation of u past the fog's box makes it positive (near a corner of the box)
    it is held at 0, so that no sample sees more than the unattenuated sun."""
    return ds * jnp.exp(jnp.minimum(-u_a - jnp.minimum(y, 0.0), 0.0)) * one_minus_exp_over(
        jnp.abs(y))


def _step_times(t0, t_end, k, step):
    """Distance of march point k (clamped to the exit) along each ray."""
    return jnp.minimum(t0 + k * step, t_end)


def _march_init(t0, t_end, sdf0):
    """Initial carry (T, L, alive, t_hit); a ray starting inside a solid hits at t0."""
    valid = t_end > t0
    inside0 = valid & (sdf0 <= 0.0)
    return (jnp.ones_like(t0), jnp.zeros_like(t0), valid & ~inside0,
            jnp.where(inside0, t0, jnp.inf))


def _march_step(carry, ta, tb, a, b):
    """One step from ta to tb (R,), with (σ_t, source, sdf, sun, u) samples a, b at its two
    ends (``_mix``).  The sun's term, when apart, is its mean over the step times the exact
    integral of e^(−u) with u linear along the step (``_sun_integral``)."""
    T, L, alive, t_hit = carry
    sig_a, src_a, sdf_a, sun_a, u_a = a
    sig_b, src_b, sdf_b, sun_b, u_b = b
    ds = tb - ta
    live = alive & (ds > 0)
    cross = live & (sdf_b <= 0.0)
    den = sdf_a - sdf_b  # > 0 where cross (sdf_a > 0 ≥ sdf_b)
    f = jnp.where(cross, jnp.clip(sdf_a / jnp.where(cross, den, 1.0), 0.0, 1.0), 1.0)
    dse = f * ds  # up to the surface, located by linear interpolation of the sdf
    s_t = sig_a + 0.5 * f * (sig_b - sig_a)  # mean over the (partial) step, linear profile
    s_j = src_a + 0.5 * f * (src_b - src_a)
    gain = s_j * _phi(s_t, dse)
    if sun_a is not None:
        s_S = sun_a + 0.5 * f * (sun_b - sun_a)
        gain = gain + s_S * _sun_integral(u_a, s_t * dse + f * (u_b - u_a), dse)
    L = L + jnp.where(live, T * gain, 0.0)
    T = jnp.where(live, T * jnp.exp(-s_t * dse), T)
    t_hit = jnp.where(cross, ta + dse, t_hit)
    return T, L, alive & ~cross, t_hit


def _e1_and_slope(x):
    """(e^(−x), e1 = (1 − e^(−x))/x, de1/dx), each with a series below |x| = 1e-3 (the values
    ``one_minus_exp_over`` gives, and the slope the adjoint needs)."""
    small = jnp.abs(x) < 1e-3
    xs = jnp.where(small, 1.0, x)
    E = jnp.exp(-x)
    e1 = jnp.where(small, 1.0 - x / 2.0 + x * x / 6.0 - x * x * x / 24.0, -jnp.expm1(-xs) / xs)
    de1 = jnp.where(small, -0.5 + x / 3.0 - x * x / 8.0, (E - e1) / xs)
    return E, e1, de1


def _march_step_vjp(T, alive, ta, tb, a, b, lam_T, g_L, lam_hit):
    """Adjoint of ``_march_step`` (L enters linearly: its cotangent g_L is the same at every
    step).  Given the cotangents (lam_T, g_L, lam_hit) of (T, L, t_hit) after the step, returns
    those of T and t_hit before it and of the samples a, b = (σ_t, source, sdf, sun, u) (the
    last two None when the sun is in the source)."""
    sig_a, src_a, sdf_a, sun_a, u_a = a
    sig_b, src_b, sdf_b, sun_b, u_b = b
    ds = tb - ta
    live = alive & (ds > 0)
    cross = live & (sdf_b <= 0.0)
    den = jnp.where(cross, sdf_a - sdf_b, 1.0)
    r = sdf_a / den
    f = jnp.where(cross, jnp.clip(r, 0.0, 1.0), 1.0)
    dse = f * ds
    s_t = sig_a + 0.5 * f * (sig_b - sig_a)
    s_j = src_a + 0.5 * f * (src_b - src_a)
    E, e1, de1 = _e1_and_slope(s_t * dse)
    phi = dse * e1
    q = g_L * T
    lte = lam_T * T * E
    g_j = q * phi
    g_s = q * s_j * dse * dse * de1 - lte * dse
    g_dse = q * s_j * E - lte * s_t + jnp.where(cross, lam_hit, 0.0)
    gain = s_j * phi
    g_f_sun = 0.0
    if sun_a is not None:
        # I = ds'·A·e1(|y|), A = e^(−u_a − min(y, 0)), y = s_t·ds' + f·(u_b − u_a)
        du = u_b - u_a
        y = s_t * dse + f * du
        _, ey, dey = _e1_and_slope(jnp.abs(y))
        expo = -u_a - jnp.minimum(y, 0.0)
        free = expo <= 0.0  # the exponent is not held at 0 (``_sun_integral``)
        A = jnp.exp(jnp.minimum(expo, 0.0))
        I = dse * A * ey  # noqa: E741
        I_y = dse * A * jnp.where(y >= 0.0, dey, -dey - jnp.where(free, ey, 0.0))  # ∂I/∂y
        s_S = sun_a + 0.5 * f * (sun_b - sun_a)
        g_S = q * I
        g_I = q * s_S
        g_s = g_s + g_I * I_y * dse
        g_dse = g_dse + g_I * (A * ey + I_y * s_t)
        g_f_sun = 0.5 * g_S * (sun_b - sun_a) + g_I * I_y * du
        gain = gain + s_S * I
    g_f = 0.5 * (g_s * (sig_b - sig_a) + g_j * (src_b - src_a)) + g_dse * ds + g_f_sun
    g_r = jnp.where(cross & (r > 0.0) & (r < 1.0), g_f, 0.0) / (den * den)
    zero = jnp.zeros_like(T)
    m = lambda v: jnp.where(live, v, zero)  # noqa: E731
    ga = (m(g_s * (1.0 - 0.5 * f)), m(g_j * (1.0 - 0.5 * f)), m(-g_r * sdf_b))
    gb = (m(0.5 * f * g_s), m(0.5 * f * g_j), m(g_r * sdf_a))
    if sun_a is not None:
        g_ua = -g_I * (jnp.where(free, I, 0.0) + f * I_y)
        g_ub = g_I * f * I_y
        ga = ga + (m(g_S * (1.0 - 0.5 * f)), m(g_ua))
        gb = gb + (m(0.5 * f * g_S), m(g_ub))
    else:
        ga, gb = ga + (None, None), gb + (None, None)
    lam_T = jnp.where(live, lam_T * E + g_L * gain, lam_T)
    return lam_T, jnp.where(cross, 0.0, lam_hit), ga, gb


def _unmix_ct(g, c, coef, cfg: _MarchConfig):
    """Cotangents (σ_t, source, sdf, sun, u) → raw table channels (R, C), and the
    coefficients' (R, J)."""
    g_sig, g_src, g_sdf, g_sun, g_u = g
    tail = [g_sdf] if cfg.has_sdf else []
    J = cfg.n_coef
    slopes = [g_src] * SLOPE_CHANNELS if cfg.slopes else []
    g_coef = [g_sun if (cfg.sun_exp and j == 0) else g_src for j in range(J)]
    depth = [g_u] if cfg.sun_exp else []
    chans = ([g_sig, g_src] + [coef[:, j] * g_coef[j] for j in range(J)] + slopes + depth
             + tail)
    g_phase = jnp.stack([g_coef[j] * c[:, 2 + j] for j in range(J)], -1) if J else (
        jnp.zeros((c.shape[0], 0), c.dtype))
    return jnp.stack(chans, -1), g_phase


def _sample(table, uvw, geo, slope_at: int | None = None):
    """Raw table samples (R, C) at lattice coordinates ``uvw`` (R, 3), made once (see the note
    inside)."""
    c = _interp_at(table, uvw, geo, slope_at)
    if jax.default_backend() == "cpu":
        # XLA:CPU would otherwise fuse the eight gathers into each consumer of c and do them
        # several times (3x slower); a tiny dot is not fused, so c is materialised once.
        c = c @ jnp.eye(c.shape[-1], dtype=c.dtype)
    return c


def _point_coords(o, d, t0, t_end, k, cfg: _MarchConfig):
    """Lattice coordinates (R, 3) of march point k.  The scans make each point's coordinates
    one iteration before they use them and carry them, so that every fusion that reads them
    reads the same values (``_stencil_at``)."""
    return _coords(o + _step_times(t0, t_end, k, cfg.step)[:, None] * d, cfg.geo)


def march_chunk(chunk: int | None = None) -> int:
    """The rays a march takes at a time: ``chunk``, else the backend's default."""
    if chunk is None:
        return MARCH_CHUNK_CPU if jax.default_backend() == "cpu" else MARCH_CHUNK_GPU
    return int(chunk)


def _chunk_steps() -> bool:
    """Whether marches stop at their chunk's own step count (``_live_steps``): on a CPU."""
    return jax.default_backend() == "cpu"


def _live_steps(t0, t_end, cfg: _MarchConfig):
    """How many of the march's steps have a positive length for some ray of the chunk (at most
    ``cfg.n_steps``): the steps after them change nothing (``_march_step`` skips ds = 0), so the
    loops stop there.  One more than the longest segment's ceil(length / step), so that no
    rounding of t0 + k·step against that division drops a last short step."""
    longest = jnp.max(jnp.where(t_end > t0, t_end - t0, 0.0), initial=0.0)
    n = jnp.ceil(longest / jnp.asarray(cfg.step, t0.dtype)) + 1.0
    return jnp.minimum(n, cfg.n_steps).astype(jnp.int32)


def _step_count(t0, t_end, cfg: _MarchConfig, every_step: bool = False):
    """The steps a march of the chunk runs, forward and back alike: its live steps where
    ``_chunk_steps`` (a traced count), else (or with ``every_step``) all ``cfg.n_steps``."""
    return cfg.n_steps if every_step or not _chunk_steps() else _live_steps(t0, t_end, cfg)


def _march_fused(table, phase, o, d, t0, t_end, cfg: _MarchConfig, trajectory: bool = False,
                 every_step: bool = False):
    """The march, the samples gathered inside the loop; ``_live_steps`` steps (a while loop: the
    chunk's own step count, not the longest camera's), or with ``every_step`` all
    ``cfg.n_steps`` (a scan, which reverse-mode autodiff can take: the tests' reference).
    Returns the final carry (T, L, alive, t_hit), and with ``trajectory`` also (T_k, alive_k)
    (n_steps, R) before each step (for the backward pass; rows past the live steps are not
    written)."""

    def coords(k):
        return _point_coords(o, d, t0, t_end, k, cfg)

    def sample(uvw):
        return _sample(table, uvw, cfg.geo, cfg.slope_at)

    first = sample(coords(0))

    def body(i, c):
        carry, c_a, u_b, traj = c  # u_b: point k + 1's coordinates, made by the iteration before
        k = jnp.asarray(i, t0.dtype)  # (a Python int op by op, under jax.disable_jit)
        ta = _step_times(t0, t_end, k, cfg.step)
        tb = _step_times(t0, t_end, k + 1, cfg.step)
        c_b = sample(u_b)
        a, b = _mix(c_a, phase, cfg), _mix(c_b, phase, cfg)
        if trajectory:
            traj = (traj[0].at[i].set(carry[0]), traj[1].at[i].set(carry[2]))
        return _march_step(carry, ta, tb, a, b), c_b, coords(k + 2), traj

    traj = ((jnp.zeros((cfg.n_steps,) + t0.shape, t0.dtype),
             jnp.zeros((cfg.n_steps,) + t0.shape, bool)) if trajectory else None)
    init = (_march_init(t0, t_end, _mix(first, phase, cfg)[2]), first, coords(1), traj)
    n = _step_count(t0, t_end, cfg, every_step)
    carry, _, _, traj = jax.lax.fori_loop(0, n, body, init)
    return (carry, traj) if trajectory else carry


@partial(jax.custom_vjp, nondiff_argnums=(6,))
def _march(table, phase, o, d, t0, t_end, cfg: _MarchConfig):
    """March a chunk of rays; returns (T, L, t_hit), each (R,) (t_hit = inf: no hit).

    table: (n_nodes', C) flat table of σ_t, j_iso, [j_sun,] [j_aniso,] [sdf] (``_flat_table``);
    phase: (R, J) per-ray source coefficients (the HG phase value towards the sun, the
    anisotropic basis; see ``_mix``); o, d: (R, 3); t0, t_end: (R,) the marched segment.
    Differentiable in ``table`` and ``phase``; the march points do not depend on them, so
    ``o, d, t0, t_end`` get no cotangent.

    The backward pass is a reverse loop over the steps: re-gather the samples of one step,
    apply the step's adjoint (``_march_step_vjp``, given the transmittance before it from a
    recomputed forward), scatter-add the samples' cotangents into one table accumulator
    carried by the loop.  JAX's own transpose of the forward scan would add a
    dense table-sized cotangent at every step (10x slower on a 64³ lattice).
    """
    T, L, _, t_hit = _march_fused(table, phase, o, d, t0, t_end, cfg)
    return T, L, t_hit


def _march_fwd(table, phase, o, d, t0, t_end, cfg):
    return _march(table, phase, o, d, t0, t_end, cfg), (table, phase, o, d, t0, t_end)


def _march_bwd(cfg, res, ct):
    table, phase, o, d, t0, t_end = res
    g_T, g_L, g_hit = ct
    _, (T_k, alive_k) = _march_fused(table, phase, o, d, t0, t_end, cfg, trajectory=True)

    def coords(k):
        return _point_coords(o, d, t0, t_end, k, cfg)

    def scatter(acc, uvw, g):
        for i, w in _weights(uvw, cfg.geo, cfg.slope_at, g.shape[-1]):
            acc = acc.at[i].add(w * g, mode="promise_in_bounds")
        return acc

    n = _step_count(t0, t_end, cfg)

    def body(i, carry):
        # u_a, u_b: points k and k + 1's coordinates, made by the iterations before
        lam_T, lam_hit, c_b, u_b, u_a, g_b_next, g_phase, acc = carry
        j = n - 1 - i  # the steps in reverse
        k, T_a, alive = jnp.asarray(j, t0.dtype), T_k[j], alive_k[j]
        ta = _step_times(t0, t_end, k, cfg.step)
        tb = _step_times(t0, t_end, k + 1, cfg.step)
        c_a = _sample(table, u_a, cfg.geo, cfg.slope_at)
        a, b = _mix(c_a, phase, cfg), _mix(c_b, phase, cfg)
        lam_T, lam_hit, g_a, g_b = _march_step_vjp(T_a, alive, ta, tb, a, b, lam_T, g_L, lam_hit)
        g_a, g_ph_a = _unmix_ct(g_a, c_a, phase, cfg)
        g_b, g_ph_b = _unmix_ct(g_b, c_b, phase, cfg)
        acc = scatter(acc, u_b, g_b + g_b_next)  # point k+1 ends step k and starts step k+1
        return (lam_T, lam_hit, c_a, u_a, coords(k - 1), g_a, g_phase + g_ph_a + g_ph_b,
                acc)

    nf = jnp.asarray(n, t0.dtype)
    u_last = coords(nf)
    c_last = _sample(table, u_last, cfg.geo, cfg.slope_at)
    init = (g_T, g_hit, c_last, u_last, coords(nf - 1), jnp.zeros_like(c_last),
            jnp.zeros_like(phase), jnp.zeros_like(table))
    _, _, _, u_first, _, g_first, g_phase, acc = jax.lax.fori_loop(0, n, body, init)
    return scatter(acc, u_first, g_first), g_phase, None, None, None, None


_march.defvjp(_march_fwd, _march_bwd)


def _march_jvp_able(table, phase, o, d, t0, t_end, cfg: _MarchConfig):
    """``_march`` as the plain loop (``forward_mode``): the same values, differentiable by
    ``jax.jvp`` (not by reverse mode: the loop's trip count is the chunk's own)."""
    T, L, _, t_hit = _march_fused(table, phase, o, d, t0, t_end, cfg)
    return T, L, t_hit


def _marcher(forward: bool):
    return _march_jvp_able if forward else _march


def _segments(fields: LatticeFields, o, d, stop, n_steps: int, step: float):
    """What a chunk's march needs: (geo, has_sun, coef (R, J), t0, t_end, reached).  The
    marched segment of each ray runs from its box entry to min(box exit, ``stop``) (``stop``:
    (R,) or None), capped at n_steps·step; ``reached``: the march gets to its segment's end."""
    dtype = o.dtype
    lo = jnp.asarray(fields.lo, dtype)
    hi = jnp.asarray(fields.hi, dtype)
    geo = (tuple(fields.lo.tolist()), fields.h, fields.shape, fields.periodic_xy)
    has_sun = fields.sun_dir is not None
    coef = []
    if has_sun:
        sd = (jnp.asarray(fields.sun_dir, dtype) if fields.sun_vec is None
              else fields.sun_vec.astype(dtype))
        cos = d @ sd
        ph = hg_phase(cos, jnp.asarray(fields.g, dtype))
        if fields.sun_window is not None:  # less the forward peak the beam keeps
            c, width = fields.sun_window[0].astype(dtype), fields.sun_window[1].astype(dtype)
            ph = ph * (1.0 - c * forward_peak_kernel(cos, width))
        coef.append(ph[:, None])
    if fields.harmonics is not None:  # light going towards the camera: −d
        coef.append(basis(*fields.harmonics).evaluate(-d, jnp).astype(dtype))
    phase = jnp.concatenate(coef, axis=1) if coef else jnp.zeros((o.shape[0], 0), dtype)
    if fields.fog_box is not None:  # no fog outside it: march only inside
        lo = jnp.maximum(lo, jnp.asarray(fields.fog_box[0], dtype))
        hi = jnp.minimum(hi, jnp.asarray(fields.fog_box[1], dtype))
    t0, t1 = _clip(lo, hi, o, d, fields.periodic_xy, jnp)
    seg_end = t1 if stop is None else jnp.minimum(t1, stop)
    valid = seg_end > t0
    reached = ~valid | (seg_end <= t0 + n_steps * step)
    # keep every sample point finite (NaN weights would poison the gathers' gradients)
    t0 = jnp.where(valid, t0, 0.0)
    t_end = jnp.where(valid, jnp.minimum(seg_end, t0 + n_steps * step), 0.0)
    return geo, has_sun, phase, t0, t_end, reached


def _trace_chunk(fields: LatticeFields, table, rad_table, o, d, *, n_steps: int,
                 step: float, forward: bool = False) -> TraceResult:
    """March one chunk of rays o, d (R, 3) (d unit) through the flat tables of ``fields``
    (``table``: σ_t, j_iso, [j_sun,] sdf; ``rad_table``: radiosity_ext); returns a
    TraceResult of (R,) arrays."""
    dtype = o.dtype
    geo, has_sun, phase, t0, t_end, reached = _segments(fields, o, d, None, n_steps, step)
    cfg = _MarchConfig(geo, phase.shape[1], int(n_steps), float(step),
                       slopes=fields.j_slope is not None, sun_exp=_sun_exp(fields))
    T, L, t_hit = _marcher(forward)(table, phase, o, d, t0, t_end, cfg)

    hit = (t_end > t0) & jnp.isfinite(t_hit)  # t_end > t0: the ray meets the box
    t_safe = jnp.where(hit, t_hit, t0)
    p_hit = o + (t_safe - HIT_BACKOFF * fields.h)[:, None] * d
    rad = _interp(rad_table, p_hit, geo)
    b_hit = rad[:, 0]
    if rad.shape[1] > 1:  # columns: ext, m·B, m, m·B·N (3), m·N (3)
        facing_b = -(rad[:, 3:6] * d).sum(-1)
        facing = -(rad[:, 6:9] * d).sum(-1)
        # The facing-weighted mean is exact wherever the nodes share a normal, however small
        # N·d (walls seen edge-on).  Where normals of opposite sides mix (a thin quad's edge)
        # the weights change sign and the ratio can explode: detect that by the interpolated
        # normal's length collapsing, fall back to the plain masked mean there, and keep the
        # result within the radiosity's range.
        ok_m = rad[:, 2] > 1e-3
        coherent = (rad[:, 6:9] ** 2).sum(-1) >= 0.25 * rad[:, 2] ** 2
        ok_f = (facing > 1e-3) & coherent
        b_mask = jnp.where(ok_m, rad[:, 1] / jnp.where(ok_m, rad[:, 2], 1.0), b_hit)
        b_hit = jnp.where(ok_f, facing_b / jnp.where(ok_f, facing, 1.0), b_mask)
        b_hit = jnp.clip(b_hit, 0.0, jnp.max(fields.radiosity_ext))
    escaped = ~hit & reached & (d[:, 2] > 0)
    sky = jnp.asarray(fields.sky, dtype)
    radiance = L + jnp.where(hit, T * b_hit, 0.0) + jnp.where(escaped, T * sky, 0.0)
    return TraceResult(radiance, T, hit, jnp.where(hit, t_hit, jnp.inf))


def _hit_irradiance(surf_table, p, n, geo):
    """The diffuse irradiance at points p (R, 3) just off exact hits with normals n (R, 3) (see
    HIT_LOOKUP_OFFSET): the mean over
    the trilinear stencil's SURFACE nodes, each weighted by its trilinear weight × max(0, its
    normal · n) (nodes on the far side of a thin wall or around an edge face away and drop
    out), blended with the nearest-surface extension with weight EXTENSION_WEIGHT.  Continuous
    in p wherever a node faces the hit, so the surface shows no lattice facets.
    ``surf_table``: (n_nodes', 4) irradiance (extended), unit normal (0 off SURFACE nodes)."""
    num = den = ext = 0.0
    for i, w in _stencil(p, *geo):
        c = surf_table.at[i].get(mode="promise_in_bounds")
        wn = w * jnp.maximum((c[:, 1:4] * n).sum(-1), 0.0)
        num = num + wn * c[:, 0]
        den = den + wn
        ext = ext + w * c[:, 0]
    return (num + EXTENSION_WEIGHT * ext) / (den + EXTENSION_WEIGHT)


def _trace_chunk_exact(fields: LatticeFields, table, surf_table, o, d, hits, *, n_steps: int,
                       step: float, forward: bool = False) -> TraceResult:
    """``_trace_chunk`` with exact hits (a RayHits of this chunk): the fog is marched up to the
    hit, and the surface's radiance is rebuilt at the exact point with its own normal, albedo
    and direct sun."""
    t_hit, n_hit, shape, sun_cos, sun_depth = hits
    dtype = o.dtype
    geo, has_sun, phase, t0, t_end, reached = _segments(fields, o, d, t_hit, n_steps, step)
    cfg = _MarchConfig(geo, phase.shape[1], int(n_steps), float(step), has_sdf=False,
                       slopes=fields.j_slope is not None, sun_exp=_sun_exp(fields))
    T, L, _ = _marcher(forward)(table, phase, o, d, t0, t_end, cfg)

    hit = (shape >= 0) & reached
    if surf_table is not None and fields.albedo is not None and fields.albedo.shape[0]:
        p = o + jnp.where(hit, t_hit, 0.0)[:, None] * d + HIT_LOOKUP_OFFSET * fields.h * n_hit
        irr = _hit_irradiance(surf_table, p, n_hit, geo)
        if has_sun:
            irr = irr + (fields.sun_irradiance * sun_cos
                         * jnp.exp(-fields.sun_extinction * sun_depth))
        s = jnp.maximum(shape, 0)
        b_hit = fields.emission[s] + fields.albedo[s] / math.pi * irr
    else:
        b_hit = jnp.zeros_like(T)
    escaped = ~(shape >= 0) & reached & (d[:, 2] > 0)
    sky = jnp.asarray(fields.sky, dtype)
    radiance = L + jnp.where(hit, T * b_hit, 0.0) + jnp.where(escaped, T * sky, 0.0)
    return TraceResult(radiance, T, hit, jnp.where(hit, t_hit, jnp.inf))


def _chunks(arrays, chunk: int):
    """Split (n, ...) arrays into (n_chunks, chunk, ...) balanced chunks, padding with copies of
    row 0; returns (chunked arrays, n)."""
    n = arrays[0].shape[0]
    n_chunks = -(-n // max(1, chunk))
    chunk = -(-n // n_chunks)  # balanced chunks: fewer than n_chunks padded rays
    pad = n_chunks * chunk - n
    out = []
    for a in arrays:
        if pad:  # their results are dropped
            a = jnp.concatenate([a, jnp.broadcast_to(a[:1], (pad,) + a.shape[1:])])
        out.append(a.reshape((n_chunks, chunk) + a.shape[1:]))
    return out, n


def _source_channels(fields: LatticeFields) -> list:
    """σ_t, j_iso, then one channel per per-ray coefficient of ``_segments``: j_sun (with a
    sun), the K of j_aniso (with harmonics); the six side slopes (the linear scheme); the
    optical depth towards the sun (``sun_depth``, with a sun)."""
    chans = [fields.sigma_t, fields.j_iso]
    if fields.sun_dir is not None:
        chans.append(fields.j_sun)
    if fields.j_aniso is not None:
        chans += [fields.j_aniso[..., k] for k in range(fields.j_aniso.shape[-1])]
    if fields.j_slope is not None:
        chans += [fields.j_slope[..., a] for a in range(SLOPE_CHANNELS)]
    if _sun_exp(fields):
        chans.append(fields.sun_depth)
    return chans


def _sun_exp(fields: LatticeFields) -> bool:
    """Whether the march attenuates the sun's single scattering itself (``sun_depth``)."""
    return fields.sun_dir is not None and fields.sun_depth is not None


@partial(jax.jit, static_argnames=("n_steps", "step", "chunk", "forward"))
def _trace_exact_jit(fields, origins, directions, hits, *, n_steps: int, step: float,
                     chunk: int, forward: bool = False):
    dtype = origins.dtype
    table = _flat_table(_source_channels(fields), dtype)
    surf_table = None
    if fields.irradiance is not None and fields.surface_normal is not None:
        nrm = jnp.asarray(fields.surface_normal, dtype)
        surf_table = _flat_table([fields.irradiance] + [nrm[..., c] for c in range(3)], dtype)
    per_ray = (hits.t.astype(dtype), hits.normal.astype(dtype), hits.shape.astype(jnp.int32),
               hits.sun_cos.astype(dtype), hits.sun_depth.astype(dtype))
    (o, d, *hc), n = _chunks([origins, directions, *per_ray], chunk)
    res = jax.lax.map(lambda x: _trace_chunk_exact(fields, table, surf_table, x[0], x[1],
                                                   tuple(x[2:]), n_steps=n_steps, step=step,
                                                   forward=forward),
                      (o, d, *hc))
    return TraceResult(*(r.reshape(-1)[:n] for r in res))


@partial(jax.jit, static_argnames=("n_steps", "step", "chunk", "forward"))
def _trace_jit(fields, origins, directions, *, n_steps: int, step: float, chunk: int,
               forward: bool = False):
    dtype = origins.dtype
    table = _flat_table(_source_channels(fields) + [fields.sdf], dtype)  # built once for all chunks
    rad = [fields.radiosity_ext]
    if fields.surface_normal is not None:
        nrm = jnp.asarray(fields.surface_normal, dtype)
        m = (jnp.sum(nrm * nrm, axis=-1) > 0).astype(dtype)
        b = fields.radiosity_ext * m
        rad += [b, m] + [b * nrm[..., c] for c in range(3)] + [nrm[..., c] for c in range(3)]
    rad_table = _flat_table(rad, dtype)
    n = origins.shape[0]
    n_chunks = -(-n // max(1, chunk))
    chunk = -(-n // n_chunks)  # balanced chunks: fewer than n_chunks padded rays
    pad = n_chunks * chunk - n
    if pad:  # pad with copies of the first ray; their results are dropped below
        origins = jnp.concatenate([origins, jnp.broadcast_to(origins[:1], (pad, 3))])
        directions = jnp.concatenate([directions, jnp.broadcast_to(directions[:1], (pad, 3))])
    o = origins.reshape(n_chunks, chunk, 3)
    d = directions.reshape(n_chunks, chunk, 3)
    res = jax.lax.map(lambda od: _trace_chunk(fields, table, rad_table, od[0], od[1],
                                              n_steps=n_steps, step=step, forward=forward),
                      (o, d))
    return TraceResult(*(r.reshape(-1)[:n] for r in res))


def trace_rays(fields: LatticeFields, origins, directions, *, step: float | None = None,
               chunk: int | None = None, max_length: float | None = None,
               hits: RayHits | None = None) -> TraceResult:
    """March rays through the lattice; see :func:`render_rays`.  Returns a TraceResult (N,)."""
    step = march_step(fields.h, step)
    if not step > 0:
        raise ValueError(f"step must be positive, got {step}")
    if hits is not None and max_length is None:
        max_length = hits.max_length
    n_steps = march_steps(fields, step, origins, directions, max_length)
    dtype = jnp.result_type(fields.sigma_t)
    o = jnp.asarray(origins, dtype).reshape(-1, 3)
    d = jnp.asarray(directions, dtype).reshape(-1, 3)
    d = d / jnp.linalg.norm(d, axis=-1, keepdims=True)
    forward = _FORWARD_MODE.get()
    if hits is not None:
        return _trace_exact_jit(fields, o, d, hits, n_steps=n_steps, step=step,
                                chunk=march_chunk(chunk), forward=forward)
    return _trace_jit(fields, o, d, n_steps=n_steps, step=step, chunk=march_chunk(chunk),
                      forward=forward)


def render_rays(fields: LatticeFields, origins: Float[Array, "... 3"],
                directions: Float[Array, "... 3"], *, step: float | None = None,
                chunk: int | None = None, max_length: float | None = None,
                hits: RayHits | None = None) -> Float[Array, " N"]:
    """Radiance (N,) arriving at each ray origin along -direction (rays flattened to N).

    Each ray is clipped to the lattice box (only in z when periodic_xy; a ray starting inside
    starts at its origin) and marched with fixed steps ``step`` (default h/2), a static count
    from :func:`march_steps`.  Per step, with coefficients interpolated linearly between the
    step ends: L += T·S·(1 - exp(-σ ds))/σ and T *= exp(-σ ds), S = j_iso + j_sun·p_HG.
    The first sdf ≤ 0 (located within the step by linear interpolation) stops the fog and adds
    T·radiosity_ext there (looked up HIT_BACKOFF·h before the hit); a ray leaving the box
    without a hit adds T·sky if d_z > 0.  The sdf is tested at the step ends only, so a solid
    thinner than a step can be missed.

    With ``hits`` (exact hits of these rays, a :class:`RayHits`), the sdf is not used: the fog
    is marched up to the exact hit, and the surface's radiance there is
    emission + albedo/π·(E + F·cos·exp(-σ·depth)) of the hit shape, with E the diffuse
    irradiance of the SURFACE nodes around the hit weighted by how much their normals agree
    with the hit's (``_hit_irradiance``) and the direct sun exact (``fields.irradiance``,
    ``albedo``, ``emission``, ``sun_irradiance``, ``sun_extinction`` are then needed).

    Differentiable in every float field of ``fields`` (g and sky included), not in the rays.
    Rays are processed ``chunk`` at a time (``lax.map``); the backward pass recomputes each
    chunk's march (memory: O(n_steps · chunk) floats).  Wrap a loss in ``jax.jit``: eager
    ``jax.grad`` compiles the backward pass anew at every call.
    """
    return trace_rays(fields, origins, directions, step=step, chunk=chunk,
                      max_length=max_length, hits=hits).radiance


def render_camera(fields: LatticeFields, camera: Camera, *, supersample: int = 2,
                  step: float | None = None, chunk: int | None = None,
                  max_length: float | None = None,
                  hits: RayHits | None = None) -> Float[Array, "H W"]:
    """Box-filtered image (H, W) of a camera: the mean of :func:`render_rays` over the
    supersample² stratified sub-pixel rays of :func:`camera_rays`, or with ``hits`` (from
    :func:`camera_hits`, which chose the rays) over its rays, per pixel.  Row 0 is the top."""
    return render_cameras(fields, [camera], supersample=supersample, step=step, chunk=chunk,
                          max_length=max_length, hits=None if hits is None else [hits])[0]


def _joined_hits(hits) -> RayHits:
    """Several cameras' RayHits as one (their rays one after the other; the longest segment of
    them all).  Materialised once (an optimisation barrier): XLA would otherwise fuse the
    concatenation into every march step that reads the rays."""
    if len(hits) == 1:
        return hits[0]
    lengths = [h.max_length for h in hits]
    arrays = {f.name: jnp.concatenate([getattr(h, f.name) for h in hits])
              for f in dataclasses.fields(RayHits) if f.name != "max_length"}
    arrays = jax.lax.optimization_barrier(arrays)
    return RayHits(**arrays, max_length=None if None in lengths else max(lengths))


def march_lanes(costs, lanes: int | None = None) -> list[list[int]]:
    """The cameras (their march costs, rays × steps) in at most ``lanes`` groups, each group one
    march of its cameras' rays together: the largest first, each to the group with the least
    so far (each group's cameras in their own order).  ``lanes`` None: one on a CPU (all the
    cameras in one march, see the comment above ``MARCH_CHUNK_CPU``), one per camera elsewhere
    (``_chunk_steps``)."""
    if lanes is None:
        lanes = 1 if _chunk_steps() else len(costs)
    n = max(1, min(int(lanes), len(costs)))
    groups, load = [[] for _ in range(n)], [0.0] * n
    for i in sorted(range(len(costs)), key=lambda i: -costs[i]):
        k = load.index(min(load))
        groups[k].append(i)
        load[k] += costs[i]
    return [sorted(g) for g in groups if g]


def render_cameras(fields: LatticeFields, cameras, *, supersample: int = 2,
                   step: float | None = None, chunk: int | None = None,
                   max_length: float | None = None, hits=None,
                   lanes: int | None = None) -> list:
    """:func:`render_camera` of each of ``cameras`` (``hits``: None, or a RayHits per camera),
    their rays marched in at most ``lanes`` marches (``march_lanes``: one on a CPU), each of
    several cameras' rays together: the compiled program holds that many marches however many
    cameras, which XLA runs side by side.  Each chunk of rays takes its own rays' step
    count (``_live_steps``), so a camera whose paths are shorter pays no more steps for being
    marched with one whose paths are longer."""
    step_len = march_step(fields.h, step)
    if hits is not None:
        rays = [h.pixel.shape[0] for h in hits]
        costs = [r * march_steps(fields, step_len,
                                 max_length=h.max_length if max_length is None else max_length)
                 for r, h in zip(rays, hits)]
    else:
        od = [camera_rays(camera, supersample) for camera in cameras]
        rays = [o.shape[0] * o.shape[1] * o.shape[2] for o, _ in od]
        costs = [r * march_steps(fields, step_len, o, d, max_length)
                 for r, (o, d) in zip(rays, od)]
    images = [None] * len(cameras)
    for group in march_lanes(costs, lanes):
        if hits is not None:
            joined = _joined_hits([hits[i] for i in group])
            rad = render_rays(fields, joined.origins, joined.directions, step=step,
                              chunk=chunk, max_length=max_length, hits=joined)
        else:
            o = np.concatenate([od[i][0].reshape(-1, 3) for i in group])
            d = np.concatenate([od[i][1].reshape(-1, 3) for i in group])
            rad = render_rays(fields, o, d, step=step, chunk=chunk, max_length=max_length)
        a = 0
        for i in group:
            r = rad[a:a + rays[i]]
            a += rays[i]
            if hits is not None:
                W, H = (int(v) for v in cameras[i].resolution)
                img = jax.ops.segment_sum(r * hits[i].weight.astype(r.dtype), hits[i].pixel,
                                          num_segments=H * W)
                images[i] = img.reshape(H, W)
            else:
                H, W, S, _ = od[i][0].shape
                images[i] = r.reshape(H, W, S).mean(axis=-1)
    return images


#: normals closer than this (cosine) count as one surface when looking for edges
EDGE_NORMAL_COS = 0.99
#: hit points farther apart than this along their normal (in domain diagonals) are two surfaces
EDGE_OFFSET = 1e-3


def _sample_keys(hits, o, d, scene_size: float):
    """What decides whether two samples see the same surface: (shape, lit, normal, point)."""
    p = o + np.where(hits.hit, hits.t, 0.0)[..., None] * d
    return hits.shape, hits.lit, hits.normal, p, EDGE_OFFSET * scene_size


def _same(a, b, tol):
    """Whether samples a and b (key tuples, broadcast) see the same smooth, equally lit surface."""
    sa, la, na, pa = a
    sb, lb, nb, pb = b
    both_miss = (sa < 0) & (sb < 0)
    smooth = ((na * nb).sum(-1) >= EDGE_NORMAL_COS) & (np.abs(((pa - pb) * na).sum(-1)) <= tol)
    return both_miss | ((sa == sb) & (la == lb) & smooth)


class _Cast:
    """Host hits of rays (R,): ``t``, ``normal``, ``shape``, ``hit``, ``cos_vis``, ``depth``,
    ``lit`` (the sun reaches the hit)."""

    def __init__(self, scene, o, d, density, origin, h, sun_box=None):
        from ...geometry._hits import first_hits, sun_depth

        hits = first_hits(scene, o, d)
        self.t, self.normal, self.shape, self.hit = hits.t, hits.normal, hits.shape, hits.hit
        self.cos_vis = np.zeros(len(o))
        self.depth = np.zeros(len(o))
        if scene.sun is not None and hits.hit.any():
            m = hits.hit
            p = o[m] + hits.t[m, None] * d[m]
            self.cos_vis[m], self.depth[m] = sun_depth(scene, p, hits.normal[m],
                                                       scene.sun.direction, density, origin, h,
                                                       box=sun_box)
        self.lit = self.cos_vis > 0


def edge_pixels(hits: RayHits, height: int, width: int) -> np.ndarray:
    """(height, width) bool: the pixels whose footprint straddles a geometric or a shadow edge,
    from a camera's exact hits (host).  A pixel straddles one when its sample rays (the
    supersample² stratified ones, or the 16 Hammersley points of a pixel that
    :func:`camera_hits` re-sampled) do not all see the same shape in the same light: another
    shape or none (a silhouette, a wall's rim against the floor behind it), or sunlit and
    shadowed points (a shadow edge).  Such a pixel's value depends on how much of its footprint
    each side covers, and the model reproduces it less well than a pixel on one surface (the
    coverage of its samples, the diffuse light reconstructed on each side from the lattice).
    A smoothly curved surface in one light is not an edge (its normal varies within a pixel,
    which the model follows), so this is narrower than the re-sampling test."""
    pix = np.asarray(hits.pixel)
    key = np.asarray(hits.shape).astype(np.int64) * 2 + (np.asarray(hits.sun_cos) > 0)
    n = int(height) * int(width)
    lo = np.full(n, np.iinfo(np.int64).max)
    hi = np.full(n, np.iinfo(np.int64).min)
    np.minimum.at(lo, pix, key)
    np.maximum.at(hi, pix, key)
    return (lo != hi).reshape(int(height), int(width))


def camera_hits(scene, camera: Camera, supersample: int, density, origin, h: float,
                shape, periodic_xy: bool = False, edge_samples: int = EDGE_SAMPLES,
                sun_box=None) -> RayHits:
    """A camera's sample rays, their exact hits and the sun there (host, once).

    Every pixel starts with the supersample² stratified rays of :func:`camera_rays`.  A pixel
    whose samples, or whose first sample and a 4-neighbour's, see different surfaces (another
    shape, a sunlit against a shadowed point, normals more than ~8° apart, or points apart
    along their normal: an occluding edge of one shape) straddles an edge: its samples are
    replaced by ``edge_samples`` Hammersley points (``_camera.hammersley_ndc``), so that the
    pixel gets the right mix of the surfaces in it (with 2×2 samples an edge pixel's coverage
    is off by up to 1/4, with 16 Hammersley points by ~1/16).
    ``density``, ``origin``, ``h``, ``shape``: the lattice's (the sun's depth integrates its
    density field; the longest fog segment is clipped to its box).  ``sun_box``: None, or the fog's
    box (lo, hi): the sun's depth then runs through ``density`` only inside that box, which
    the density continues outwards from its outer nodes (``geometry._hits.sun_depth``).
    """
    from .._camera import hammersley_ndc, rays_at

    W, H = (int(v) for v in camera.resolution)
    o, d = camera_rays(camera, supersample)
    S = o.shape[2]
    o, d = o.reshape(-1, 3), d.reshape(-1, 3)
    dens = np.asarray(density)
    size = h * float(np.linalg.norm(np.asarray(shape, float)))
    base = _Cast(scene, o, d, dens, origin, h, sun_box)
    keys = _sample_keys(base, o, d, size)
    tol = keys[-1]
    k = tuple(np.asarray(x).reshape((H, W, S) + np.shape(x)[1:]) for x in keys[:-1])
    first = tuple(x[:, :, :1] for x in k)
    edge = ~_same(k, first, tol).all(-1)
    f0 = tuple(x[:, :, 0] for x in k)
    for axis in (0, 1):
        n = H if axis == 0 else W
        if n < 2:
            continue
        lo = tuple(np.take(x, np.arange(n - 1), axis=axis) for x in f0)
        hi = tuple(np.take(x, np.arange(1, n), axis=axis) for x in f0)
        diff = ~_same(lo, hi, tol)
        pad = [(0, 0), (0, 0)]
        pad[axis] = (0, 1)
        edge |= np.pad(diff, pad)
        pad[axis] = (1, 0)
        edge |= np.pad(diff, pad)
    if edge_samples <= S:
        edge[:] = False
    keep = ~edge.reshape(-1)
    pix = np.repeat(np.arange(H * W), S)
    sel = np.repeat(keep, S)
    parts = [(o[sel], d[sel], pix[sel], np.full(int(sel.sum()), 1.0 / S), base, sel)]
    rows, cols = np.nonzero(edge)
    if len(rows):
        E = int(edge_samples)
        x, y = hammersley_ndc(camera, np.stack([rows, cols], -1), E)
        oe, de = rays_at(camera, x, y)
        oe, de = oe.reshape(-1, 3), de.reshape(-1, 3)
        cast = _Cast(scene, oe, de, dens, origin, h, sun_box)
        parts.append((oe, de, np.repeat(rows * W + cols, E), np.full(len(oe), 1.0 / E), cast,
                      slice(None)))
    cat = lambda f: np.concatenate([f(p) for p in parts])  # noqa: E731
    origins = cat(lambda p: p[0])
    directions = cat(lambda p: p[1])
    t = cat(lambda p: p[4].t[p[5]])
    max_length = None
    if not periodic_xy:
        lo = np.asarray(origin, np.float64)
        hi = lo + h * np.asarray(shape, np.float64)
        t0, t1 = _clip(lo, hi, origins, directions, False, np)
        seg = np.minimum(t1, t) - t0
        max_length = float(np.max(np.where(seg > 0, seg, 0.0), initial=0.0))

    def put(x):
        """``x`` on the device in the dtype jnp.asarray would give it (float32, int32 unless
        x64 is on), converted on the host: jnp.asarray of a host array stages an operation that
        compiles anew for every shape, 12-17 ms each, three shapes a camera (measured)."""
        return jax.device_put(np.asarray(x, jax.dtypes.canonicalize_dtype(x.dtype)))

    return RayHits(origins=put(origins), directions=put(directions),
                   pixel=put(cat(lambda p: p[2])), weight=put(cat(lambda p: p[3])), t=put(t),
                   normal=put(cat(lambda p: p[4].normal[p[5]])),
                   shape=put(cat(lambda p: p[4].shape[p[5]]).astype(np.int32)),
                   sun_cos=put(cat(lambda p: p[4].cos_vis[p[5]])),
                   sun_depth=put(cat(lambda p: p[4].depth[p[5]])), max_length=max_length)
