"""Exact first hits of rays against the scene's shapes, and the sun seen from a hit (host, NumPy).

Camera rays, and the shadow rays from their hits towards the sun, depend only on the cameras and
the geometry, which no fit changes: they are cast here once per camera, against the exact
shapes, and the sweep's camera then marches the fog only up to the exact hit.

* sphere: the quadratic, exactly;
* torus: the real roots of its quartic along the ray (companion-matrix eigenvalues from the
  bounding sphere's entry point, polished by Newton);
* box, the walls of an open box, quad, mesh: their triangles (12 per box; a quad's two; a
  mesh's own), which are these shapes exactly, through ``_rays.cast_rays``.

The normal at a hit is the shape's exact outward normal (a quad's: the side the ray comes from).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import ndimage

from ..scene._description import Scene, Sphere, Torus
from ._lattice import _TorusS
from ._rays import cast_rays, scene_triangles

__all__ = ["Hits", "first_hits", "sun_depth"]

@dataclass(frozen=True, eq=False)
class Hits:
    """First hits of R rays: ``t`` (R,) distance along the unit direction (inf: none),
    ``normal`` (R, 3) unit, facing the ray's origin (0 where none), ``shape`` (R,) index into
    ``scene.shapes`` (-1: none)."""

    t: np.ndarray
    normal: np.ndarray
    shape: np.ndarray

    @property
    def hit(self) -> np.ndarray:
        return self.shape >= 0


def _sphere_hits(s: Sphere, o, d, t_min):
    c, r = np.asarray(s.center, float), float(s.radius)
    oc = o - c
    b = np.einsum("ij,ij->i", oc, d)
    q = np.einsum("ij,ij->i", oc, oc) - r * r
    disc = b * b - q
    ok = disc >= 0
    sq = np.sqrt(np.where(ok, disc, 0.0))
    t_near, t_far = -b - sq, -b + sq
    t = np.where(t_near > t_min, t_near, np.where(t_far > t_min, t_far, np.inf))
    t = np.where(ok, t, np.inf)
    p = o + np.where(np.isfinite(t), t, 0.0)[:, None] * d
    return t, (p - c) / r


def _torus_frame(s: Torus):
    a = np.asarray(s.axis, float)
    return np.asarray(s.center, float), a / np.linalg.norm(a), float(s.major_radius), \
        float(s.minor_radius)


def _torus_hits(s: Torus, o, d, t_min):
    """The quartic of the ray and the torus, solved by the eigenvalues of its companion matrix
    (vectorized LAPACK) from the bounding sphere's entry point, then polished by Newton."""
    c, a, R, r = _torus_frame(s)
    # local frame: the axis along z
    e1 = np.cross(a, [1.0, 0.0, 0.0] if abs(a[0]) < 0.9 else [0.0, 1.0, 0.0])
    e1 /= np.linalg.norm(e1)
    F = np.stack([e1, np.cross(a, e1), a])  # rows: local x, y, z
    ol, dl = (o - c) @ F.T, d @ F.T
    b = np.einsum("ij,ij->i", ol, dl)
    q = np.einsum("ij,ij->i", ol, ol) - (R + r) ** 2
    disc = b * b - q
    t_out = np.full(len(o), np.inf)
    live = np.flatnonzero(disc >= 0)
    t0 = np.maximum(-b[live] - np.sqrt(disc[live]), 0.0)  # start on the bounding sphere
    oo, dd = ol[live] + t0[:, None] * dl[live], dl[live]
    H = 2.0 * np.einsum("ij,ij->i", oo, dd)
    I_ = np.einsum("ij,ij->i", oo, oo) + R * R - r * r
    J = dd[:, 0] ** 2 + dd[:, 1] ** 2
    K = 2.0 * (oo[:, 0] * dd[:, 0] + oo[:, 1] * dd[:, 1])
    L = oo[:, 0] ** 2 + oo[:, 1] ** 2
    coef = np.stack([2.0 * H, H * H + 2.0 * I_ - 4.0 * R * R * J, 2.0 * H * I_ - 4.0 * R * R * K,
                     I_ * I_ - 4.0 * R * R * L], -1)  # monic: t⁴ + c3 t³ + c2 t² + c1 t + c0
    comp = np.zeros((len(live), 4, 4))
    comp[:, 0, :] = -coef
    comp[:, 1, 0] = comp[:, 2, 1] = comp[:, 3, 2] = 1.0
    roots = np.linalg.eigvals(comp) if len(live) else np.zeros((0, 4), complex)
    tr = roots.real
    for _ in range(2):  # Newton on the quartic
        p_ = (((tr + coef[:, :1]) * tr + coef[:, 1:2]) * tr + coef[:, 2:3]) * tr + coef[:, 3:]
        dp = ((4.0 * tr + 3.0 * coef[:, :1]) * tr + 2.0 * coef[:, 1:2]) * tr + coef[:, 2:3]
        tr = tr - np.where(np.abs(dp) > 0, p_ / np.where(dp == 0, 1.0, dp), 0.0)
    ok = (np.abs(roots.imag) <= 1e-6 * (R + r)) & (tr + t0[:, None] > t_min)
    t = np.where(ok, tr, np.inf).min(axis=-1) + t0
    t_out[live] = t
    hit = np.isfinite(t_out)
    p = o + np.where(hit, t_out, 0.0)[:, None] * d
    return t_out, _TorusS(s, -1).grad(p)  # the voxelizer's: away from the core circle


def first_hits(scene: Scene, origins, directions, *, t_min: float = 0.0) -> Hits:
    """The first hit (t > t_min) of each ray o + t·d against the exact shapes of ``scene``.

    origins, directions: (R, 3), directions unit.  Shapes are not repeated across the sides of
    a periodic-xy domain.
    """
    o = np.asarray(origins, np.float64).reshape(-1, 3)
    d = np.asarray(directions, np.float64).reshape(-1, 3)
    R = len(o)
    best = np.full(R, np.inf)
    normal = np.zeros((R, 3))
    owner = np.full(R, -1, np.int64)

    def take(t, n, index):
        closer = t < best
        best[closer] = t[closer]
        normal[closer] = n[closer]
        owner[closer] = index

    for i, s in enumerate(scene.shapes):
        if isinstance(s, Sphere):
            take(*_sphere_hits(s, o, d, t_min), i)
        elif isinstance(s, Torus):
            take(*_torus_hits(s, o, d, t_min), i)
    tris = scene_triangles(scene, skip=(Sphere, Torus))  # spheres and tori: exact above
    if len(tris):
        t, face, _, _ = cast_rays(tris, o, d, t_min=t_min)
        hit = face >= 0
        n = np.where(hit[:, None], tris.face_normals[np.where(hit, face, 0)], 0.0)
        closer = t < best
        best[closer] = t[closer]
        normal[closer] = n[closer]
        owner[closer] = tris.shape[face[closer]]
    # face the ray's origin (two-sided quads; a closed shape's outside faces already do)
    flip = np.einsum("ij,ij->i", normal, d) > 0
    normal[flip] *= -1.0
    normal[owner < 0] = 0.0
    return Hits(best, normal, owner)


def sun_depth(scene: Scene, points, normals, sun_dir, density, origin, h: float,
              *, step: float = 0.5):
    """What the sun needs at surface points: ``cos_vis`` (R,) = max(0, n·s) where no shape
    blocks the shadow ray towards the sun (0 where one does), and ``depth`` (R,) the
    density-weighted path length ∫ density ds from each point towards the sun to the lattice
    box's edge (the sun's transmittance is exp(-σ_t·depth) for a uniform extinction σ_t per
    unit density).  ``density`` is the lattice's node field (node (i, j, k) at
    origin + (idx + 0.5)·h, trilinear between nodes, 0 outside), integrated by the midpoint rule
    in steps of ``step``·h.  Points: (R, 3); normals: (R, 3) unit.
    """
    p = np.asarray(points, np.float64).reshape(-1, 3)
    n = np.asarray(normals, np.float64).reshape(-1, 3)
    s = np.asarray(sun_dir, np.float64)
    s = s / np.linalg.norm(s)
    R = len(p)
    cos = np.maximum(n @ s, 0.0)
    cos_vis = np.zeros(R)
    depth = np.zeros(R)
    lit = np.flatnonzero(cos > 0)
    if not len(lit):
        return cos_vis, depth
    size = h * max(density.shape)
    start = p[lit] + 1e-7 * size * n[lit]
    blocked = first_hits(scene, start, np.broadcast_to(s, start.shape),
                         t_min=1e-7 * size).hit
    lit = lit[~blocked]
    cos_vis[lit] = cos[lit]
    if not len(lit) or not np.any(density):
        return cos_vis, depth
    lo = np.asarray(origin, float)
    hi = lo + h * np.asarray(density.shape, float)
    q = p[lit]
    with np.errstate(divide="ignore"):
        ta = np.where(s != 0, (lo - q) / s, np.inf)
        tb = np.where(s != 0, (hi - q) / s, np.inf)
    t_end = np.maximum(np.min(np.maximum(ta, tb), axis=-1), 0.0)
    ds = step * h
    n_steps = int(np.ceil(t_end.max() / ds)) if len(t_end) else 0
    acc = np.zeros(len(q))
    dens = np.asarray(density, np.float64)
    chunk = max(1, (1 << 22) // max(n_steps, 1))
    for c0 in range(0, len(q), chunk):
        qc, te = q[c0:c0 + chunk], t_end[c0:c0 + chunk]
        k = (np.arange(n_steps) + 0.5) * ds  # midpoints
        pts = qc[:, None, :] + k[None, :, None] * s  # (r, K, 3)
        u = (pts - lo) / h - 0.5  # node coordinates
        vals = ndimage.map_coordinates(dens, u.reshape(-1, 3).T, order=1, mode="constant",
                                       cval=0.0).reshape(len(qc), n_steps)
        w = np.clip((te[:, None] - (k[None, :] - 0.5 * ds)) / ds, 0.0, 1.0)  # last partial step
        acc[c0:c0 + chunk] = (vals * w).sum(-1) * ds
    depth[lit] = acc
    return cos_vis, depth
