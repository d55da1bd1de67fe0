"""Polygons for the splat solver: every shape as triangles, and their z-buffers by ray casting.

Zhang & Crawfis (§4.1, stage 1) rasterize the polygons once with respect to the eye (colour,
normal, depth per pixel) and once with respect to the light (depth per shadow-buffer texel).
Both are z-buffers sampled at fixed points: the eye's at the camera's (sub-)pixel rays, the
light's at the shadow buffer's texel rays.  We fill them by casting exactly those rays against
the triangles (Möller–Trumbore, vectorized in NumPy), which gives the same buffer as a scanline
rasterizer at the same sample points and needs no near-plane clipping for perspective cameras
inside the scene.  Host-side, once per scene and camera; nothing here is traced.

Shapes become triangles with trimesh: ``quad`` (two triangles, two-sided), ``mesh`` (its
world-space faces), ``box`` and the walls of an ``open-box`` (``trimesh.creation.box``),
``sphere`` (icosphere) and ``torus`` (``trimesh.creation.torus``, turned to its axis); spheres and
tori carry vertex normals that are interpolated at a hit, the others their face normals.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..scene._description import Box, Mesh, OpenBox, Quad, Scene, Sphere, Torus

__all__ = ["Triangles", "scene_triangles", "cast_rays", "hit_normals"]


@dataclass(frozen=True, eq=False)
class Triangles:
    """A triangle soup: corners (F, 3, 3), owning shape index (F,), optional vertex normals
    (F, 3, 3) (zero rows: use the face normal), and the part (one mesh: a sphere, a wall of an
    open box) of each face (F,) (None: the shape), which the ray-casting hierarchy keeps
    together."""

    corners: np.ndarray
    shape: np.ndarray
    vertex_normals: np.ndarray
    part: np.ndarray | None = None

    def __len__(self) -> int:
        return len(self.shape)

    @property
    def face_normals(self) -> np.ndarray:
        c = self.corners
        n = np.cross(c[:, 1] - c[:, 0], c[:, 2] - c[:, 0])
        return n / np.maximum(np.linalg.norm(n, axis=-1, keepdims=True), 1e-300)


def _rotation_z_to(axis) -> np.ndarray:
    import trimesh

    a = np.asarray(axis, float)
    a = a / np.linalg.norm(a)
    return trimesh.geometry.align_vectors([0.0, 0.0, 1.0], a)


def _shape_meshes(s, sphere_subdivisions: int, torus_sections: tuple[int, int]):
    """[(trimesh.Trimesh, smooth)] of one shape."""
    import trimesh  # 0.15 s to import: only the splat's shapes need it, when built

    if isinstance(s, Sphere):
        m = trimesh.creation.icosphere(subdivisions=sphere_subdivisions, radius=s.radius)
        m.apply_translation(s.center)
        return [(m, True)]
    if isinstance(s, Torus):
        m = trimesh.creation.torus(major_radius=s.major_radius, minor_radius=s.minor_radius,
                                   major_sections=torus_sections[0],
                                   minor_sections=torus_sections[1])
        m.apply_transform(_rotation_z_to(s.axis))
        m.apply_translation(s.center)
        return [(m, True)]
    if isinstance(s, Box):
        lo, hi = np.asarray(s.min, float), np.asarray(s.max, float)
        return [(trimesh.creation.box(extents=hi - lo,
                                      transform=trimesh.transformations.translation_matrix(
                                          (lo + hi) / 2)), False)]
    if isinstance(s, OpenBox):
        out = []
        for lo, hi in s.walls():
            lo, hi = np.asarray(lo, float), np.asarray(hi, float)
            out.append((trimesh.creation.box(
                extents=hi - lo, transform=trimesh.transformations.translation_matrix(
                    (lo + hi) / 2)), False))
        return out
    if isinstance(s, Quad):
        c = np.asarray(s.corners, float)
        return [(trimesh.Trimesh(vertices=c, faces=[[0, 1, 2], [0, 2, 3]], process=False),
                 False)]
    if isinstance(s, Mesh):
        return [(trimesh.Trimesh(vertices=np.asarray(s.vertices, float),
                                 faces=np.asarray(s.faces, np.int64), process=False), False)]
    raise TypeError(f"unknown shape kind {type(s).__name__}")


def scene_triangles(scene: Scene, *, sphere_subdivisions: int = 3,
                    torus_sections: tuple[int, int] = (64, 24), skip: tuple = ()) -> Triangles:
    """Every shape of ``scene`` as triangles (world space), but those of the types in
    ``skip`` (their owner indices stay those of ``scene.shapes``)."""
    corners, owner, vnorm, part = [], [], [], []
    for i, s in enumerate(scene.shapes):
        if isinstance(s, skip):
            continue
        for m, smooth in _shape_meshes(s, sphere_subdivisions, torus_sections):
            f = np.asarray(m.faces)
            corners.append(np.asarray(m.vertices, float)[f])
            owner.append(np.full(len(f), i, np.int32))
            part.append(np.full(len(f), len(part), np.int32))
            vnorm.append(np.asarray(m.vertex_normals, float)[f] if smooth
                         else np.zeros((len(f), 3, 3)))
    if not corners:
        z = np.zeros((0, 3, 3))
        return Triangles(z, np.zeros(0, np.int32), z, np.zeros(0, np.int32))
    return Triangles(np.concatenate(corners), np.concatenate(owner), np.concatenate(vnorm),
                     np.concatenate(part))


def _moller_trumbore(o, d, v0, e1, e2, t_min):
    """Möller–Trumbore on broadcast (…) arrays of components: o, d, v0, e1, e2 are 3-tuples.
    Returns t (inf: no hit) and the barycentric coordinates u, v.  The brute-force and the culled
    paths of :func:`cast_rays` share this arithmetic, so they return bit-identical hits."""
    ox, oy, oz = o
    dx, dy, dz = d
    px, py, pz = dy * e2[2] - dz * e2[1], dz * e2[0] - dx * e2[2], dx * e2[1] - dy * e2[0]
    det = px * e1[0] + py * e1[1] + pz * e1[2]
    ok = np.abs(det) > 1e-14
    inv = np.where(ok, 1.0 / np.where(ok, det, 1.0), 0.0)
    tx, ty, tz = ox - v0[0], oy - v0[1], oz - v0[2]
    u = (tx * px + ty * py + tz * pz) * inv
    qx, qy, qz = ty * e1[2] - tz * e1[1], tz * e1[0] - tx * e1[2], tx * e1[1] - ty * e1[0]
    v = (dx * qx + dy * qy + dz * qz) * inv
    t = (e2[0] * qx + e2[1] * qy + e2[2] * qz) * inv
    good = ok & (u >= 0) & (v >= 0) & (u + v <= 1) & (t > t_min)
    return np.where(good, t, np.inf), u, v


def _cast_rays_brute(tris: Triangles, o, d, t_min: float = 0.0, max_pairs: int = 1 << 18):
    """Every ray against every triangle (the reference for the culled :func:`cast_rays`)."""
    R = len(o)
    t_out = np.full(R, np.inf)
    f_out = np.full(R, -1, np.int64)
    b1_out = np.zeros(R)
    b2_out = np.zeros(R)
    F = len(tris)
    if F == 0 or R == 0:
        return t_out, f_out, b1_out, b2_out
    v0 = tris.corners[:, 0].T  # (3, F) components, so that every product is a plain
    e1 = (tris.corners[:, 1] - tris.corners[:, 0]).T  # (R, F) broadcast (np.cross is slow)
    e2 = (tris.corners[:, 2] - tris.corners[:, 0]).T
    step = max(1, max_pairs // F)
    for r0 in range(0, R, step):
        oc = tuple(o[r0:r0 + step, c, None] for c in range(3))
        dc = tuple(d[r0:r0 + step, c, None] for c in range(3))
        t, u, v = _moller_trumbore(oc, dc, v0, e1, e2, t_min)
        j = np.argmin(t, axis=1)  # the first face among equal t
        rows = np.arange(len(j))
        tj = t[rows, j]
        hit = np.isfinite(tj)
        sl = slice(r0, r0 + len(j))
        t_out[sl] = tj
        f_out[sl] = np.where(hit, j, -1)
        b1_out[sl] = np.where(hit, u[rows, j], 0.0)
        b2_out[sl] = np.where(hit, v[rows, j], 0.0)
    return t_out, f_out, b1_out, b2_out


@dataclass(frozen=True, eq=False)
class _BVH:
    """Bounding-volume hierarchy over a triangle soup: node boxes (padded outwards), children
    (-1 at leaves) and each leaf's faces (-1 padding), and the same data in the layout the
    vectorized traversal reads: ``box`` (6, nodes) the rows lo_x, lo_y, lo_z, hi_x, hi_y, hi_z,
    ``tri`` (9, leaves, leaf_size) the components of each leaf face's corner 0 and of its
    edges 1 - 0 and 2 - 0 (zero for padding), and ``fill`` each leaf's number of faces (its
    padding follows them).  Contiguous component rows rather than (n, 3) rows make the slab
    test ~5x faster (a 3-wide reduction along the last axis costs more than the arithmetic,
    measured)."""

    lo: np.ndarray  # (nodes, 3)
    hi: np.ndarray
    left: np.ndarray  # (nodes,)
    right: np.ndarray
    leaf: np.ndarray  # (nodes,) row in ``faces`` (-1: inner node)
    faces: np.ndarray  # (leaves, leaf_size)
    box: np.ndarray  # (6, nodes)
    tri: np.ndarray  # (9, leaves, leaf_size)
    fill: np.ndarray  # (leaves,) faces before the padding


def _build_bvh(corners: np.ndarray, part: np.ndarray, leaf_size: int = 8) -> _BVH:
    """Parts first (a node over several parts splits them in two halves by their centroids),
    then a median split of the face centroids along their longest extent, down to ``leaf_size``
    faces: large faces of one part (a wall) are not boxed together with the small ones of
    another (a sphere)."""
    cmin, cmax = corners.min(1), corners.max(1)  # (F, 3) per-face boxes
    cen = corners.mean(1)
    n_parts = int(part.max()) + 1 if len(part) else 0
    part_cen = np.zeros((n_parts, 3))
    np.add.at(part_cen, part, cen)
    part_cen /= np.maximum(np.bincount(part, minlength=n_parts), 1)[:, None]
    ext = float(np.max(cmax.max(0) - cmin.min(0))) if len(corners) else 1.0
    pad = 1e-9 * max(ext, 1e-300) + 1e-12  # a hit accepted by Möller–Trumbore lies in the box
    lo, hi, left, right, leaf, faces = [], [], [], [], [], []
    stack = [(np.arange(len(corners)), -1, 0)]  # (faces, parent, side)
    while stack:
        idx, parent, side = stack.pop()
        n = len(lo)
        lo.append(cmin[idx].min(0) - pad)
        hi.append(cmax[idx].max(0) + pad)
        left.append(-1)
        right.append(-1)
        if parent >= 0:
            (left if side == 0 else right)[parent] = n
        if len(idx) <= leaf_size:
            leaf.append(len(faces))
            faces.append(np.pad(idx, (0, leaf_size - len(idx)), constant_values=-1))
            continue
        leaf.append(-1)
        parts = np.unique(part[idx])
        if len(parts) > 1:
            c = part_cen[parts]
            ax = int(np.argmax(c.max(0) - c.min(0)))
            ps = parts[np.argsort(c[:, ax], kind="stable")]
            lower = np.isin(part[idx], ps[:len(ps) // 2])
            stack.append((idx[~lower], n, 1))
            stack.append((idx[lower], n, 0))
            continue
        c = cen[idx]
        ax = int(np.argmax(c.max(0) - c.min(0)))
        order = idx[np.argsort(c[:, ax], kind="stable")]
        half = len(order) // 2
        stack.append((order[half:], n, 1))
        stack.append((order[:half], n, 0))
    lo, hi = np.array(lo), np.array(hi)
    faces = np.array(faces, np.int64).reshape(-1, leaf_size)
    c0 = corners[:, 0]
    comp = np.concatenate([c0, corners[:, 1] - c0, corners[:, 2] - c0], axis=1)  # (F, 9)
    tri = np.where(faces[..., None] >= 0, comp[np.maximum(faces, 0)], 0.0)  # as the brute force
    return _BVH(lo, hi, np.array(left), np.array(right), np.array(leaf), faces,
                np.ascontiguousarray(np.concatenate([lo, hi], axis=1).T),
                np.ascontiguousarray(np.moveaxis(tri, -1, 0)), (faces >= 0).sum(1))


def _bvh_of(tris: Triangles) -> _BVH:
    bvh = getattr(tris, "_bvh", None)
    if bvh is None:
        bvh = _build_bvh(tris.corners, tris.shape if tris.part is None else tris.part)
        object.__setattr__(tris, "_bvh", bvh)  # cached on the (frozen) soup
    return bvh


def cast_rays(tris: Triangles, origins, directions, *, t_min: float = 0.0,
              max_pairs: int = 1 << 20):
    """First hit of each ray o + t·d (t > t_min) against the triangles (Möller–Trumbore).

    origins, directions: (R, 3).  Returns ``t`` (R,) (inf: no hit), ``face`` (R,) (-1: none) and
    the barycentric coordinates ``(b1, b2)`` (R,) of the hit on its face.

    Rays are culled with a bounding-volume hierarchy (breadth-first, vectorized: every (ray, node)
    pair whose padded box the ray crosses descends), then tested against the faces of the leaves
    they reach with the same arithmetic as the brute force; among hits at equal t the lowest face
    index wins, as there.  The result is bit-identical to testing every ray against every face.
    """
    o = np.asarray(origins, np.float64).reshape(-1, 3)
    d = np.asarray(directions, np.float64).reshape(-1, 3)
    R = len(o)
    t_out = np.full(R, np.inf)
    f_out = np.full(R, -1, np.int64)
    b1_out = np.zeros(R)
    b2_out = np.zeros(R)
    if len(tris) == 0 or R == 0:
        return t_out, f_out, b1_out, b2_out
    bvh = _bvh_of(tris)
    oc = tuple(np.ascontiguousarray(o[:, c]) for c in range(3))
    dc = tuple(np.ascontiguousarray(d[:, c]) for c in range(3))
    with np.errstate(divide="ignore", invalid="ignore"):
        inv_d = tuple(1.0 / x for x in dc)  # ±inf along axes the ray does not move on

    # descend: (ray, node) pairs whose box the ray crosses in front of t_min
    ray = np.arange(R)
    node = np.zeros(R, np.int64)
    leaf_r, leaf_l, leaf_t = [], [], []
    while len(ray):
        tn = tf = None
        with np.errstate(invalid="ignore"):  # 0·inf: the origin on a box face, no constraint
            for c in range(3):
                oo, ii = oc[c][ray], inv_d[c][ray]
                t1 = (bvh.box[c][node] - oo) * ii
                t2 = (bvh.box[c + 3][node] - oo) * ii
                near, far = np.fmin(t1, t2), np.fmax(t1, t2)
                tn = near if tn is None else np.fmax(tn, near, out=tn)
                tf = far if tf is None else np.fmin(tf, far, out=tf)
        keep = ~(tf < tn) & ~(tf < t_min)  # NaN (no axis constrains) keeps the pair
        ray, node, tn = ray[keep], node[keep], tn[keep]
        lf = bvh.leaf[node]
        at_leaf = lf >= 0
        leaf_r.append(ray[at_leaf])
        leaf_l.append(lf[at_leaf])
        leaf_t.append(np.nan_to_num(tn[at_leaf], nan=-np.inf))  # box entry along the ray
        ray, node = ray[~at_leaf], node[~at_leaf]
        ray = np.concatenate([ray, ray])
        node = np.concatenate([bvh.left[node], bvh.right[node]])
    pr, pl, pt = (np.concatenate(x) for x in (leaf_r, leaf_l, leaf_t))

    # the leaves each ray reaches, nearest box first, one rank per round: a leaf whose box the
    # ray enters beyond its nearest hit so far cannot hold that hit or a nearer one (a hit lies
    # inside its padded box), so it is skipped
    order = np.lexsort((pt, pr))
    pr, pl, pt = pr[order], pl[order], pt[order]
    start = np.ones(len(pr), bool)
    start[1:] = pr[1:] != pr[:-1]
    rank = np.arange(len(pr)) - np.flatnonzero(start)[np.cumsum(start) - 1]
    by_rank = np.argsort(rank, kind="stable")
    bounds = np.searchsorted(rank[by_rank], np.arange(rank.max() + 2 if len(rank) else 1))
    best = np.full(R, np.inf)
    found = []  # (ray, face, t, u, v) of every hit tested
    step = max(1, max_pairs // bvh.faces.shape[1])
    for k in range(len(bounds) - 1):
        idx = by_rank[bounds[k]:bounds[k + 1]]
        idx = idx[pt[idx] <= best[pr[idx]]]
        sr, sl = pr[idx], pl[idx]
        for p0 in range(0, len(sr), step):
            r_, l_ = sr[p0:p0 + step], sl[p0:p0 + step]
            fill = bvh.fill[l_]
            for f in np.unique(fill):  # (P, 1) rays against their leaves' (P, f) faces
                m = fill == f
                rf, lf = r_[m], l_[m]
                t, u, v = _moller_trumbore(tuple(x[rf, None] for x in oc),
                                           tuple(x[rf, None] for x in dc),
                                           *(tuple(bvh.tri[c][lf, :f] for c in range(c0, c0 + 3))
                                             for c0 in (0, 3, 6)), t_min)
                pi, fi = np.nonzero(np.isfinite(t))
                rr, th = rf[pi], t[pi, fi]
                found.append((rr, bvh.faces[lf[pi], fi], th, u[pi, fi], v[pi, fi]))
                np.minimum.at(best, rr, th)
    if not found or not sum(len(x[0]) for x in found):
        return t_out, f_out, b1_out, b2_out
    fr_, ff_, ft_, fu_, fv_ = (np.concatenate(x) for x in zip(*found))
    order = np.lexsort((ff_, ft_, fr_))  # per ray: nearest, then the lowest face
    fr_ = fr_[order]
    first = np.ones(len(fr_), bool)
    first[1:] = fr_[1:] != fr_[:-1]
    sel = order[first]
    rows = fr_[first]
    t_out[rows] = ft_[sel]
    f_out[rows] = ff_[sel]
    b1_out[rows] = fu_[sel]
    b2_out[rows] = fv_[sel]
    return t_out, f_out, b1_out, b2_out


def hit_normals(tris: Triangles, face, b1, b2) -> np.ndarray:
    """Unit normals (R, 3) at hits (interpolated vertex normals where the face has them, else the
    face normal); zero where ``face`` < 0."""
    face = np.asarray(face)
    hit = face >= 0
    f = np.where(hit, face, 0)
    fn = tris.face_normals[f] if len(tris) else np.zeros((len(face), 3))
    if len(tris):
        vn = tris.vertex_normals[f]
        w = np.stack([1.0 - b1 - b2, b1, b2], -1)[..., None]
        sn = (vn * w).sum(1)
        smooth = np.linalg.norm(vn[:, 0], axis=-1) > 0
        n = np.where(smooth[:, None], sn, fn)
    else:
        n = fn
    n = n / np.maximum(np.linalg.norm(n, axis=-1, keepdims=True), 1e-300)
    return np.where(hit[:, None], n, 0.0)
