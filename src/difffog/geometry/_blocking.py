"""Which lattice segments cross a solid: host-side, once per lattice (for the sweep).

A lattice ray jumps M planes per step.  The sweep needs to know, for each SURFACE node y and
each direction L, whether the segment from y − L to y crosses a SOLID node: if it does, the ray
arriving at y was emitted by the surface in between (see ``_sweep.py``).
"""

from __future__ import annotations

import numpy as np


def segment_blocking(solid: np.ndarray, surface: np.ndarray, vectors_int: np.ndarray,
                     periodic_xy: bool) -> np.ndarray:
    """(D, nx, ny, nz) bool: does the segment from y − L_d to y cross a SOLID node?

    solid, surface: (nx, ny, nz) bool; vectors_int: (D, 3) integer lattice vectors.  The segment
    is sampled at 2·max|L| points (every half node or closer), each tested against the node it
    falls in; only SURFACE nodes can be blocked (FREE nodes are > M nodes from any solid).
    Shifted reads are views of one padded copy of ``solid`` (vacuum outside an open domain,
    wrapped laterally for a periodic one), restricted to the box around the SURFACE nodes.
    """
    D = vectors_int.shape[0]
    out = np.zeros((D,) + solid.shape, bool)
    if not surface.any():
        return out
    P = int(np.abs(vectors_int).max())
    modes = [("wrap" if periodic_xy and a < 2 else "constant") for a in range(3)]
    padded = solid
    for a, mode in enumerate(modes):
        widths = [(0, 0)] * 3
        widths[a] = (P, P)
        padded = np.pad(padded, widths, mode=mode)
    where = np.argwhere(surface)
    lo, hi = where.min(0), where.max(0) + 1
    box = tuple(slice(lo[a], hi[a]) for a in range(3))
    size = hi - lo
    for d in range(D):
        L = vectors_int[d]
        S = 2 * int(np.abs(L).max())
        offsets = {tuple(np.rint(k / S * L).astype(int)) for k in range(1, S + 1)}
        acc = np.zeros(tuple(size), bool)
        for off in offsets:
            start = [P + lo[a] - off[a] for a in range(3)]
            acc |= padded[start[0]:start[0] + size[0], start[1]:start[1] + size[1],
                          start[2]:start[2] + size[2]]
        out[d][box] = acc & surface[box]
    return out
