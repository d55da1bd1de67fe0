"""Voxelization: a :class:`~difffog.Scene` → the static :class:`Lattice` of the solvers.

Host-side (NumPy / SciPy / trimesh), run once per scene and resolution, never traced.

Grid
    Cubic voxels of side ``h = (longest domain side) / resolution``; ``max(1, round(side / h))``
    nodes per axis; node ``(i, j, k)`` sits at the cell centre ``origin + (idx + 0.5) * h`` with
    ``origin = domain.min``.  Arrays are indexed ``[ix, iy, iz]``.

Node types (Langer, Breton & Zucker §5)
    ``SOLID``   inside the geometry; light never reaches it.
    ``SURFACE`` a non-SOLID node within Chebyshev (max-norm) distance ``M`` of a SOLID node: light
                is absorbed, reflected and emitted there.  The max-norm makes the shell exactly as
                thick as one step ``(p, q, M)`` of a lattice ray, so a ray never steps from a FREE
                node onto a SOLID one: it lands on the shell first.  With ``boundary =
                "periodic-xy"`` the shell, the shapes and every neighbourhood wrap in x and y.
    ``FREE``    everything else: light travels (and scatters in fog) there.

Geometry rules (node centres)
    * sphere, torus, box, open-box walls: ``SOLID ⇔ analytic SDF < 0``.
    * quad (two-sided): SOLID where the distance to the polygon is below ``w = ‖n‖₁·h/2`` (``n``
      its unit normal).  One 26-connected step changes the signed plane distance by at most
      ``‖n‖₁·h``, so no step jumps over this band: the layer is 26-tunnel-free, yet one node
      thick for an axis-aligned quad (the looser ``|d| ≤ √3·h/2`` gives two).
    * mesh: non-zero winding number (one ray per (x, y) column, crossings counted by an exact,
      half-open rasterization of the triangles, so shared edges and vertices count once; bodies
      that overlap, like the shared airplane's wings and fuselage, are a union).  Then parts
      thinner than the spacing are closed: along each of the 13 lattice directions, an inside
      run that holds no node and enters and leaves through opposite-facing triangles (a thin
      wall, not a grazed thick body) marks its node nearest to the run's middle.  For a sheet of
      zero thickness this is exactly the quad's band (up to exact ties), hence 26-tunnel-free.

SDF (scene units), ``sdf < 0 ⇔ SOLID`` exactly
    Analytic shapes: the exact SDF (a quad: distance to the polygon − w); union = min.  Meshes: the
    exact distance to the closest triangle in a band (the M-node shell outside, 2.5 nodes inside),
    signed by the SOLID mask; farther, the EDT of the mask within the mesh's box (± h/2), and the
    distance to that box beyond (a positive lower bound).

Normals (unit, outward, at SURFACE nodes only)
    ``"com"``: the paper's rule, the direction from the node to the centre of mass of the FREE
    nodes in its (2M+1)³ neighbourhood.  ``"analytic"`` (= ``"auto"``): the SDF gradient of the
    nearest shape (a two-sided quad: towards the node's side; a mesh: away from the closest
    surface point, i.e. the face normal inside a face).  A zero centre-of-mass vector falls back
    to the analytic normal.

Fog (``density``, per node: the fog of the cell it stands for)
    The density multiplier × the share of the node's cell inside the fog's region (exact, per
    axis) and outside the solids (the SDF's tangent plane at the node: exact for flat faces; a
    quad is a sheet and takes no fog), with the fog of each SOLID node's cell added to its
    outward non-SOLID neighbour.  So Σ density·h³ is the scene's fog volume at every
    resolution, wherever the nodes fall against the faces (``_fog_volumes``).  What the cameras
    and the sun's depth sample between nodes is ``fog_density``, the fog's own density.

Material: the shape of a SOLID node (the one with the lowest SDF where shapes overlap); for a
SURFACE node, that of its (Euclidean) nearest SOLID node; -1 at FREE nodes.
"""

from __future__ import annotations

import math
import warnings
from dataclasses import dataclass

import numpy as np
from scipy import ndimage
from scipy.spatial import cKDTree

from .._errors import SceneError
from ..scene._description import Box, Mesh, OpenBox, Quad, Scene, Sphere, Torus

FREE, SURFACE, SOLID = 0, 1, 2
NODE_TYPE_NAMES = ("free", "surface", "solid")
#: the vacuum nodes the renderer adds outside an open domain (``voxelize(margin=...)``).  Light
#: that leaves the domain (a box, convex) never comes back into it, so the margin only serves
#: what lies on the domain's boundary: a wall's outer face or top lit and seen as in open
#: space, which a camera reads from the node beside it and the next.  Two nodes give the
#: images of M + 1 (the margin until stop 82) to float32 rounding on every shared scene
#: (fog-balls at N = 128, M = 5: 140³ → 132³ nodes, the light 14-28% sooner); one node moved
#: fog-balls' images by 0.5% at a few pixels.
VACUUM_MARGIN = 2

_CHUNK = 1 << 20  # nodes per vectorized block when evaluating shapes over the grid
# nodes per block of the evaluations from per-axis tables: their few float64 temporaries stay in
# the L2 cache (N = 128, M = 5: an open box's SDF 19 ms, a torus's 52 ms; 30 and 75 ms in blocks
# of _CHUNK nodes)
_BLOCK = 1 << 16


@dataclass(frozen=True, eq=False)
class Lattice:
    """The voxelized scene (plain NumPy; the solvers convert to jax arrays).

    Shapes below are ``(nx, ny, nz)``; lengths in scene units.
    """

    shape: tuple[int, int, int]
    h: float  # node spacing
    origin: np.ndarray  # (3,) float64, the domain's min corner (node (0,0,0) is at origin + h/2)
    M: int  # shell thickness / direction-set half-width, in nodes
    boundary: str  # "open" | "periodic-xy"
    node_type: np.ndarray  # int8: FREE / SURFACE / SOLID
    # int16: index into scene.shapes of the SOLID node's shape / the SURFACE node's nearest SOLID
    # node's shape; -1 at FREE nodes
    material: np.ndarray
    normal: np.ndarray  # float32 (nx, ny, nz, 3): unit outward normal at SURFACE nodes, 0 elsewhere
    # float32: the fog's density multiplier for the cell each node stands for, so that
    # Σ density·h³ is the fog's volume (cells cut by a region's face or a surface count their
    # share, SOLID cells give theirs to a neighbour; up to ~1.5 beside a surface); 0 at SOLID
    # nodes and outside the fog
    density: np.ndarray
    sdf: np.ndarray  # float32: signed distance to the solid geometry, < 0 exactly at SOLID nodes
    # float32: the fog's density as if there were no solids (grid × region), for what samples
    # the fog between nodes right up to an exact surface (the cameras' march, the sun's depth
    # at a hit): trilinear between the last fog node and a SOLID node it does not fall to 0
    # half-way; None: ``density``
    fog_density: np.ndarray | None = None
    # a density grid's fog: ``density`` and ``fog_density`` as linear maps of the grid (what a
    # fit of the density traces); None for a uniform fog
    density_map: "DensityMap | None" = None

    def counts(self) -> dict[str, int]:
        """Number of nodes of each type: ``{"free": …, "surface": …, "solid": …}``."""
        c = np.bincount(self.node_type.ravel(), minlength=3)
        return {name: int(c[i]) for i, name in enumerate(NODE_TYPE_NAMES)}

    def node_positions(self) -> np.ndarray:
        """World positions of the nodes, (nx, ny, nz, 3) float64."""
        axes = [self.origin[a] + (np.arange(n) + 0.5) * self.h for a, n in enumerate(self.shape)]
        return np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1)

    def optical_depth_range(
        self, scattering: float, absorption: float
    ) -> dict[str, tuple[float, float]]:
        """Per axis ``"x" / "y" / "z"``: (min, max) over the lattice lines parallel to that axis of
        the optical depth ∫σ_t dl across the domain, σ_t = (ζ+γ)·density (midpoint rule)."""
        sigma = (float(scattering) + float(absorption)) * self.density.astype(np.float64)
        out = {}
        for a, name in enumerate("xyz"):
            tau = sigma.sum(axis=a) * self.h
            out[name] = (float(tau.min()), float(tau.max()))
        return out

    @property
    def peak_density(self) -> float:
        """The fog's largest density multiplier at a non-SOLID node: the medium's own, not the
        cell bookkeeping of ``density`` (which exceeds it beside surfaces); what a lattice
        step's optical depth is judged by."""
        fog = self.density if self.fog_density is None else self.fog_density
        return float(np.max(fog, where=self.node_type != SOLID, initial=0.0))

    def max_segment_optical_depth(self, scattering: float, absorption: float) -> float:
        """Largest optical depth σ_t·h·M of one lattice-ray segment (≲ 0.3: see docs/design.md)."""
        return float((scattering + absorption) * self.peak_density * self.h * self.M)

    @property
    def nbytes(self) -> int:
        """Bytes held by the node arrays."""
        return sum(
            a.nbytes for a in (self.node_type, self.material, self.normal, self.density, self.sdf)
        )

    def __repr__(self) -> str:
        c = self.counts()
        return (
            f"Lattice(shape={self.shape}, h={self.h:.4g}, M={self.M}, boundary={self.boundary!r}, "
            f"free={c['free']}, surface={c['surface']}, solid={c['solid']})"
        )


# ----------------------------------------------------------------------------------------------
# entry point


def voxelize(scene: Scene, resolution: int, M: int, *, normals: str = "auto",
             margin: int = 0) -> Lattice:
    """Voxelize ``scene`` on a cubic lattice of ``resolution`` nodes along its longest side.

    ``M`` is the shell thickness in nodes (and the half-width of the solver's direction set);
    ``normals`` is ``"auto"`` (= ``"analytic"``), ``"analytic"`` or ``"com"`` (see the module doc).
    ``margin``: vacuum nodes added outside the domain on every open side (z only for a periodic
    domain).  Surfaces lying on the domain boundary (a wall's top at z = max) then get SURFACE
    nodes on their outer side, so they are lit and seen as in open space; the renderer uses
    ``VACUUM_MARGIN``.  The fog stays inside the domain.
    """
    _check_int("resolution", resolution, 2, "use e.g. resolution=64")
    _check_int("M", M, 1, "use e.g. M=3 (the paper uses M=5 at resolution 128)")
    if normals not in ("auto", "analytic", "com"):
        raise SceneError(
            f"normals={normals!r} is not a normal rule; use 'auto', 'analytic' or 'com'"
        )
    _check_int("margin", margin, 0, f"use 0 (none) or {VACUUM_MARGIN}")
    resolution, M = int(resolution), int(M)

    grid = _Grid.from_domain(scene.domain, resolution, int(margin))
    shapes = [_make_shape(s, i, grid) for i, s in enumerate(scene.shapes)]
    for s in shapes:
        s.warn_if_thin(grid, resolution)

    # --- SOLID, sdf and the owning shape (argmin of the per-shape SDF) -------------------------
    n = grid.shape
    sdf = np.full(n, _far(grid), np.float64)
    owner = np.full(n, -1, np.int16)
    closer = np.empty(n, bool)
    for s in shapes:
        d = s.sdf_grid(grid, M)
        np.less(d, sdf, out=closer)
        np.copyto(sdf, d, where=closer)
        np.copyto(owner, s.index, where=closer)
    solid = sdf < 0
    # float32 must keep the sign: SOLID strictly negative, the rest >= 0 (computed in float64,
    # rounded on the way out)
    sdf32 = np.empty(n, np.float32)
    np.maximum(sdf, 0.0, out=sdf32)
    np.minimum(sdf, -1e-6 * grid.h, out=sdf32, where=solid)

    # --- SURFACE shell: Chebyshev distance <= M from a SOLID node --------------------------------
    near = ndimage.maximum_filter(solid, size=2 * M + 1, mode=grid.modes(), cval=0)
    surface = near & ~solid
    node_type = np.full(n, FREE, np.int8)
    np.copyto(node_type, SURFACE, where=surface)
    np.copyto(node_type, SOLID, where=solid)

    # --- material ----------------------------------------------------------------------------
    material = np.full(n, -1, np.int16)
    np.copyto(material, owner, where=solid)
    if surface.any():
        if len(shapes) == 1:
            np.copyto(material, 0, where=surface)
        else:
            _surface_material(material, solid, owner, surface, grid, M)

    # --- normals -----------------------------------------------------------------------------
    normal = np.zeros(n + (3,), np.float32)
    if surface.any():
        idx = np.nonzero(surface)
        if normals == "com":
            nv, ok = _com_normals(node_type == FREE, idx, M, grid)
            if not ok.all():
                bad = tuple(i[~ok] for i in idx)
                nv[~ok] = _analytic_normals(shapes, owner[bad], bad, grid)
        else:
            nv = _analytic_normals(shapes, owner[idx], idx, grid)
        normal[idx] = nv

    fog_density, cell_fog = _density(scene, grid)
    grid_fog = scene.fog is not None and scene.fog.density is not None
    parts = [] if grid_fog else None
    density = _fog_volumes(cell_fog, sdf, solid, owner, shapes, grid, parts)
    return Lattice(
        shape=n,
        h=grid.h,
        origin=grid.origin.copy(),
        M=M,
        boundary=grid.boundary,
        node_type=node_type,
        material=material,
        normal=normal,
        density=density,
        sdf=sdf32,
        fog_density=fog_density,
        density_map=_density_map(scene, grid, parts) if grid_fog else None,
    )


def _check_int(name, value, lo, fix):
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < lo:
        raise SceneError(f"{name}={value!r} is invalid: it must be an integer >= {lo}; {fix}")


# ----------------------------------------------------------------------------------------------
# grid


@dataclass(frozen=True)
class _Grid:
    shape: tuple[int, int, int]
    h: float
    origin: np.ndarray
    boundary: str
    domain_min: np.ndarray
    domain_size: np.ndarray
    # vacuum nodes before the domain along each axis (the margin; 0 on a periodic axis)
    pad: tuple[int, int, int] = (0, 0, 0)

    @classmethod
    def from_domain(cls, domain, resolution, margin=0):
        lo = np.asarray(domain.min, np.float64)
        size = np.asarray(domain.max, np.float64) - lo
        if not (size > 0).all():
            raise SceneError(f"domain min {tuple(domain.min)} / max {tuple(domain.max)} is empty")
        h = float(size.max()) / resolution
        pad = np.array([0 if (domain.boundary == "periodic-xy" and a < 2) else margin
                        for a in range(3)])
        shape = tuple(max(1, round(s / h)) + 2 * int(m) for s, m in zip(size, pad))
        return cls(shape, h, lo - pad * h, domain.boundary, lo, size, tuple(int(p) for p in pad))

    @property
    def periodic(self) -> bool:
        return self.boundary == "periodic-xy"

    @property
    def period(self) -> np.ndarray:
        """Lateral period of the lattice (n·h), used for periodic images."""
        return np.array([self.shape[0] * self.h, self.shape[1] * self.h, 0.0])

    def modes(self, open_mode="constant"):
        """Per-axis ndimage boundary modes: wrap in x, y when periodic."""
        lat = "wrap" if self.periodic else open_mode
        return (lat, lat, open_mode)

    def axis_coords(self, a, idx=None):
        """Node centres along axis ``a``, from the domain's corner: a node has the same
        coordinate (to the bit) whatever the margin, so a node on a shape's face is classified
        alike on every lattice that holds it (from ``origin`` a margin of 3, 4 or 5 nodes
        flipped 13 nodes of cloud-plane's airplane at N = 64: images 3-14% apart at ~80 pixels)."""
        i = np.arange(self.shape[a]) if idx is None else np.asarray(idx)
        return self.domain_min[a] + (i - self.pad[a] + 0.5) * self.h

    def positions(self, idx) -> np.ndarray:
        """World positions (N, 3) of the nodes with index arrays ``idx = (ix, iy, iz)``."""
        return np.stack([self.axis_coords(a, idx[a]) for a in range(3)], axis=-1)

    def slabs(self):
        """Yield (slice over ix, node positions (k, ny, nz, 3)) in blocks of about _CHUNK nodes."""
        nx, ny, nz = self.shape
        step = max(1, _CHUNK // (ny * nz))
        ys, zs = self.axis_coords(1), self.axis_coords(2)
        for i0 in range(0, nx, step):
            xs = self.axis_coords(0)[i0 : i0 + step]
            p = np.stack(np.meshgrid(xs, ys, zs, indexing="ij"), axis=-1)
            yield slice(i0, i0 + step), p

    def blocks(self):
        """Yield slices over ix of about _BLOCK nodes each."""
        nx, ny, nz = self.shape
        step = max(1, _BLOCK // (ny * nz))
        for i0 in range(0, nx, step):
            yield slice(i0, min(i0 + step, nx))

    def axis_shifts(self, a) -> list[float]:
        """The periodic images' shifts along axis ``a`` (``[0.0]`` along an open axis).

        ``images()`` is the full product of these, so the minimum over the images of an SDF that
        is non-decreasing in one term per axis (a box's ``|x - c| - e``, a sphere's ``(x - c)²``)
        is that SDF of the per-axis minima, exactly (rounding is monotone too)."""
        if self.periodic and a < 2:
            return [i * self.period[a] for i in (-1, 0, 1)]
        return [0.0]

    def images(self) -> list[np.ndarray]:
        """Lateral shifts of the periodic images (just the zero shift for an open domain)."""
        if not self.periodic:
            return [np.zeros(3)]
        px, py, _ = self.period
        return [np.array([i * px, j * py, 0.0]) for i in (-1, 0, 1) for j in (-1, 0, 1)]


def _far(grid: _Grid) -> float:
    """SDF value where there is no geometry at all: the domain diagonal (finite, positive)."""
    return float(np.linalg.norm(grid.domain_size)) + grid.h


# ----------------------------------------------------------------------------------------------
# shapes: SDF and its gradient


class _Shape:
    index: int
    name: str
    kind: str

    def sdf(self, p: np.ndarray) -> np.ndarray:  # (..., 3) -> (...)
        raise NotImplementedError

    def grad(self, p: np.ndarray) -> np.ndarray:  # (N, 3) -> (N, 3) unit
        raise NotImplementedError

    def sdf_grid(self, grid: _Grid, M: int) -> np.ndarray:
        """SDF at every node, with periodic images (min over the lateral shifts)."""
        out = np.empty(grid.shape, np.float64)
        shifts = self.relevant_images(grid)
        for sl, p in grid.slabs():
            out[sl] = np.min([self.sdf(p - s) for s in shifts], axis=0)
        return out

    def relevant_images(self, grid):
        return grid.images()

    def grad_at(self, idx, grid):
        """Unit gradient at the (non-SOLID) nodes with index arrays ``idx``."""
        return self.grad_periodic(grid.positions(idx), grid)

    def grad_periodic(self, p, grid):
        """Gradient of the nearest periodic image."""
        shifts = self.relevant_images(grid)
        if len(shifts) == 1:
            return self.grad(p - shifts[0])
        d = np.stack([self.sdf(p - s) for s in shifts])
        best = np.argmin(d, axis=0)
        out = np.empty_like(p)
        for i, s in enumerate(shifts):
            m = best == i
            if m.any():
                out[m] = self.grad(p[m] - s)
        return out

    def warn_if_thin(self, grid, resolution):
        t = self.thickness()
        if t is not None and t < grid.h:
            need = math.ceil(resolution * grid.h / t) + 1
            warnings.warn(
                f"shape '{self.name}' ({self.kind}) is {t:.4g} thick, less than one voxel "
                f"(h = {grid.h:.4g} at resolution {resolution}): it may vanish or leak light; "
                f"use resolution >= {need}",
                stacklevel=3,
            )

    def thickness(self) -> float | None:
        return None


def _norm3(v):
    """``np.linalg.norm(v, axis=-1)`` bit for bit (its sum runs x, y, z in order), for (..., 3)
    ``v``, without its (..., 3) temporaries."""
    x, y, z = v[..., 0], v[..., 1], v[..., 2]
    return np.sqrt(x * x + y * y + z * z)


def _unit(v, fallback=None):
    n = _norm3(v)[..., None]
    ok = n > 1e-300
    u = np.where(ok, v / np.where(ok, n, 1.0), 0.0)
    if fallback is not None:
        u = np.where(ok, u, fallback)
    return u


class _SphereS(_Shape):
    def __init__(self, s: Sphere, index):
        self.index, self.name, self.kind = index, s.name, s.kind
        self.c, self.r = np.asarray(s.center, float), float(s.radius)

    def sdf(self, p):
        return _norm3(p - self.c) - self.r

    def sdf_grid(self, grid: _Grid, M: int) -> np.ndarray:
        """``sdf`` at every node, with its arithmetic, from per-axis tables: the squared offset
        along each axis (minimised over the periodic shifts), summed x, y, z as the norm does."""
        d2 = [
            np.min([np.square(grid.axis_coords(a) - s - self.c[a]) for s in grid.axis_shifts(a)], 0)
            for a in range(3)
        ]
        sxy = np.add.outer(d2[0], d2[1])
        out = np.empty(grid.shape, np.float64)
        for sl in grid.blocks():
            o = out[sl]
            np.add(sxy[sl, :, None], d2[2], out=o)
            np.sqrt(o, out=o)
            np.subtract(o, self.r, out=o)
        return out

    def grad(self, p):
        return _unit(p - self.c, fallback=np.array([0.0, 0.0, 1.0]))

    def warn_if_thin(self, grid, resolution):  # a ball thinner than a voxel: its radius < h
        if self.r < grid.h:
            need = math.ceil(resolution * grid.h / self.r) + 1
            warnings.warn(
                f"shape '{self.name}' (sphere) has radius {self.r:.4g}, less than one voxel "
                f"(h = {grid.h:.4g} at resolution {resolution}): it is a few nodes at most; "
                f"use resolution >= {need}",
                stacklevel=3,
            )


class _TorusS(_Shape):
    def __init__(self, s: Torus, index):
        self.index, self.name, self.kind = index, s.name, s.kind
        self.c = np.asarray(s.center, float)
        self.a = np.asarray(s.axis, float) / np.linalg.norm(s.axis)
        self.R, self.r = float(s.major_radius), float(s.minor_radius)

    def core_point(self, p):
        """Nearest point of the core circle (radius R around the axis)."""
        v = p - self.c
        z = v @ self.a
        radial = v - z[..., None] * self.a
        return self.c + self.R * _unit(radial)

    def sdf(self, p):
        return self._sdf_v(p - self.c)

    def _sdf_v(self, v):
        """SDF at the offsets ``v = p - c`` (..., 3)."""
        z = v @ self.a
        rho = np.sqrt(np.maximum(np.einsum("...i,...i", v, v) - z * z, 0.0))
        return np.hypot(rho - self.R, z) - self.r

    def sdf_grid(self, grid: _Grid, M: int) -> np.ndarray:
        """``sdf`` at every node, block by block, the offsets filled in from per-axis tables
        rather than built as positions and then shifted (the same values)."""
        out = np.empty(grid.shape, np.float64)
        ny, nz = grid.shape[1:]
        tables = [
            [grid.axis_coords(a) - s - self.c[a] for s in grid.axis_shifts(a)] for a in range(3)
        ]
        for sl in grid.blocks():
            v = np.empty((sl.stop - sl.start, ny, nz, 3))
            best = None
            for tx in tables[0]:
                for ty in tables[1]:
                    v[..., 0] = tx[sl, None, None]
                    v[..., 1] = ty[None, :, None]
                    v[..., 2] = tables[2][0]
                    d = self._sdf_v(v)
                    best = d if best is None else np.minimum(best, d, out=best)
            out[sl] = best
        return out

    def grad(self, p):
        return _unit(p - self.core_point(p), fallback=self.a)

    def thickness(self):
        return 2 * self.r


class _BoxesS(_Shape):
    """A union of axis-aligned boxes: a box, or the walls of an open box.

    Evaluated from 1-D tables: a box's SDF depends on a node through one term per axis,
    ``q = |x - c| - e``: it is ``max q`` where that is <= 0 (inside) and ``sqrt(Σ max(q, 0)²)``
    elsewhere (the sum over x, y, z in that order, as ``np.linalg.norm`` adds).  So the union
    over the boxes is ``min max q`` where that is <= 0 and the square root of ``min Σ max(q, 0)²``
    elsewhere, every step monotone: the same floating-point values as the point formula,
    computed in a few full-grid passes instead of one (N, 3) evaluation per box (the 5 walls of
    an open box at N = 128, M = 5: 1.9 s before, 0.02 s).
    """

    def __init__(self, s, index):
        self.index, self.name, self.kind = index, s.name, s.kind
        if isinstance(s, OpenBox):
            boxes = s.walls()
            self._thick = float(s.thickness)
        else:
            boxes = [(s.min, s.max)]
            self._thick = float(np.min(np.subtract(s.max, s.min)))
        self.boxes = [(np.asarray(a, float), np.asarray(b, float)) for a, b in boxes]
        self._c = np.array([(lo + hi) / 2 for lo, hi in self.boxes]).reshape(-1, 3)
        self._e = np.array([(hi - lo) / 2 for lo, hi in self.boxes]).reshape(-1, 3)

    def _tables(self, grid, a, shift):
        """Per box (rows) and node along axis ``a``: the offset ``d = x - shift - c`` and
        ``q = |d| - e``."""
        d = grid.axis_coords(a) - shift - self._c[:, a, None]
        return d, np.abs(d) - self._e[:, a, None]

    def sdf_grid(self, grid: _Grid, M: int) -> np.ndarray:
        if not self.boxes:
            return np.full(grid.shape, np.inf)
        q = [
            np.min([self._tables(grid, a, s)[1] for s in grid.axis_shifts(a)], 0) for a in range(3)
        ]
        o2 = [np.square(np.maximum(qa, 0.0)) for qa in q]
        # boxes with the same z table share the 3-D pass: the min over them of max(qxy, qz) and
        # of sxy + oz² is max(min qxy, qz) and (min sxy) + oz² (the 4 side walls of an open box)
        groups = {}
        for b in range(len(self.boxes)):
            qxy, sxy = np.maximum.outer(q[0][b], q[1][b]), np.add.outer(o2[0][b], o2[1][b])
            g = groups.setdefault(q[2][b].tobytes(), [qxy, sxy, q[2][b], o2[2][b]])
            if g[0] is not qxy:
                np.minimum(g[0], qxy, out=g[0])
                np.minimum(g[1], sxy, out=g[1])
        out = np.empty(grid.shape, np.float64)
        for sl in grid.blocks():
            ssum = out[sl]  # min Σ max(q, 0)², then the SDF
            qmax = np.empty_like(ssum)  # min max q
            tmp = np.empty_like(ssum)
            for i, (qxy, sxy, qz, oz) in enumerate(groups.values()):
                if i == 0:
                    np.maximum(qxy[sl, :, None], qz, out=qmax)
                    np.add(sxy[sl, :, None], oz, out=ssum)
                else:
                    np.minimum(qmax, np.maximum(qxy[sl, :, None], qz, out=tmp), out=qmax)
                    np.minimum(ssum, np.add(sxy[sl, :, None], oz, out=tmp), out=ssum)
            np.sqrt(ssum, out=ssum)
            np.copyto(ssum, qmax, where=qmax <= 0)
        return out

    def grad_at(self, idx, grid):
        """Unit outward gradient of the nearest box (the first on ties) of the nearest periodic
        image (the first on ties) at the non-SOLID nodes ``idx``: outside, away from the box's
        closest point; on its boundary, along the axis of the nearest face (the first on ties).

        At a non-SOLID node every box's SDF is the square root of its Σ max(q, 0)².  The per-axis
        tables are gathered at the nodes and combined per axis (N = 128, M = 5, 0.8 M nodes on
        the walls of fog-balls: 0.6 s as (N, 3) arrays before, 0.1 s)."""
        ny = grid.shape[1]
        shifts = [grid.axis_shifts(a) for a in range(3)]
        tabs = [[self._tables(grid, a, s) for s in shifts[a]] for a in range(3)]
        D = [np.stack([t[0] for t in tabs[a]]) for a in range(3)]  # (shift, box, node)
        Q = [np.stack([t[1] for t in tabs[a]]) for a in range(3)]
        O2 = [np.square(np.maximum(qa, 0.0)) for qa in Q]
        ix, iy, iz = idx
        ixy = ix * ny + iy
        n, nb, nsy = len(ix), len(self.boxes), len(shifts[1])
        best, f = np.full(n, np.inf), np.empty(n)
        code = np.zeros(n, np.int64)  # (x shift · (y shifts) + y shift) · (boxes) + box
        closer = np.empty(n, bool)
        for i in range(len(shifts[0])):  # strictly smaller wins, in the order of grid.images()
            for j in range(nsy):
                for b in range(nb):
                    sxy = np.add.outer(O2[0][i, b], O2[1][j, b]).ravel()
                    np.add(sxy[ixy], O2[2][0, b][iz], out=f)
                    np.sqrt(f, out=f)
                    np.less(f, best, out=closer)
                    np.copyto(best, f, where=closer)
                    np.copyto(code, (i * nsy + j) * nb + b, where=closer)
        si, rest = np.divmod(code, nsy * nb)
        sj, box = np.divmod(rest, nb)
        # flat indices into the (shift, box, node) tables of each axis
        at = [
            (si * nb + box) * D[0].shape[2] + ix,
            (sj * nb + box) * D[1].shape[2] + iy,
            box * D[2].shape[2] + iz,
        ]
        sgn = [np.where(Da >= 0, 1.0, -1.0) for Da in D]
        m = [np.take(sa * np.maximum(Qa, 0.0), ia) for sa, Qa, ia in zip(sgn, Q, at)]
        nrm = np.sqrt(m[0] * m[0] + m[1] * m[1] + m[2] * m[2])
        ok = nrm > 1e-300
        safe = np.where(ok, nrm, 1.0)
        out = np.empty((n, 3))
        for a in range(3):  # outside the box (some q > 0, so m != 0): away from it
            out[:, a] = np.where(ok, m[a] / safe, 0.0)
        face = np.nonzero((m[0] == 0) & (m[1] == 0) & (m[2] == 0))[0]  # on it: max q = 0
        if face.size:
            qf = np.stack([np.take(Qa, ia[face]) for Qa, ia in zip(Q, at)], axis=-1)
            sf = np.stack([np.take(sa, ia[face]) for sa, ia in zip(sgn, at)], axis=-1)
            ax = np.argmax(qf, axis=-1)
            out[face] = 0.0
            out[face, ax] = sf[np.arange(face.size), ax]
        return out

    def thickness(self):
        return self._thick if self.boxes else None


def _closest_on_triangles(p, a, b, c):
    """Closest points on triangles (a, b, c) to points p; all (..., 3) broadcast (Ericson 5.1.5)."""
    ab, ac, ap = b - a, c - a, p - a
    d1, d2 = np.einsum("...i,...i", ab, ap), np.einsum("...i,...i", ac, ap)
    bp = p - b
    d3, d4 = np.einsum("...i,...i", ab, bp), np.einsum("...i,...i", ac, bp)
    cp = p - c
    d5, d6 = np.einsum("...i,...i", ab, cp), np.einsum("...i,...i", ac, cp)
    va, vb, vc = d3 * d6 - d5 * d4, d5 * d2 - d1 * d6, d1 * d4 - d3 * d2

    def div(x, y):
        return x / np.where(y == 0, 1.0, y)

    denom = va + vb + vc
    v_in, w_in = div(vb, denom), div(vc, denom)
    res = a + ab * v_in[..., None] + ac * w_in[..., None]  # interior
    cb = c - b
    w_bc = div(d4 - d3, (d4 - d3) + (d5 - d6))
    res = np.where(
        ((va <= 0) & (d4 - d3 >= 0) & (d5 - d6 >= 0))[..., None], b + cb * w_bc[..., None], res
    )
    w_ac = div(d2, d2 - d6)
    res = np.where(((vb <= 0) & (d2 >= 0) & (d6 <= 0))[..., None], a + ac * w_ac[..., None], res)
    res = np.where(((d6 >= 0) & (d5 <= d6))[..., None], c, res)
    v_ab = div(d1, d1 - d3)
    res = np.where(((vc <= 0) & (d1 >= 0) & (d3 <= 0))[..., None], a + ab * v_ab[..., None], res)
    res = np.where(((d3 >= 0) & (d4 <= d3))[..., None], b, res)
    res = np.where(((d1 <= 0) & (d2 <= 0))[..., None], a, res)
    return res


class _QuadS(_Shape):
    """Two-sided polygon (two triangles), thickened to a 26-tunnel-free layer: SOLID where the
    distance to the polygon is below w = ‖n‖₁·h/2 (see the module docstring).

    A horizontal quad (its corners at one z; the ground of the shipped scenes) is evaluated per
    (x, y) column and per z layer: the in-polygon test and the closest points' x, y do not depend
    on z (the z terms of their dot products are products with an exact 0), the closest points lie
    at the corners' z, and the norm adds the z term last.  So ``sdf_grid`` and ``grad_at`` take
    the point formula's values from 2-D and 1-D tables (N = 128, M = 5: 1.6 s before, 0.02 s).
    """

    def __init__(self, s: Quad, index, grid):
        self.index, self.name, self.kind = index, s.name, s.kind
        c = np.asarray(s.corners, float)
        self.tris = []
        for t in ((0, 1, 2), (0, 2, 3)):
            a, b, cc = c[list(t)]
            n = np.cross(b - a, cc - a)
            if np.linalg.norm(n) > 1e-300:
                self.tris.append((a, b, cc, n / np.linalg.norm(n)))
        if not self.tris:
            raise SceneError(f"quad '{s.name}' is degenerate: its corners {s.corners} span no area")
        self.n = self.tris[0][3]
        self.w = 0.5 * grid.h * float(np.abs(self.n).sum()) * (1 + 1e-6)
        size = float(np.linalg.norm(c.max(0) - c.min(0)))
        self.planar = len(self.tris) == 2 and abs(float((c[3] - c[0]) @ self.n)) <= 1e-9 * size
        self.horizontal = (
            self.planar
            and (c[:, 2] == c[0, 2]).all()
            and self.n[0] == 0
            and self.n[1] == 0
            and abs(self.n[2]) == 1
        )

    def _separable(self, grid) -> bool:
        # one-row matrix products take another code path in NumPy (not the same bits)
        return self.horizontal and grid.shape[0] * grid.shape[1] >= 2

    def _z_terms(self, grid):
        """Per z layer: the signed distance to the plane ``(p - a0) @ n``, and the z offsets from
        a node to its projection on the plane (inside the polygon) and to the corners' z."""
        z = grid.axis_coords(2)
        a0z, nz = self.tris[0][0][2], self.n[2]
        dn = (z - a0z) * nz
        return dn, z - (z - dn * nz), z - a0z

    def _columns(self, grid, shift):
        """Per (x, y) column (flat index ix·ny + iy) of the periodic image shifted by ``shift``:
        whether it projects inside the polygon; per triangle (first axis), the x and y offsets of
        its nodes from their closest point on the triangle and the sum of their squares (inf
        inside)."""
        nx, ny = grid.shape[:2]
        x = np.repeat(grid.axis_coords(0) - shift[0], ny)
        y = np.tile(grid.axis_coords(1) - shift[1], nx)
        p = np.stack([x, y, np.full(nx * ny, self.tris[0][0][2])], axis=-1)  # in the plane
        inside = np.zeros(nx * ny, bool)
        for a, b, c, _ in self.tris:
            inside |= _in_triangle(p, a, b, c)
        rest = np.nonzero(~inside)[0]
        ex, ey = np.zeros((2, 2, nx * ny))
        e2 = np.full((2, nx * ny), np.inf)
        for t, (a, b, c, _) in enumerate(self.tris):
            q = _closest_on_triangles(p[rest], a, b, c)
            ex[t, rest], ey[t, rest] = x[rest] - q[:, 0], y[rest] - q[:, 1]
            e2[t, rest] = ex[t, rest] * ex[t, rest] + ey[t, rest] * ey[t, rest]
        return inside, ex, ey, e2

    def sdf_grid(self, grid: _Grid, M: int) -> np.ndarray:
        if not self._separable(grid):
            return super().sdf_grid(grid, M)
        _, ez_in, ez_out = self._z_terms(grid)
        val_in = np.sqrt(ez_in * ez_in) - self.w  # a node over the polygon: its plane distance
        # over the images, min of the squared in-plane offset of the columns projecting outside
        # (sqrt(e2 + ez²) - w is monotone in e2), and whether any image projects inside
        any_in = np.zeros(grid.shape[0] * grid.shape[1], bool)
        e2_out = np.full(grid.shape[0] * grid.shape[1], np.inf)
        for shift in grid.images():
            inside, _, _, e2 = self._columns(grid, shift)
            any_in |= inside
            np.minimum(e2_out, e2.min(axis=0), out=e2_out)
        out = np.empty(grid.shape, np.float64)
        out[...] = val_in
        cols = out.reshape(-1, grid.shape[2])
        fin = np.isfinite(e2_out)
        o = np.sqrt(e2_out[fin][:, None] + ez_out * ez_out) - self.w
        both = any_in[fin]
        o[both] = np.minimum(o[both], val_in)
        cols[fin] = o
        return out

    def grad_at(self, idx, grid):
        if not self._separable(grid):
            return super().grad_at(idx, grid)
        ix, iy, iz = idx
        col = ix * grid.shape[1] + iy
        dn, ez_in, ez_out = (t[iz] for t in self._z_terms(grid))
        val_in = np.sqrt(ez_in * ez_in) - self.w
        ez2 = ez_out * ez_out
        best = np.full(len(iz), np.inf)
        vec = np.zeros((len(iz), 3))
        closer = np.empty(len(iz), bool)
        for shift in grid.images():  # the nearest image, the first on ties
            inside, ex, ey, e2 = self._columns(grid, shift)
            ins = inside[col]
            d0, d1 = np.sqrt(e2[0, col] + ez2), np.sqrt(e2[1, col] + ez2)
            t1 = d1 < d0  # the nearer triangle, the first on ties
            f = np.where(ins, val_in, np.where(t1, d1, d0) - self.w)
            np.less(f, best, out=closer)
            np.copyto(best, f, where=closer)
            # from the closest point: (0, 0, plane offset) over the polygon, else beside it
            np.copyto(
                vec[:, 0], np.where(ins, 0.0, np.where(t1, ex[1, col], ex[0, col])), where=closer
            )
            np.copyto(
                vec[:, 1], np.where(ins, 0.0, np.where(t1, ey[1, col], ey[0, col])), where=closer
            )
            np.copyto(vec[:, 2], np.where(ins, ez_in, ez_out), where=closer)
        side = np.where((dn >= 0)[:, None], self.n, -self.n)
        return _unit(vec, fallback=side)

    def _closest(self, p):
        """Closest points of the polygon to p (N, 3)."""
        a0 = self.tris[0][0]
        dn = (p - a0) @ self.n
        q = p - dn[:, None] * self.n  # projection on the plane
        if self.planar:
            inside = np.zeros(len(p), bool)
            for a, b, c, _ in self.tris:
                inside |= _in_triangle(q, a, b, c)
            rest = np.nonzero(~inside)[0]
        else:
            rest = np.arange(len(p))
        if rest.size:
            pr = p[rest]
            cands = [_closest_on_triangles(pr, a, b, c) for a, b, c, _ in self.tris]
            d = np.stack([np.linalg.norm(pr - qq, axis=-1) for qq in cands])
            best = np.argmin(d, axis=0)
            q[rest] = np.choose(best[:, None], cands)
        return q

    def sdf(self, p):
        flat = p.reshape(-1, 3)
        d = np.linalg.norm(flat - self._closest(flat), axis=-1) - self.w
        return d.reshape(p.shape[:-1])

    def grad(self, p):
        side = np.where(((p - self.tris[0][0]) @ self.n)[:, None] >= 0, self.n, -self.n)
        return _unit(p - self._closest(p), fallback=side)


def _in_triangle(q, a, b, c):
    """Whether points q (N, 3) lying in the triangle's plane are inside it (barycentric test)."""
    v0, v1, x = b - a, c - a, q - a
    d00, d01, d11 = v0 @ v0, v0 @ v1, v1 @ v1
    den = d00 * d11 - d01 * d01
    d20, d21 = x @ v0, x @ v1
    v = (d11 * d20 - d01 * d21) / den
    w = (d00 * d21 - d01 * d20) / den
    return (v >= 0) & (w >= 0) & (v + w <= 1)


# ----------------------------------------------------------------------------------------------
# meshes


_DIRECTIONS_13 = [
    (1, 0, 0), (0, 1, 0), (0, 0, 1),
    (1, 1, 0), (1, -1, 0), (1, 0, 1), (1, 0, -1), (0, 1, 1), (0, 1, -1),
    (1, 1, 1), (1, 1, -1), (1, -1, 1), (1, -1, -1),
]  # fmt: skip


def _line_basis(d):
    """Unimodular integer basis (rows d, e1, e2): node = i·d + j·e1 + k·e2, lines along d."""
    d = np.array(d)
    if d[0] != 0:
        return np.array([d, [0, 1, 0], [0, 0, 1]])
    if d[1] != 0:
        return np.array([d, [1, 0, 0], [0, 0, 1]])
    return np.array([d, [1, 0, 0], [0, 1, 0]])


def _line_crossings(W, faces, max_pairs=1 << 22):
    """Crossings of a triangle mesh with the lattice lines (j, k integer) along the i axis.

    ``W`` (nv, 3) are vertex coordinates (i, j, k).  A line hits a triangle when its (j, k) lies in
    the projected triangle under a half-open rule that is exact and consistent between the triangles
    sharing an edge (edge functions computed from a canonical vertex order, ties given to the side
    of a fixed generic direction), so a closed mesh gives a balanced crossing count on every line.
    Returns j, k (int64), t (the i coordinate of the crossing), the orientation sign (±1) and the
    face index of every crossing.
    """
    P = W[:, 1:]
    fa, fb, fc = faces[:, 0], faces[:, 1], faces[:, 2]
    area2 = _cross2(P[fb] - P[fa], P[fc] - P[fa])
    fid = np.nonzero(area2 != 0)[0]  # faces parallel to the lines never count
    if fid.size == 0:
        z = np.zeros(0, np.int64)
        return z, z, np.zeros(0), np.zeros(0, np.int8), z
    Pf = P[faces[fid]]  # (F, 3, 2)
    jlo, jhi = (
        np.ceil(Pf[..., 0].min(1)).astype(np.int64),
        np.floor(Pf[..., 0].max(1)).astype(np.int64),
    )
    klo, khi = (
        np.ceil(Pf[..., 1].min(1)).astype(np.int64),
        np.floor(Pf[..., 1].max(1)).astype(np.int64),
    )
    nk = np.maximum(khi - klo + 1, 0)
    cnt = np.maximum(jhi - jlo + 1, 0) * nk
    csum = np.cumsum(cnt)
    out, s = [], 0
    while s < fid.size:  # blocks of at most max_pairs candidate (triangle, line) pairs
        e = max(
            int(np.searchsorted(csum, (csum[s - 1] if s else 0) + max_pairs, side="right")), s + 1
        )
        b = slice(s, e)
        out.append(_crossings_block(W, faces, fid[b], area2[fid[b]], jlo[b], klo[b], nk[b], cnt[b]))
        s = e
    return tuple(np.concatenate(x) for x in zip(*out))


def _cross2(u, v):
    return u[..., 0] * v[..., 1] - u[..., 1] * v[..., 0]


def _crossings_block(W, faces, fid, area2, jlo, klo, nk, cnt):
    tri = np.repeat(np.arange(fid.size), cnt)
    r = np.arange(tri.size) - np.repeat(np.cumsum(cnt) - cnt, cnt)
    pj = jlo[tri] + r // nk[tri]
    pk = klo[tri] + r % nk[tri]
    orient = np.sign(area2)[tri]
    fv = faces[fid[tri]]  # (N, 3)
    hit = np.ones(tri.size, bool)
    lam = []
    for u_col, v_col in ((1, 2), (2, 0), (0, 1)):  # the edge opposite vertex 0, 1, 2
        U, V = W[fv[:, u_col]], W[fv[:, v_col]]
        # canonical order of the edge's ends (lexicographic on (j, k, i)): both triangles sharing
        # the edge then compute the very same floating-point edge function
        swap = (U[:, 1] > V[:, 1]) | (
            (U[:, 1] == V[:, 1])
            & ((U[:, 2] > V[:, 2]) | ((U[:, 2] == V[:, 2]) & (U[:, 0] > V[:, 0])))
        )
        lo = np.where(swap[:, None], V, U)
        hi = np.where(swap[:, None], U, V)
        d0, d1 = hi[:, 1] - lo[:, 1], hi[:, 2] - lo[:, 2]
        E = d0 * (pk - lo[:, 2]) - d1 * (pj - lo[:, 1])
        s = orient * np.where(swap, -1.0, 1.0)  # sign of E on the triangle's interior side
        n0, n1 = -s * d1, s * d0  # interior normal of the edge; ties go to the side of (1, 0+)
        tie = (n0 > 0) | ((n0 == 0) & (n1 > 0))
        hit &= (s * E > 0) | ((E == 0) & tie)
        lam.append(s * E)
    lam = np.stack(lam, axis=1)[hit]  # barycentric weights (unnormalized)
    fv = fv[hit]
    ti = W[fv, 0]  # (N, 3) i coordinates of the vertices
    tot = lam.sum(1)
    t = np.where(tot > 0, (lam * ti).sum(1) / np.where(tot > 0, tot, 1.0), ti.mean(1))
    return pj[hit], pk[hit], t, orient[hit].astype(np.int8), fid[tri[hit]]


def _inside_runs(j, k, t, sgn, face):
    """Inside runs (non-zero winding number) of every balanced line.

    Returns the runs as (j, k, t0, t1, entry face, exit face), and the (j, k) of the unbalanced
    lines (a round-off failure of the crossing test, or a mesh that is not closed).
    """
    if t.size == 0:
        z = np.zeros(0, np.int64)
        return (z, z, np.zeros(0), np.zeros(0), z, z), (z, z)
    j0, k0 = j.min(), k.min()
    nk = k.max() - k0 + 1
    key = (j - j0) * nk + (k - k0)
    order = np.lexsort((t, key))
    key, t, c, face = key[order], t[order], sgn[order].astype(np.int64), face[order]
    first = np.r_[True, key[1:] != key[:-1]]
    last = np.r_[key[1:] != key[:-1], True]
    cs = np.cumsum(c)
    start = np.maximum.accumulate(np.where(first, np.arange(key.size), 0))
    w_after = cs - np.where(start > 0, cs[start - 1], 0)  # winding number just after each crossing
    w_before = w_after - c
    bad = key[last & (w_after != 0)]
    good = ~np.isin(key, bad)
    st = good & (w_before == 0) & (w_after != 0)
    en = good & (w_before != 0) & (w_after == 0)
    runs = (key[st] // nk + j0, key[st] % nk + k0, t[st], t[en], face[st], face[en])
    return runs, (bad // nk + j0, bad % nk + k0)


class _MeshS(_Shape):
    def __init__(self, s: Mesh, index, grid: _Grid):
        self.index, self.name, self.kind = index, s.name, s.kind
        if s.vertices is None or s.faces is None:
            raise SceneError(f"mesh '{s.name}' has no geometry loaded (vertices/faces are None)")
        V = np.asarray(s.vertices, np.float64)
        F = np.asarray(s.faces, np.int64)
        if _signed_volume(V, F) < 0:  # inside-out file: flip so that normals point outwards
            F = F[:, ::-1]
        self.bounds = np.array([V.min(0), V.max(0)])
        if grid.periodic:  # the copies that can reach the domain
            reach = (float(np.max(grid.shape)) + 4) * grid.h
            keep = []
            for sh in grid.images():
                lo, hi = self.bounds + sh
                if (hi[:2] > grid.origin[:2] - reach).all() and (
                    lo[:2] < grid.origin[:2] + grid.period[:2] + reach
                ).all():
                    keep.append(sh)
            V = np.concatenate([V + sh for sh in keep])
            F = np.concatenate([F + i * len(s.vertices) for i in range(len(keep))])
        self.V, self.F = V, F
        self.face_normal = _unit(np.cross(V[F[:, 1]] - V[F[:, 0]], V[F[:, 2]] - V[F[:, 0]]))
        self._tree = None
        self._h = grid.h
        # closest points of the band nodes, kept by sdf_grid for the normals: (flat, point, face)
        self._cache = (np.zeros(0, np.int64), np.zeros((0, 3)), np.zeros(0, np.int64))

    def relevant_images(self, grid):
        return [np.zeros(3)]  # the periodic copies are already in self.V

    def thickness(self):
        return float((self.bounds[1] - self.bounds[0]).min())

    # -- inside test ------------------------------------------------------------------------
    def solid_mask(self, grid: _Grid) -> np.ndarray:
        n = grid.shape
        # the domain's nodes at integer coordinates (from the domain's corner, so that the
        # rounding does not follow the margin, ``_Grid.axis_coords``); ``off`` shifts integer
        # node indices to the lattice's (exactly)
        off = np.asarray(grid.pad, np.int64)
        Vi = (self.V - grid.domain_min) / grid.h - 0.5
        mask = np.zeros(n, bool)
        # 1) non-zero winding along z columns (x, y) -> fill
        Bz = np.array([[0, 0, 1], [1, 0, 0], [0, 1, 0]])
        (rj, rk, t0, t1, _, _), (bj, bk) = _inside_runs(
            *_line_crossings(Vi @ np.linalg.inv(Bz), self.F)
        )
        rj, rk, bj, bk = rj + off[0], rk + off[1], bj + off[0], bk + off[1]
        ok = (rj >= 0) & (rj < n[0]) & (rk >= 0) & (rk < n[1])
        rj, rk, t0, t1 = rj[ok], rk[ok], t0[ok], t1[ok]
        a = np.clip(np.ceil(t0) + off[2], 0, n[2]).astype(np.int64)
        b = np.clip(np.floor(t1) + 1 + off[2], 0, n[2]).astype(np.int64)
        if rj.size:  # over the columns' bounding box only
            j0, k0 = rj.min(), rk.min()
            diff = np.zeros((rj.max() - j0 + 1, rk.max() - k0 + 1, n[2] + 1), np.int32)
            np.add.at(diff, (rj - j0, rk - k0, a), 1)
            np.add.at(diff, (rj - j0, rk - k0, b), -1)
            cols = (slice(j0, j0 + diff.shape[0]), slice(k0, k0 + diff.shape[1]))
            mask[cols] = np.cumsum(diff, axis=2)[..., :-1] > 0
        bad = (bj >= 0) & (bj < n[0]) & (bk >= 0) & (bk < n[1])
        if bad.any():  # unbalanced columns (round-off at a vertex): ask trimesh for those nodes
            self._fallback_columns(mask, bj[bad], bk[bad], grid)
        # 2) close parts thinner than the spacing along each of the 13 lattice directions
        for d in _DIRECTIONS_13:
            B = _line_basis(d)
            (rj, rk, t0, t1, fa, fb), _ = _inside_runs(
                *_line_crossings(Vi @ np.linalg.inv(B), self.F)
            )
            # a run that holds no node, through opposite-facing surfaces (a thin wall crossed, not
            # a thick body's surface grazed)
            thin = (np.floor(t1) < np.ceil(t0)) & (
                np.einsum("ij,ij->i", self.face_normal[fa], self.face_normal[fb]) < 0
            )
            if not thin.any():
                continue
            i = np.rint(0.5 * (t0[thin] + t1[thin]))
            node = (np.stack([i, rj[thin], rk[thin]], 1) @ B).astype(np.int64) + off
            inb = ((node >= 0) & (node < np.array(n))).all(1)
            mask[tuple(node[inb].T)] = True
        return mask

    def _fallback_columns(self, mask, cx, cy, grid):
        import trimesh

        tm = trimesh.Trimesh(self.V, self.F, process=False)
        nz = grid.shape[2]
        ix, iz = np.repeat(cx, nz), np.tile(np.arange(nz), len(cx))
        iy = np.repeat(cy, nz)
        p = grid.positions((ix, iy, iz))
        mask[ix, iy, iz] = tm.contains(p)

    # -- distances ----------------------------------------------------------------------------
    def closest(self, p: np.ndarray):
        """Closest surface points to p (N, 3): (distance, point, face index)."""
        if self._tree is None:
            self._build_samples()
        k = min(6, len(self._sample_face))  # 6 candidates: max error ~0.01 h on the shared ring
        # independent queries, so the same answer on every core (2 free cores: 0.39 s -> 0.21 s
        # for the 58 k band nodes of translucent-cube at N = 128, M = 5)
        _, idx = self._tree.query(p, k=k, workers=-1)
        idx = idx.reshape(len(p), k)
        cand = self._sample_face[idx]  # (N, k)
        # several of a node's samples are often on one face (2.6 faces in 6 on the shared ring):
        # each (node, face) pair once, the first of equally near faces still winning
        fresh = np.ones(cand.shape, bool)
        for j in range(1, k):
            fresh[:, j] = (cand[:, :j] != cand[:, j : j + 1]).all(axis=1)
        rows, cols = np.nonzero(fresh)
        tri = self.V[self.F[cand[rows, cols]]]  # (K, 3, 3)
        pr = p[rows]
        qk = _closest_on_triangles(pr, tri[:, 0], tri[:, 1], tri[:, 2])
        d = np.full(cand.shape, np.inf)
        d[rows, cols] = _norm3(pr - qk)
        at = np.zeros(cand.shape, np.int64)
        at[rows, cols] = np.arange(len(rows))
        best = np.argmin(d, axis=1)
        r = np.arange(len(p))
        return d[r, best], qk[at[r, best]], cand[r, best]

    def _build_samples(self):
        """Points on every triangle about h/2 apart (KD-tree candidates for closest())."""
        s = self._h / 2
        A, B, C = (self.V[self.F[:, i]] for i in range(3))
        L = np.stack(
            [
                np.linalg.norm(B - A, axis=1),
                np.linalg.norm(C - B, axis=1),
                np.linalg.norm(A - C, axis=1),
            ],
            1,
        )
        rot = np.argmin(L, axis=1)  # put the shortest edge first so that slivers sample cheaply
        V3 = np.stack([A, B, C], 1)
        ids = (np.arange(3)[None, :] + rot[:, None]) % 3
        V3 = np.take_along_axis(V3, ids[..., None], 1)
        a, b, c = V3[:, 0], V3[:, 1], V3[:, 2]
        nu = np.maximum(1, np.ceil(np.linalg.norm(b - a, axis=1) / s)).astype(np.int64)
        nv = np.maximum(1, np.ceil(np.linalg.norm(c - a, axis=1) / s)).astype(np.int64)
        cnt = (nu + 1) * (nv + 1)
        tri = np.repeat(np.arange(len(a)), cnt)
        r = np.arange(tri.size) - np.repeat(np.cumsum(cnt) - cnt, cnt)
        u = (r // (nv[tri] + 1)) / nu[tri]
        v = (r % (nv[tri] + 1)) / nv[tri]
        tot = np.maximum(u + v, 1.0)  # beyond the third edge: project onto it
        u, v = u / tot, v / tot
        pts = a[tri] + u[:, None] * (b - a)[tri] + v[:, None] * (c - a)[tri]
        self._tree = cKDTree(pts)
        self._sample_face = tri

    def sdf_grid(self, grid: _Grid, M: int) -> np.ndarray:
        """Signed distance, with the sign of the SOLID mask: exact (closest triangle) in a band
        (the M-node shell outside, 2.5 nodes inside), EDT of the mask farther within the mesh's
        bounding box (+ margin), and the distance to that box beyond (a positive lower bound)."""
        n = np.array(grid.shape)
        h = grid.h
        mask = self.solid_mask(grid)
        lo, hi = self.V.min(0), self.V.max(0)
        # distance to the bounding box + h: outside a box its SDF is sqrt(Σ max(|x - c| - e, 0)²),
        # x, y, z summed in order as np.linalg.norm does; inside, that is 0
        c, e = (lo + hi) / 2, (hi - lo) / 2
        o2 = [
            np.square(np.maximum(np.abs(grid.axis_coords(a) - c[a]) - e[a], 0.0)) for a in range(3)
        ]
        out = np.add.outer(np.add.outer(o2[0], o2[1]), o2[2])
        np.sqrt(out, out=out)
        out += h
        # sub-box: the mask and the mesh's bounds, with a margin beyond the shell's reach (M·√3)
        pad = math.ceil(M * math.sqrt(3)) + 3
        vb = np.stack(
            [np.floor((lo - grid.origin) / h - 0.5), np.ceil((hi - grid.origin) / h - 0.5)]
        )
        if mask.any():
            mi = np.argwhere(mask)
            vb = np.stack([np.minimum(vb[0], mi.min(0)), np.maximum(vb[1], mi.max(0))])
        b0 = np.clip(vb[0] - pad, 0, n).astype(int)
        b1 = np.clip(vb[1] + pad + 1, 0, n).astype(int)
        m = mask[tuple(slice(x, y) for x, y in zip(b0, b1))]
        if m.size == 0 or not m.any():
            return np.where(mask, -1e-6 * h, out)  # nothing (or only boundary-clipped bits) here
        sub = tuple(slice(x, y) for x, y in zip(b0, b1))
        din = ndimage.distance_transform_edt(m)
        e = np.where(m, -(din - 0.5), ndimage.distance_transform_edt(~m) - 0.5) * h
        shell = ndimage.maximum_filter(m, size=2 * M + 1, mode="constant") & ~m
        bi = np.nonzero(shell | (m & (din <= 2.5)))
        gi = tuple(i + o for i, o in zip(bi, b0))
        d, q, f = self.closest(grid.positions(gi))
        e[bi] = np.where(m[bi], -np.maximum(d, 1e-6 * h), d)
        out[sub] = np.where(m, np.minimum(e, -1e-6 * h), np.maximum(e, 0.0))
        flat = np.ravel_multi_index(gi, grid.shape)
        order = np.argsort(flat)
        self._cache = (flat[order], q[order], f[order])
        return out  # beyond the sub-box: no SOLID node, and the box distance is > 0

    def grad_at(self, idx, grid):
        """Outward unit normals at the nodes ``idx``: the direction away from the closest surface
        point (the face normal when the node lies on a face)."""
        p = grid.positions(idx)
        flat = np.ravel_multi_index(idx, grid.shape)
        keys, cq, cf = self._cache
        pos = np.clip(np.searchsorted(keys, flat), 0, max(len(keys) - 1, 0))
        hit = (keys[pos] == flat) if len(keys) else np.zeros(len(flat), bool)
        q = np.empty_like(p)
        f = np.empty(len(p), np.int64)
        q[hit], f[hit] = cq[pos[hit]], cf[pos[hit]]
        if (~hit).any():
            _, q[~hit], f[~hit] = self.closest(p[~hit])
        v = p - q
        flat_face = np.linalg.norm(v, axis=-1) < 1e-9 * self._h
        return np.where(flat_face[:, None], self.face_normal[f], _unit(v))


def _signed_volume(V, F):
    a, b, c = V[F[:, 0]], V[F[:, 1]], V[F[:, 2]]
    return float(np.einsum("ij,ij->i", a, np.cross(b, c)).sum() / 6.0)


def thin_resolution(scene: Scene) -> int:
    """The smallest resolution at which no shape of ``scene`` is thinner than a voxel (where
    ``voxelize`` warns that a shape may vanish or leak light); 2 without thin shapes."""
    grid = _Grid.from_domain(scene.domain, 1)  # h = the longest side
    need = 2
    for i, s in enumerate(scene.shapes):
        shape = _make_shape(s, i, grid)
        t = shape.r if isinstance(shape, _SphereS) else shape.thickness()
        if t:
            need = max(need, math.ceil(grid.h / t - 1e-9))  # voxelize warns where t < h
    return need


def _make_shape(s, index, grid) -> _Shape:
    if isinstance(s, Sphere):
        return _SphereS(s, index)
    if isinstance(s, Torus):
        return _TorusS(s, index)
    if isinstance(s, (Box, OpenBox)):
        return _BoxesS(s, index)
    if isinstance(s, Quad):
        return _QuadS(s, index, grid)
    if isinstance(s, Mesh):
        return _MeshS(s, index, grid)
    raise SceneError(
        f"shape '{getattr(s, 'name', s)}' of kind {getattr(s, 'kind', type(s))!r} cannot be "
        "voxelized; the kinds are sphere, torus, box, open-box, quad and mesh"
    )


# ----------------------------------------------------------------------------------------------
# material, normals, density


def _surface_material(material, solid, owner, surface, grid: _Grid, M: int) -> None:
    """Set ``material`` at the SURFACE nodes to the owner shape of their (Euclidean) nearest SOLID
    node.

    That node lies within Chebyshev distance R = ⌊M√3⌋ (a SURFACE node has a SOLID node within
    Chebyshev distance M, so within Euclidean M√3).  Where the SOLID nodes within R are all of one
    shape, that shape is the answer however the nearest is chosen; so each shape but the one with
    the largest bounding box (the rest's default) is dilated by R inside its bounding box + 2R,
    and the dilation of the other shapes' SOLID nodes there tells whether a node sees two shapes.
    Only then (near contacts, coarse lattices; no shipped scene at N = 128) does the Euclidean
    feature transform of the whole lattice decide, ties broken its way (0.2-0.4 s at N = 128).
    """
    labels = np.where(solid, owner + 1, 0)
    boxes = ndimage.find_objects(labels)
    present = [o for o, b in enumerate(boxes) if b is not None]
    vol = [math.prod(sl.stop - sl.start for sl in boxes[o]) for o in present]
    default = present[int(np.argmax(vol))]
    np.copyto(material, default, where=surface)
    R = math.floor(M * math.sqrt(3))
    modes = grid.modes()
    for o in present:
        if o == default:
            continue
        reach, ctx = [], []  # the nodes within R of the shape, and those within 2R (per axis)
        for a, sl in enumerate(boxes[o]):
            if modes[a] == "wrap":  # periodic: the whole period, wrapped
                reach.append(slice(0, grid.shape[a]))
                ctx.append(slice(0, grid.shape[a]))
            else:
                r0, r1 = max(sl.start - R, 0), min(sl.stop + R, grid.shape[a])
                c0, c1 = max(sl.start - 2 * R, 0), min(sl.stop + 2 * R, grid.shape[a])
                reach.append(slice(r0, r1))
                ctx.append(slice(c0, c1))
        inner = tuple(slice(r.start - c.start, r.stop - c.start) for r, c in zip(reach, ctx))
        lab = labels[tuple(ctx)]
        mine = ndimage.maximum_filter(lab == o + 1, size=2 * R + 1, mode=modes)[inner]
        cand = mine & surface[tuple(reach)]
        if not cand.any():
            continue
        lab = lab.copy()
        lab[lab == o + 1] = 0
        others = ndimage.maximum_filter(lab > 0, size=2 * R + 1, mode=modes)[inner]
        if (cand & others).any():
            material[surface] = _nearest_solid_owner(solid, owner, surface, grid, M)
            return
        material[tuple(reach)][cand] = o


def _nearest_solid_owner(solid, owner, surface, grid: _Grid, M: int) -> np.ndarray:
    """Owner shape of the (Euclidean) nearest SOLID node, for every SURFACE node."""
    if grid.periodic:
        p = math.ceil(M * math.sqrt(3)) + 1
        pads = ((p, p), (p, p), (0, 0))
        s = np.pad(solid, pads, mode="wrap")
        _, ind = ndimage.distance_transform_edt(~s, return_indices=True)
        ind = ind[:, p:-p, p:-p, :]
        ix = (ind[0] - p) % grid.shape[0]
        iy = (ind[1] - p) % grid.shape[1]
        iz = ind[2]
    else:
        _, (ix, iy, iz) = ndimage.distance_transform_edt(~solid, return_indices=True)
    return owner[ix[surface], iy[surface], iz[surface]]


def _com_normals(free, idx, M, grid: _Grid):
    """Unit vectors from the nodes ``idx`` to the centre of mass of the FREE nodes in their
    (2M+1)³ neighbourhood (paper §5), by separable correlations.  Returns (N, 3) and a mask of the
    nodes where that vector is non-zero."""
    f = free.astype(np.float32)
    ramp = np.arange(-M, M + 1, dtype=np.float32)
    ones = np.ones(2 * M + 1, np.float32)
    modes = grid.modes(open_mode="nearest")
    comps = []
    for a in range(3):
        g = f
        for b in range(3):
            g = ndimage.correlate1d(g, ramp if a == b else ones, axis=b, mode=modes[b])
        comps.append(g[idx])
    v = np.stack(comps, axis=-1).astype(np.float64)
    nrm = np.linalg.norm(v, axis=-1)
    ok = nrm > 1e-6
    return np.where(ok[:, None], v / np.where(ok, nrm, 1.0)[:, None], 0.0), ok


def _analytic_normals(shapes, owner, idx, grid):
    """SDF gradient of the nearest shape (``owner``: argmin of the SDF) at the nodes ``idx``."""
    out = np.zeros((len(idx[0]), 3))
    for s in shapes:
        m = owner == s.index
        if m.all():
            out[:] = s.grad_at(idx, grid)
        elif m.any():
            out[m] = s.grad_at(tuple(i[m] for i in idx), grid)
    return out


def _density(scene: Scene, grid: _Grid) -> tuple[np.ndarray, np.ndarray]:
    """The fog per node, as if there were no solids: (the density multiplier at the node,
    trilinear (clamped) grid × region mask, float32; the fog its cell holds, the grid × the
    share of the cell inside the region, float64).

    The second is what the lattice's fog volume is built from: a region's face cuts the cells
    it crosses, and counting a node's whole cell in or out by where its centre falls would give
    the region the volume of a whole number of cells (the translucent cube's 0.6-wide fog at
    N = 32: 20 nodes, 0.625 wide, +13% fog volume)."""
    fog = scene.fog
    if fog is None:
        return np.zeros(grid.shape, np.float32), np.zeros(grid.shape)
    ins, share = _region_factors(fog, grid)
    mask = ins[0][:, None, None] & ins[1][None, :, None] & ins[2][None, None, :]
    cell = share[0][:, None, None] * share[1][None, :, None] * share[2][None, None, :]
    if fog.density is None:
        return mask.astype(np.float32), cell
    g = np.asarray(fog.density, np.float64)
    if g.ndim != 3:
        raise SceneError(f"fog density grid must be 3-D [ix, iy, iz], got shape {g.shape}")
    for a in range(3):  # separable: trilinear between cell centres, clamped to the edge cells
        g = _lerp_axis(g, _grid_coords(grid, a, g.shape[a]), a)
    out = np.empty(grid.shape, np.float32)
    return np.multiply(g, mask, out=out), g * cell  # in float64, rounded on the way out


def _region_factors(fog, grid: _Grid):
    """Per axis, which nodes lie inside the fog's region (bool) and the share of each node's
    cell inside it (float64, exactly 0 or 1 away from the region's faces)."""
    if fog.region is not None:
        (r0, r1) = (np.asarray(fog.region[0], float), np.asarray(fog.region[1], float))
    else:
        r0, r1 = grid.domain_min, grid.domain_min + grid.domain_size
    r0 = np.maximum(r0, grid.domain_min)  # the fog never leaves the domain (vacuum margin)
    r1 = np.minimum(r1, grid.domain_min + grid.domain_size)
    ins, share = [], []
    for a in range(3):
        x = grid.axis_coords(a)
        ins.append((x >= r0[a]) & (x <= r1[a]))
        lo, hi = np.maximum(x - grid.h / 2, r0[a]), np.minimum(x + grid.h / 2, r1[a])
        # a face on a cell boundary must give exactly 0 and 1, not 1e-15 of fog in the vacuum
        # margin (a node with any fog is a fog node to the solver)
        share.append(_exact_ends(np.clip((hi - lo) / grid.h, 0.0, 1.0)))
    return ins, share


def _grid_coords(grid: _Grid, a: int, n: int) -> np.ndarray:
    """The nodes' coordinates along axis ``a`` in the cells of a density grid with ``n`` cells
    over the domain (cell centres at integers)."""
    return (grid.axis_coords(a) - grid.domain_min[a]) / grid.domain_size[a] * n - 0.5


def _lerp_matrix(n_grid: int, u) -> np.ndarray:
    """(len(u), n_grid): ``_lerp_axis`` as a matrix (trilinear between cell centres, clamped)."""
    return _lerp_axis(np.eye(n_grid)[:, :, None], u, 0)[:, :, 0]


@dataclass(frozen=True, eq=False)
class DensityMap:
    """The lattice's fog fields as linear maps of a density grid of ``grid_shape`` (cell-centred
    over the domain, indexed [ix, iy, iz] as scene files are): what makes ``fog.density`` an
    unknown (``Params.density``) while the geometry stays on the host.

    ``fog_density`` (the fog's own density at the nodes) is the grid interpolated per axis
    (``at_node``: trilinear, clamped, × the region's mask); ``density`` (the fog each node's
    cell holds, the solver's) is the grid × the cell's share in the region (``in_cell``), × the
    share of the cell outside the solids (``keep``), plus the fog of SOLID cells moved onto a
    neighbour (``src`` → ``dst``, flat indices, × ``moved``): ``_fog_volumes`` as a linear map.
    Which cells beside a surface hold fog is fixed by the grid the map was built for (a grid
    that is 0 where that one was not, or the other way round, moves its SOLID cells' fog as
    that one would); a fit that keeps the grid positive where it was (log or softplus
    parameters) stays exact.
    """

    grid_shape: tuple[int, int, int]
    at_node: tuple[np.ndarray, np.ndarray, np.ndarray]  # (n_a, g_a) float64
    in_cell: tuple[np.ndarray, np.ndarray, np.ndarray]  # (n_a, g_a) float64
    keep: np.ndarray  # (nx, ny, nz) float64, 0 at SOLID nodes
    src: np.ndarray  # (K,) int64
    dst: np.ndarray  # (K,) int64
    moved: np.ndarray  # (K,) float64

    def apply(self, grid, xp=np):
        """(fog_density, density) on the lattice for ``grid`` (NumPy, or ``jax.numpy``: then
        traced and differentiable), in ``grid``'s dtype."""
        return apply_density_map(self, grid, xp)


def apply_density_map(m, grid, xp=np):
    """:meth:`DensityMap.apply` for ``m``, a ``DensityMap`` or anything with its fields (the
    sweep model keeps them as device arrays)."""
    grid = xp.asarray(grid)
    if tuple(grid.shape) != tuple(m.grid_shape):
        raise SceneError(f"fog.density: a grid of shape {tuple(grid.shape)} was given, but "
                         f"the model was built for the scene's grid of shape "
                         f"{tuple(m.grid_shape)}; build the model from a scene whose fog has a "
                         f"grid of that shape (scene.replace(fog=...))")
    dt = grid.dtype

    def sep(mats):
        out = grid
        for a, mat in enumerate(mats):  # contract one axis at a time (small GEMMs)
            out = xp.moveaxis(xp.tensordot(xp.asarray(mat, dt), out, axes=([1], [a])), 0, a)
        return out

    fog = sep(m.at_node)
    cell = sep(m.in_cell)
    dens = cell * xp.asarray(m.keep, dt)
    if len(m.src):
        add = cell.reshape(-1)[m.src] * xp.asarray(m.moved, dt)
        flat = dens.reshape(-1)
        if xp is np:
            np.add.at(flat, m.dst, add)
            dens = flat.reshape(dens.shape)
        else:
            dens = flat.at[m.dst].add(add).reshape(dens.shape)
    return fog, dens


def _density_map(scene: Scene, grid: _Grid, volume_parts) -> DensityMap:
    ins, share = _region_factors(scene.fog, grid)
    g = np.asarray(scene.fog.density)
    at_node, in_cell = [], []
    for a in range(3):
        m = _lerp_matrix(g.shape[a], _grid_coords(grid, a, g.shape[a]))
        at_node.append(m * ins[a][:, None])
        in_cell.append(m * share[a][:, None])
    keep, src, dst, moved = volume_parts
    return DensityMap(grid_shape=tuple(int(n) for n in g.shape), at_node=tuple(at_node),
                      in_cell=tuple(in_cell), keep=keep, src=src, dst=dst, moved=moved)


# the half-diagonal of a cell in cells: a node farther than this from every surface has its
# whole cell on one side
_HALF_DIAGONAL = 0.5 * math.sqrt(3.0)
_COLUMNS = 8  # midpoint columns per cell side for a cell's share on one side of a plane


def _fog_volumes(cell_fog, sdf, solid, owner, shapes, grid, parts: list | None = None
                 ) -> np.ndarray:
    """The lattice's density (float32): each node's ``cell_fog`` × the share of its cell outside
    the solids, and the fog of the cells of SOLID nodes moved onto a non-SOLID neighbour, so
    that Σ density·h³ is the scene's fog volume at every resolution.

    A node stands for its cell in the sweep (it scatters and absorbs σ·density·h³ of the light
    passing through); counting a cell as all fog or all solid by where its centre falls gives
    the fog the volume of a whole number of cells, and which number depends on where the nodes
    fall against the surfaces (fog-balls' 0.05-thick walls: +4.8 / +8.3 / −6.9 / −3.1% fog
    volume at N = 24 / 28 / 32 / 36), a model error a fit absorbs into ζ.  The share of a
    cell near a surface is that of the tangent plane (the SDF and its central-difference
    gradient at the node): exact for flat faces, O(h/R) on a ball of radius R.  A quad is a
    sheet without thickness: its (lattice-thickened) cells count as fog.  The fog of a SOLID
    node's cell goes to the neighbour along the gradient (outwards), else to its neighbour of
    largest SDF, among the non-SOLID nodes whose cells hold fog (never into the vacuum margin
    beyond a wall: what finds no such neighbour, ~0.1% of fog-balls' fog at its outer edges
    where the tangent plane overestimates a share, is left out).  SOLID nodes keep density 0.
    """
    out = np.zeros(grid.shape, np.float64)
    none = np.zeros(0, np.int64)
    if not cell_fog.any():
        if parts is not None:
            parts.extend((np.where(solid, 0.0, 1.0), none, none, np.zeros(0)))
        return out.astype(np.float32)
    h = grid.h
    frac = np.where(solid, 0.0, 1.0)
    band = np.nonzero((np.abs(sdf) < _HALF_DIAGONAL * h) & (cell_fog > 0))
    if band[0].size:
        f, normal = _plane_shares(sdf, band, grid)
        quads = [s.index for s in shapes if isinstance(s, _QuadS)]
        if quads:
            f[np.isin(owner[band], quads)] = 1.0
        frac[band] = f
    np.multiply(cell_fog, frac, out=out)
    np.copyto(out, 0.0, where=solid)
    moves = (none, none, np.zeros(0))
    if band[0].size:
        give = solid[band] & (f > 0)
        if give.any():
            src = tuple(i[give] for i in band)
            dst = _outward_neighbour(src, normal[give], sdf, solid | (cell_fog <= 0), grid)
            ok = dst[0] >= 0
            np.add.at(out, tuple(i[ok] for i in dst), (cell_fog[src] * f[give])[ok])
            moves = (np.ravel_multi_index(tuple(i[ok] for i in src), grid.shape),
                     np.ravel_multi_index(tuple(i[ok] for i in dst), grid.shape), f[give][ok])
    if parts is not None:  # the linear map, for ``DensityMap``
        parts.extend((np.where(solid, 0.0, frac),) + moves)
    return out.astype(np.float32)


def _exact_ends(share):
    """A cell's share in [0, 1] with rounding's 1e-16 off either end snapped to 0 or 1."""
    return np.where(share < 1e-9, 0.0, np.where(share > 1 - 1e-9, 1.0, share))


def _wrap_or_clip(i, a, grid):
    n = grid.shape[a]
    return i % n if (grid.periodic and a < 2) else np.clip(i, 0, n - 1)


def _plane_shares(sdf, idx, grid):
    """The share of each node's cell (nodes ``idx``) on the positive side of the SDF's tangent
    plane, and the plane's unit normal (N, 3): the gradient by central differences (one-sided at
    an open edge); where it vanishes (the middle of a thin part) the share is that of the plane
    normal to an axis."""
    d = sdf[idx] / grid.h
    gvec = np.empty((d.size, 3))
    for a in range(3):
        lo, hi = list(idx), list(idx)
        lo[a] = _wrap_or_clip(idx[a] - 1, a, grid)
        hi[a] = _wrap_or_clip(idx[a] + 1, a, grid)
        span = (hi[a] - lo[a]) % grid.shape[a] if (grid.periodic and a < 2) else hi[a] - lo[a]
        gvec[:, a] = (sdf[tuple(hi)] - sdf[tuple(lo)]) / np.maximum(span, 1)
    norm = _norm3(gvec)
    flat = norm < 0.25 * grid.h
    n = np.where(flat[:, None], 0.0, gvec / np.where(flat, 1.0, norm)[:, None])
    m = np.sort(np.abs(n), axis=1)  # the plane's column axis is its normal's largest component
    big = np.where(flat, 1.0, m[:, 2])
    t = (np.arange(_COLUMNS) + 0.5) / _COLUMNS - 0.5
    u, v = np.meshgrid(t, t, indexing="ij")
    off = m[:, 0, None] * u.ravel() + m[:, 1, None] * v.ravel()  # (N, columns²)
    share = np.clip(0.5 + (d[:, None] + off) / big[:, None], 0.0, 1.0).mean(axis=1)
    # a face on a cell boundary gives exactly 0 or 1 (no 1e-16 of fog moved out of a solid)
    share = _exact_ends(share)
    return share, n


def _outward_neighbour(src, n, sdf, closed, grid):
    """A 26-neighbour of each SOLID node ``src`` that is not ``closed``: the one along its
    normal ``n``, else the one of largest SDF; index −1 where there is none."""
    steps = np.array([(i, j, k) for i in (-1, 0, 1) for j in (-1, 0, 1) for k in (-1, 0, 1)
                      if (i, j, k) != (0, 0, 0)])
    big = np.abs(n).max(axis=1, keepdims=True)
    along = np.rint(n / np.where(big > 0, big, 1.0)).astype(np.int64)

    def at(step):
        out, inside = [], np.ones(src[0].size, bool)
        for a in range(3):
            i = src[a] + step[:, a]
            if not (grid.periodic and a < 2):
                inside &= (i >= 0) & (i < grid.shape[a])
            out.append(_wrap_or_clip(i, a, grid))
        return tuple(out), inside

    dst, ok = at(along)
    ok &= ~closed[dst] & (big[:, 0] > 0)
    best = np.full(src[0].size, -np.inf)
    pick = np.zeros((src[0].size, 3), np.int64)
    for s in steps:
        nb, inside = at(np.broadcast_to(s, (src[0].size, 3)))
        val = np.where(inside & ~closed[nb], sdf[nb], -np.inf)
        better = val > best
        best = np.where(better, val, best)
        pick[better] = s
    alt, _ = at(pick)
    res = [np.where(ok, dst[a], np.where(np.isfinite(best), alt[a], -1)) for a in range(3)]
    return tuple(res)


def _lerp_axis(g, u, axis):
    n = g.shape[axis]
    if n == 1:
        return np.repeat(g, len(u), axis=axis)
    u = np.clip(u, 0.0, n - 1)
    i0 = np.minimum(np.floor(u).astype(np.int64), n - 2)
    t = u - i0
    shape = [1, 1, 1]
    shape[axis] = len(u)
    t = t.reshape(shape)
    out = np.take(g, i0, axis=axis)
    out *= 1 - t
    hi = np.take(g, i0 + 1, axis=axis)
    hi *= t
    out += hi
    return out
