"""The lattice direction set of half-width M (Langer, Breton & Zucker §5).

The rays through a node are the segments from the node to the integer points of the cube
surface of half-width M around it: face ``+z`` holds the (2M+1)² directions (p, q, M) with
|p|, |q| ≤ M, and likewise for the other five faces.  There are 24M²+2 distinct directions;
those on cube edges and corners belong to two or three faces.

Weights.  Each face direction owns the cell [p-½, p+½] × [q-½, q+½] of its face, clipped at the
face's edges, projected on the unit sphere (exact solid angle of a rectangle).  An edge
direction thus owns half a cell on each of its two faces (a corner a quarter on each of three),
so summing the per-face weights over the six faces covers the sphere exactly once (4π) and
every distinct direction gets the full solid angle of its cell.

Flux correction.  Exact cell solid angles still integrate |cos θ| over a hemisphere to 0.968π at
M = 2 (the lattice over-weights grazing directions, which carry no flux).  We rescale the weights
by a factor (α + β·Σᵢ|L̂ᵢ|), which keeps the set symmetric under negation and under permutation
of the axes, with α, β chosen so that the weights still sum to 4π and the hemispheric flux sum
Σ_{L̂z>0} w L̂z is exactly π.  (docs/design.md: this roughly halves slab errors at τ ≥ 1.)
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

# The six sweep faces in the order the solver uses them: (axis, sign).
FACE_AXES: tuple[tuple[int, int], ...] = ((0, 1), (0, -1), (1, 1), (1, -1), (2, 1), (2, -1))
FACE_NAMES = ("+x", "-x", "+y", "-y", "+z", "-z")


def face_plane_axes(axis: int) -> tuple[int, int]:
    """The in-plane axes (u, v) of a sweep along ``axis``, in increasing order."""
    return tuple(a for a in range(3) if a != axis)  # type: ignore[return-value]


def _rect_solid_angle(x0, x1, y0, y1, d):
    """Solid angle of the rectangle [x0,x1]×[y0,y1] in the plane at distance d (exact)."""

    def F(x, y):
        return np.arctan2(x * y, d * np.sqrt(x * x + y * y + d * d))

    return F(x1, y1) - F(x0, y1) - F(x1, y0) + F(x0, y0)


@dataclass(frozen=True)
class DirectionSet:
    """Directions of half-width M, grouped by sweep face.

    For face f (``FACE_AXES[f] = (axis, sign)``) and in-plane axes (u, v) = face_plane_axes(axis),
    direction index d = (p+M)·(2M+1) + (q+M) is the lattice vector with component ``sign·M``
    along ``axis``, ``p`` along u and ``q`` along v.

    Attributes (D = (2M+1)², all float64 NumPy):
      M: half-width.
      pq: (D, 2) int — the in-plane steps (p, q) (same for every face).
      length: (D,) — |L| = sqrt(p² + q² + M²) in lattice units.
      vectors: (6, D, 3) — unit world directions L̂ of each face's directions.
      weights: (6, D) — flux-corrected solid angles (sum over all faces = 4π).
      raw_weights: (6, D) — exact clipped-cell solid angles before flux correction.
    """

    M: int
    pq: np.ndarray
    length: np.ndarray
    vectors: np.ndarray
    weights: np.ndarray
    raw_weights: np.ndarray

    @property
    def D(self) -> int:
        return (2 * self.M + 1) ** 2

    @property
    def n_unique(self) -> int:
        return 24 * self.M**2 + 2

    def all_vectors(self) -> np.ndarray:
        """(6·D, 3) unit vectors, face by face (edge directions repeated)."""
        return self.vectors.reshape(-1, 3)

    def all_weights(self) -> np.ndarray:
        return self.weights.reshape(-1)


def direction_set(M: int, flux_correction: bool = True) -> DirectionSet:
    """Build the direction set of half-width ``M`` (an int ≥ 1)."""
    if not isinstance(M, (int, np.integer)) or isinstance(M, bool) or M < 1:
        from .._errors import SceneError

        raise SceneError(
            f"directions: half-width M must be an integer >= 1, got {M!r}; "
            "typical values are 2 (draft), 3 (default) or 5 (the paper's choice)"
        )
    M = int(M)
    r = np.arange(-M, M + 1)
    p, q = np.meshgrid(r, r, indexing="ij")
    p, q = p.reshape(-1), q.reshape(-1)
    length = np.sqrt(p**2 + q**2 + M**2, dtype=np.float64)
    x0, x1 = np.maximum(p - 0.5, -M), np.minimum(p + 0.5, M)
    y0, y1 = np.maximum(q - 0.5, -M), np.minimum(q + 0.5, M)
    cell = _rect_solid_angle(x0, x1, y0, y1, float(M))

    vectors = np.zeros((6, p.size, 3))
    for f, (axis, sign) in enumerate(FACE_AXES):
        u, v = face_plane_axes(axis)
        vectors[f, :, axis] = sign * M / length
        vectors[f, :, u] = p / length
        vectors[f, :, v] = q / length
    raw = np.broadcast_to(cell, (6, p.size)).copy()

    weights = raw
    if flux_correction:
        s = np.abs(vectors).sum(-1)  # Σ|L̂ᵢ|, symmetric under negation and axis permutation
        up = vectors[..., 2] > 0
        cz = np.where(up, vectors[..., 2], 0.0)
        # solve [Σw, Σw s; Σw cz, Σw s cz] [α, β] = [4π, π]
        A = np.array(
            [[raw.sum(), (raw * s).sum()], [(raw * cz).sum(), (raw * s * cz).sum()]],
        )
        alpha, beta = np.linalg.solve(A, [4 * np.pi, np.pi])
        weights = raw * (alpha + beta * s)
    return DirectionSet(
        M=M,
        pq=np.stack([p, q], -1),
        length=length,
        vectors=vectors,
        weights=weights,
        raw_weights=raw,
    )


def cosine_normalization(normals: np.ndarray, dirs: DirectionSet) -> np.ndarray:
    """Per-node factor c so that c·Σ_{L̂·N>0} w L̂·N = π exactly for each unit normal.

    ``normals``: (..., 3) unit vectors; returns (...) factors (1 where a normal is zero).
    A Lambertian surface's irradiance is then E = c·Σ_{arriving L} w R |L̂·N|.
    """
    n = np.asarray(normals, dtype=np.float64)
    flat = np.ascontiguousarray(n.reshape(-1, 3))
    # Lattices repeat normals (a flat wall's nodes share one): evaluate each distinct normal
    # once.  Rows compared bit for bit (a 24-byte key), so the result is unchanged; fog-balls at
    # N = 128: 899,230 SURFACE nodes, 99,040 distinct normals, 2.1 s → 0.5 s.
    uniq, inverse = np.unique(flat.view("V24").ravel(), return_inverse=True)
    uniq = uniq.view(np.float64).reshape(-1, 3)
    V, W = dirs.all_vectors(), dirs.all_weights()
    out = np.empty(uniq.shape[0])
    for start in range(0, uniq.shape[0], 65536):  # chunks bound the (chunk, 6D) temporary
        c = uniq[start : start + 65536] @ V.T
        out[start : start + 65536] = np.maximum(c, 0.0, out=c) @ W
    ok = out > 0
    factor = np.where(ok, np.pi / np.where(ok, out, 1.0), 1.0)
    return factor[inverse.ravel()].reshape(n.shape[:-1])


def sky_quadrature(n_mu: int, n_phi: int):
    """Directions towards the sky (unit vectors with z > 0) and their solid-angle weights.

    Gauss–Legendre in μ = cos θ on (0, 1) × n_phi uniform azimuths (offset by half a step so
    that no direction lies in a lattice plane).  Σ weights = 2π exactly.
    """
    x, w = np.polynomial.legendre.leggauss(n_mu)
    mu, wmu = 0.5 * (x + 1.0), 0.5 * w
    phi = (np.arange(n_phi) + 0.5) * (2 * np.pi / n_phi)
    m, p = np.meshgrid(mu, phi, indexing="ij")
    s = np.sqrt(1.0 - m**2)
    dirs = np.stack([s * np.cos(p), s * np.sin(p), m], -1).reshape(-1, 3)
    wts = np.repeat(wmu * (2 * np.pi / n_phi), n_phi)
    return dirs, wts
