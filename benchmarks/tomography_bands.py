"""Where a density estimate's error sits: its mass and squared error by optical depth from
the cloud's outside.

Each cell of the truth gets the least optical depth from the domain's faces to its centre
along the six axis directions (σ_t = (ζ + γ)·density, cells of the scene's grid): the cloud's
skin (below 1) is what the cameras see directly, the core (above 2) what they see only
through multiple scattering.  For each band: the truth's share of the mass, the estimate's
mass against the truth's there, and the band's share of ‖estimate − truth‖².  A fit that
comes out too thin because the forward model is too bright at the cloud's edge misses mass
in the skin; one whose prior smooths an unconstrained core misses it in the core.

    python benchmarks/tomography_bands.py ESTIMATE.npz [ESTIMATE.npz ...] [--cloud shared|b|c]

(ESTIMATE.npz: a ``density.npz`` that ``difffog fit`` or ``benchmarks/tomography.py``
wrote.)
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

import _common as C
from tomography import load_case

BANDS = ((0.0, 0.5), (0.5, 1.0), (1.0, 2.0), (2.0, 3.0), (3.0, np.inf))


def depth_from_outside(sigma_cell: np.ndarray) -> np.ndarray:
    """Each cell's least optical depth to its centre from the grid's six faces along the
    axes, given each cell's optical depth ``sigma_cell`` (σ_t × cell width)."""
    out = np.full(sigma_cell.shape, np.inf)
    for ax in range(3):
        for flip in (False, True):
            d = np.flip(sigma_cell, ax) if flip else sigma_cell
            c = np.cumsum(d, axis=ax) - 0.5 * d
            out = np.minimum(out, np.flip(c, ax) if flip else c)
    return out


def band_rows(est: np.ndarray, truth: np.ndarray, tau: np.ndarray, empty: float = 1e-3):
    err2 = np.sum((est - truth) ** 2)
    rows = []
    for lo, hi in BANDS:
        m = (tau >= lo) & (tau < hi) & (truth > empty)
        if m.any():
            rows.append([f"{lo:g}–{hi:g}", str(int(m.sum())),
                         f"{truth[m].sum() / truth.sum():.1%}",
                         f"{est[m].sum() / truth[m].sum() - 1:+.1%}",
                         f"{np.sum((est - truth)[m] ** 2) / err2:.1%}"])
    m = truth <= empty
    rows.append(["no fog", str(int(m.sum())), "0", f"{est[m].sum() / truth.sum():+.1%} of the mass",
                 f"{np.sum((est - truth)[m] ** 2) / err2:.1%}"])
    return rows


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("estimates", nargs="+", type=Path)
    ap.add_argument("--cloud", default="shared", choices=["shared", "b", "c", "d", "e"])
    args = ap.parse_args(argv)
    _, _, _, truth_scene = load_case(args.cloud)
    truth = np.asarray(truth_scene.fog.density, np.float64)
    fog = truth_scene.fog
    lo, hi = np.asarray(truth_scene.domain.min), np.asarray(truth_scene.domain.max)
    cell = (hi - lo) / np.asarray(truth.shape)
    if not np.allclose(cell, cell[0]):
        raise SystemExit("tomography_bands: the grid's cells are not cubes")
    tau = depth_from_outside((fog.scattering + fog.absorption) * truth * cell[0])
    for path in args.estimates:
        est = np.load(path)["density"].astype(np.float64)
        if est.shape != truth.shape:
            raise SystemExit(f"{path}: grid {est.shape}, the truth's is {truth.shape}")
        l2 = np.linalg.norm(est - truth) / np.linalg.norm(truth)
        print(f"\n# {path}: relative L2 {l2:.3f}, mass {est.sum() / truth.sum() - 1:+.1%}\n")
        print("\n".join(C.md_table(["optical depth from outside", "cells", "truth's mass",
                                    "estimate's mass there", "share of the squared error"],
                                   band_rows(est, truth, tau), "lrrrr")))


if __name__ == "__main__":
    main()
