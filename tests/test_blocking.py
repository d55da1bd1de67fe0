"""The sweep's segment-blocking masks (bit-packed, 64 nodes per word) against a per-node,
per-sample evaluation of their definition."""

import numpy as np
import pytest

from difffog.geometry._blocking import segment_blocking, segment_offsets
from difffog.geometry._directions import FACE_AXES, direction_set, face_plane_axes


def _by_definition(solid, surface, vectors, periodic_xy):
    """(D, nx, ny, nz) bool: a SURFACE node y is blocked along L when one of the segment's
    samples y − o (``segment_offsets``) is a SOLID node (vacuum outside, x and y wrapped when
    periodic)."""
    n = np.array(solid.shape)
    out = np.zeros((len(vectors),) + solid.shape, bool)
    for d, L in enumerate(vectors):
        for y in np.argwhere(surface):
            for o in segment_offsets(L):
                z = y - np.array(o)
                if periodic_xy:
                    z[:2] %= n[:2]
                if np.all((z >= 0) & (z < n)) and solid[tuple(z)]:
                    out[d][tuple(y)] = True
                    break
    return out


@pytest.mark.parametrize("face", range(6))
@pytest.mark.parametrize("periodic_xy", [False, True])
def test_packed_masks_match_the_definition(face, periodic_xy):
    rng = np.random.default_rng(face + 10 * periodic_xy)
    shape = (23, 70, 9) if face % 2 else (67, 5, 41)  # z longer and shorter than a 64-bit word
    solid = rng.random(shape) < 0.08
    surface = ~solid & (rng.random(shape) < 0.05)
    M = 2
    dirs = direction_set(M)
    axis, sign = FACE_AXES[face]
    u, v = face_plane_axes(axis)
    vec = np.zeros((dirs.D, 3), np.int64)
    vec[:, axis] = sign * M
    vec[:, u], vec[:, v] = dirs.pq[:, 0], dirs.pq[:, 1]
    got = segment_blocking(solid, surface, vec, periodic_xy)
    ref = _by_definition(solid, surface, vec, periodic_xy)
    assert ref.sum() > 50  # the case blocks something
    assert got.shape == shape + (-(-dirs.D // 8),) and got.dtype == np.uint8
    # bit d % 8 of byte d // 8
    unpacked = np.unpackbits(got, axis=-1, bitorder="little")[..., :dirs.D]
    np.testing.assert_array_equal(np.moveaxis(unpacked, -1, 0).astype(bool), ref)


def test_no_surface_blocks_nothing():
    solid = np.ones((4, 4, 4), bool)
    out = segment_blocking(solid, np.zeros_like(solid), np.array([[1, 0, 1]]), False)
    assert out.shape == (4, 4, 4, 1) and not out.any()
