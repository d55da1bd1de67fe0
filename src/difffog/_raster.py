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
import trimesh

from ._scene import Box, Mesh, OpenBox, Quad, Scene, Sphere, Torus

__all__ = ["Triangles", "scene_triangles", "cast_rays", "hit_normals"]


@dataclass(frozen=True, eq=False)
class Triangles:
    """A triangle soup: corners (F, 3, 3), owning shape index (F,), optional vertex normals
    (F, 3, 3) (zero rows: use the face normal)."""

    corners: np.ndarray
    shape: np.ndarray
    vertex_normals: np.ndarray

    def __len__(self) -> int:
        return len(self.shape)

    @property
    def face_normals(self) -> np.ndarray:
        c = self.corners
        n = np.cross(c[:, 1] - c[:, 0], c[:, 2] - c[:, 0])
        return n / np.maximum(np.linalg.norm(n, axis=-1, keepdims=True), 1e-300)


def _rotation_z_to(axis) -> np.ndarray:
    a = np.asarray(axis, float)
    a = a / np.linalg.norm(a)
    return trimesh.geometry.align_vectors([0.0, 0.0, 1.0], a)


def _shape_meshes(s, sphere_subdivisions: int, torus_sections: tuple[int, int]):
    """[(trimesh.Trimesh, smooth)] of one shape."""
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
                    torus_sections: tuple[int, int] = (64, 24)) -> Triangles:
    """Every shape of ``scene`` as triangles (world space)."""
    corners, owner, vnorm = [], [], []
    for i, s in enumerate(scene.shapes):
        for m, smooth in _shape_meshes(s, sphere_subdivisions, torus_sections):
            f = np.asarray(m.faces)
            corners.append(np.asarray(m.vertices, float)[f])
            owner.append(np.full(len(f), i, np.int32))
            vnorm.append(np.asarray(m.vertex_normals, float)[f] if smooth
                         else np.zeros((len(f), 3, 3)))
    if not corners:
        z = np.zeros((0, 3, 3))
        return Triangles(z, np.zeros(0, np.int32), z)
    return Triangles(np.concatenate(corners), np.concatenate(owner), np.concatenate(vnorm))


def cast_rays(tris: Triangles, origins, directions, *, t_min: float = 0.0,
              max_pairs: int = 1 << 18):
    """First hit of each ray o + t·d (t > t_min) against the triangles (Möller–Trumbore).

    origins, directions: (R, 3).  Returns ``t`` (R,) (inf: no hit), ``face`` (R,) (-1: none) and
    the barycentric coordinates ``(b1, b2)`` (R,) of the hit on its face.
    """
    o = np.asarray(origins, np.float64).reshape(-1, 3)
    d = np.asarray(directions, np.float64).reshape(-1, 3)
    R = len(o)
    t_out = np.full(R, np.inf)
    f_out = np.full(R, -1, np.int64)
    b1_out = np.zeros(R)
    b2_out = np.zeros(R)
    F = len(tris)
    if F == 0 or R == 0:
        return t_out, f_out, b1_out, b2_out
    v0 = tris.corners[:, 0].T  # (3, F) components, so that every product below is a plain
    e1 = (tris.corners[:, 1] - tris.corners[:, 0]).T  # (R, F) broadcast (np.cross is slow)
    e2 = (tris.corners[:, 2] - tris.corners[:, 0]).T
    step = max(1, max_pairs // F)
    for r0 in range(0, R, step):
        ox, oy, oz = (o[r0:r0 + step, c, None] for c in range(3))
        dx, dy, dz = (d[r0:r0 + step, c, None] for c in range(3))
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
        t = np.where(good, t, np.inf)
        j = np.argmin(t, axis=1)
        rows = np.arange(len(j))
        tj = t[rows, j]
        hit = np.isfinite(tj)
        sl = slice(r0, r0 + len(j))
        t_out[sl] = tj
        f_out[sl] = np.where(hit, j, -1)
        b1_out[sl] = np.where(hit, u[rows, j], 0.0)
        b2_out[sl] = np.where(hit, v[rows, j], 0.0)
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
