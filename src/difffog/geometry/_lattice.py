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

_CHUNK = 1 << 20  # nodes per vectorized block when evaluating shapes over the grid


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
    density: np.ndarray  # float32: fog density multiplier (0 at SOLID nodes and outside the fog)
    sdf: np.ndarray  # float32: signed distance to the solid geometry, < 0 exactly at SOLID nodes
    # float32: the fog's density as if there were no solids (grid × region), for what samples
    # the fog between nodes right up to an exact surface (the cameras' march, the sun's depth
    # at a hit): trilinear between the last fog node and a SOLID node it does not fall to 0
    # half-way; None: ``density``
    fog_density: np.ndarray | None = None

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

    def max_segment_optical_depth(self, scattering: float, absorption: float) -> float:
        """Largest optical depth σ_t·h·M of one lattice-ray segment (≲ 0.3: see docs/design.md)."""
        return float((scattering + absorption) * self.density.max(initial=0.0) * self.h * self.M)

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
    M + 1.  The fog stays inside the domain.
    """
    _check_int("resolution", resolution, 2, "use e.g. resolution=64")
    _check_int("M", M, 1, "use e.g. M=3 (the paper uses M=5 at resolution 128)")
    if normals not in ("auto", "analytic", "com"):
        raise SceneError(
            f"normals={normals!r} is not a normal rule; use 'auto', 'analytic' or 'com'"
        )
    _check_int("margin", margin, 0, "use 0 (none) or M + 1")
    resolution, M = int(resolution), int(M)

    grid = _Grid.from_domain(scene.domain, resolution, int(margin))
    shapes = [_make_shape(s, i, grid) for i, s in enumerate(scene.shapes)]
    for s in shapes:
        s.warn_if_thin(grid, resolution)

    # --- SOLID, sdf and the owning shape (argmin of the per-shape SDF) -------------------------
    n = grid.shape
    sdf = np.full(n, _far(grid), np.float64)
    owner = np.full(n, -1, np.int16)
    for s in shapes:
        d = s.sdf_grid(grid, M)
        closer = d < sdf
        sdf[closer] = d[closer]
        owner[closer] = s.index
    solid = sdf < 0
    # float32 must keep the sign: SOLID strictly negative, the rest >= 0
    tiny = 1e-6 * grid.h
    sdf = np.where(solid, np.minimum(sdf, -tiny), np.maximum(sdf, 0.0)).astype(np.float32)

    # --- SURFACE shell: Chebyshev distance <= M from a SOLID node --------------------------------
    near = ndimage.maximum_filter(solid, size=2 * M + 1, mode=grid.modes(), cval=0)
    surface = near & ~solid
    node_type = np.full(n, FREE, np.int8)
    node_type[surface] = SURFACE
    node_type[solid] = SOLID

    # --- material ----------------------------------------------------------------------------
    material = np.full(n, -1, np.int16)
    material[solid] = owner[solid]
    if surface.any():
        if len(shapes) == 1:
            material[surface] = 0
        else:
            material[surface] = _nearest_solid_owner(solid, owner, surface, grid, M)

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

    density = _density(scene, grid, solid)
    fog_density = _density(scene, grid, np.zeros_like(solid)) if solid.any() else density
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
        sdf=sdf,
        fog_density=fog_density,
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
        return cls(shape, h, lo - pad * h, domain.boundary, lo, size)

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
        i = np.arange(self.shape[a]) if idx is None else np.asarray(idx)
        return self.origin[a] + (i + 0.5) * self.h

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


def _unit(v, fallback=None):
    n = np.linalg.norm(v, axis=-1, keepdims=True)
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
        return np.linalg.norm(p - self.c, axis=-1) - self.r

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
        v = p - self.c
        z = v @ self.a
        rho = np.sqrt(np.maximum(np.einsum("...i,...i", v, v) - z * z, 0.0))
        return np.hypot(rho - self.R, z) - self.r

    def grad(self, p):
        return _unit(p - self.core_point(p), fallback=self.a)

    def thickness(self):
        return 2 * self.r


def _box_sdf(p, lo, hi):
    c, e = (lo + hi) / 2, (hi - lo) / 2
    q = np.abs(p - c) - e
    outside = np.linalg.norm(np.maximum(q, 0.0), axis=-1)
    inside = np.minimum(q.max(axis=-1), 0.0)
    return outside + inside


def _box_grad(p, lo, hi):
    c, e = (lo + hi) / 2, (hi - lo) / 2
    d = p - c
    sgn = np.where(d >= 0, 1.0, -1.0)
    q = np.abs(d) - e
    out = sgn * np.maximum(q, 0.0)
    inside_n = np.zeros_like(p)
    ax = np.argmax(q, axis=-1)
    np.put_along_axis(inside_n, ax[..., None], np.take_along_axis(sgn, ax[..., None], -1), -1)
    is_out = (q > 0).any(axis=-1, keepdims=True)
    return np.where(is_out, _unit(out), inside_n)


class _BoxesS(_Shape):
    """A union of axis-aligned boxes: a box, or the walls of an open box."""

    def __init__(self, s, index):
        self.index, self.name, self.kind = index, s.name, s.kind
        if isinstance(s, OpenBox):
            boxes = s.walls()
            self._thick = float(s.thickness)
        else:
            boxes = [(s.min, s.max)]
            self._thick = float(np.min(np.subtract(s.max, s.min)))
        self.boxes = [(np.asarray(a, float), np.asarray(b, float)) for a, b in boxes]

    def sdf(self, p):
        if not self.boxes:
            return np.full(p.shape[:-1], np.inf)
        return np.min([_box_sdf(p, lo, hi) for lo, hi in self.boxes], axis=0)

    def grad(self, p):
        d = np.stack([_box_sdf(p, lo, hi) for lo, hi in self.boxes])
        best = np.argmin(d, axis=0)
        out = np.zeros_like(p)
        for i, (lo, hi) in enumerate(self.boxes):
            m = best == i
            if m.any():
                out[m] = _box_grad(p[m], lo, hi)
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
    distance to the polygon is below w = ‖n‖₁·h/2 (see the module docstring)."""

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
        Vi = (self.V - grid.origin) / grid.h - 0.5  # node centres at integer coordinates
        mask = np.zeros(n, bool)
        # 1) non-zero winding along z columns (x, y) -> fill
        Bz = np.array([[0, 0, 1], [1, 0, 0], [0, 1, 0]])
        (rj, rk, t0, t1, _, _), (bj, bk) = _inside_runs(
            *_line_crossings(Vi @ np.linalg.inv(Bz), self.F)
        )
        ok = (rj >= 0) & (rj < n[0]) & (rk >= 0) & (rk < n[1])
        rj, rk, t0, t1 = rj[ok], rk[ok], t0[ok], t1[ok]
        a = np.clip(np.ceil(t0), 0, n[2]).astype(np.int64)
        b = np.clip(np.floor(t1) + 1, 0, n[2]).astype(np.int64)
        diff = np.zeros((n[0], n[1], n[2] + 1), np.int32)
        np.add.at(diff, (rj, rk, a), 1)
        np.add.at(diff, (rj, rk, b), -1)
        mask |= np.cumsum(diff, axis=2)[..., :-1] > 0
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
            node = (np.stack([i, rj[thin], rk[thin]], 1) @ B).astype(np.int64)
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
        _, idx = self._tree.query(p, k=k)
        idx = idx.reshape(len(p), k)
        cand = self._sample_face[idx]  # (N, k)
        tri = self.V[self.F[cand]]  # (N, k, 3, 3)
        q = _closest_on_triangles(p[:, None, :], tri[..., 0, :], tri[..., 1, :], tri[..., 2, :])
        d = np.linalg.norm(p[:, None, :] - q, axis=-1)
        best = np.argmin(d, axis=1)
        r = np.arange(len(p))
        return d[r, best], q[r, best], cand[r, best]

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
        out = np.empty(grid.shape, np.float64)
        for sl, p in grid.slabs():
            out[sl] = np.maximum(_box_sdf(p, lo, hi), 0.0) + h
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
        out[sub] = e
        flat = np.ravel_multi_index(gi, grid.shape)
        order = np.argsort(flat)
        self._cache = (flat[order], q[order], f[order])
        return np.where(mask, np.minimum(out, -1e-6 * h), np.maximum(out, 0.0))

    def grad_nodes(self, flat: np.ndarray, p: np.ndarray) -> np.ndarray:
        """Outward unit normals at nodes (flat indices, positions (N, 3)): the direction away from
        the closest surface point (the face normal when the node lies on a face)."""
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
    p = grid.positions(idx)
    out = np.zeros_like(p)
    for s in shapes:
        m = owner == s.index
        if not m.any():
            continue
        if isinstance(s, _MeshS):
            out[m] = s.grad_nodes(np.ravel_multi_index(tuple(i[m] for i in idx), grid.shape), p[m])
        else:
            out[m] = s.grad_periodic(p[m], grid)
    return out


def _density(scene: Scene, grid: _Grid, solid: np.ndarray) -> np.ndarray:
    """Fog density multiplier per node: trilinear (clamped) grid × region mask × non-SOLID."""
    fog = scene.fog
    if fog is None:
        return np.zeros(grid.shape, np.float32)
    if fog.density is not None:
        g = np.asarray(fog.density, np.float64)
        if g.ndim != 3:
            raise SceneError(f"fog density grid must be 3-D [ix, iy, iz], got shape {g.shape}")
        for a in range(3):  # separable: trilinear between cell centres, clamped to the edge cells
            x = grid.axis_coords(a)
            u = (x - grid.domain_min[a]) / grid.domain_size[a] * g.shape[a] - 0.5
            g = _lerp_axis(g, u, a)
    else:
        g = np.ones(grid.shape)
    if fog.region is not None:
        (r0, r1) = (np.asarray(fog.region[0], float), np.asarray(fog.region[1], float))
    else:
        r0, r1 = grid.domain_min, grid.domain_min + grid.domain_size
    r0 = np.maximum(r0, grid.domain_min)  # the fog never leaves the domain (vacuum margin)
    r1 = np.minimum(r1, grid.domain_min + grid.domain_size)
    ins = [(grid.axis_coords(a) >= r0[a]) & (grid.axis_coords(a) <= r1[a]) for a in range(3)]
    g = g * (ins[0][:, None, None] & ins[1][None, :, None] & ins[2][None, None, :])
    g = np.where(solid, 0.0, g)
    return g.astype(np.float32)


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
    return np.take(g, i0, axis=axis) * (1 - t) + np.take(g, i0 + 1, axis=axis) * t
