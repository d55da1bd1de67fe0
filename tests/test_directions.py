"""The lattice direction set: counts, weights, symmetry, per-node cosine normalization."""

import numpy as np
import pytest

from difffog import SceneError, direction_set
from difffog.geometry._directions import cosine_normalization


@pytest.mark.parametrize("M", [1, 2, 3, 5, 8])
def test_unique_directions_and_weights(M):
    d = direction_set(M)
    V, W = d.all_vectors(), d.all_weights()
    assert V.shape == (6 * (2 * M + 1) ** 2, 3)
    keys = np.round(V * 1e9).astype(np.int64)
    uniq, inv = np.unique(keys, axis=0, return_inverse=True)
    assert len(uniq) == 24 * M**2 + 2
    # per-face weights cover the sphere exactly once (raw and flux-corrected)
    assert abs(d.raw_weights.sum() - 4 * np.pi) < 1e-10
    assert abs(W.sum() - 4 * np.pi) < 1e-6 * 4 * np.pi
    assert np.all(W > 0)
    # each unique direction owns one full cube cell, split between the faces it lies on
    full = np.bincount(inv.ravel(), weights=d.raw_weights.ravel())
    assert np.all(full > 0)
    np.testing.assert_allclose(full.sum(), 4 * np.pi, rtol=1e-12)


@pytest.mark.parametrize("M", [1, 2, 3, 5])
def test_flux_correction_and_symmetry(M):
    d = direction_set(M)
    V, W = d.all_vectors(), d.all_weights()
    for axis in range(3):
        for sign in (1, -1):
            c = sign * V[:, axis]
            np.testing.assert_allclose((W * np.maximum(c, 0)).sum(), np.pi, rtol=1e-12)
    # symmetric under negation: -L is a direction of the opposite face with the same weight
    keyed = {tuple(np.round(v, 9)): w for v, w in zip(V, W)}
    for v, w in zip(V, W):
        assert keyed[tuple(np.round(-v, 9))] == pytest.approx(w, rel=1e-12)
    # the raw (exact cell) weights under-count the hemispheric flux, as DESIGN.md measured
    raw = (d.raw_weights.reshape(-1) * np.maximum(V[:, 2], 0)).sum() / np.pi
    assert raw < 1.0


def test_raw_flux_deficit_matches_design_note():
    raw = direction_set(2)
    V = raw.all_vectors()
    flux = (raw.raw_weights.reshape(-1) * np.maximum(V[:, 2], 0)).sum() / np.pi
    assert flux == pytest.approx(0.968, abs=0.001)


@pytest.mark.parametrize("M", [2, 3, 5])
def test_cosine_normalization_gives_pi(M):
    d = direction_set(M)
    rng = np.random.default_rng(M)
    n = rng.normal(size=(500, 3))
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    c = cosine_normalization(n, d)
    sums = (np.maximum(n @ d.all_vectors().T, 0) * d.all_weights()).sum(1)
    np.testing.assert_allclose(c * sums, np.pi, rtol=1e-12)
    # the correction is small: the direction set is already close to cosine-exact
    assert np.all(np.abs(c - 1) < {2: 0.06, 3: 0.03, 5: 0.015}[M])
    # axis normals need none after flux correction
    np.testing.assert_allclose(cosine_normalization(np.eye(3), d), 1.0, rtol=1e-12)


@pytest.mark.parametrize("bad", [0, -1, 2.5, True, "3"])
def test_bad_half_width(bad):
    with pytest.raises(SceneError, match="half-width M must be an integer >= 1"):
        direction_set(bad)
