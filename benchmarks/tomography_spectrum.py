"""How much of each tomography cloud lies at the scale of its cells: what no smooth estimate
can recover, whatever the fit.

For each cloud's true density grid (the shared ``cloud-tomo`` and data_synthetic's ``b`` …
``e``, as ``tomography.load_case`` finds them; 32³), the relative L2 error (‖a − t‖ / ‖t‖, as ``DensityFit.relative_error``)
of smoothed versions of the truth itself: a Gaussian blur of σ cells (zero outside the grid),
and the truth averaged over blocks of 2³ / 4³ cells and resampled back (``fit._density.resample``,
the fit's own ladder map), and the share of the truth's L2 norm at wavelengths under 4 cells
(spatial frequency above half the grid's Nyquist).  An estimate that holds only the scales a
prior keeps smooth cannot be closer to the truth than these; a density fit's error on a cloud
is to be read against them.  NumPy only (seconds).

    python benchmarks/tomography_spectrum.py [--out benchmarks/results/tomography/spectrum.md]
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
from scipy.ndimage import gaussian_filter

import _common as C
from difffog.fit._density import resample
from tomography import load_case

ROOT = Path(__file__).resolve().parents[1]
SIGMAS = (0.5, 0.75, 1.0, 1.5)


def truth(cloud: str) -> np.ndarray:
    return np.asarray(load_case(cloud)[3].fog.density, np.float64)


def rel(a: np.ndarray, t: np.ndarray) -> float:
    return float(np.linalg.norm(a - t) / np.linalg.norm(t))


def high_share(t: np.ndarray, cutoff: float = 0.25) -> float:
    """√(share of Σ|FFT(t)|² at |k| > cutoff cycles per cell) (0.25: wavelengths < 4 cells)."""
    F = np.abs(np.fft.fftn(t)) ** 2
    k = np.sqrt(sum(g ** 2 for g in np.meshgrid(*(np.fft.fftfreq(n) for n in t.shape),
                                                 indexing="ij")))
    return float(np.sqrt(F[k > cutoff].sum() / F.sum()))


def row(cloud: str) -> dict:
    t = truth(cloud)
    out = {"cloud": cloud, "shape": "×".join(map(str, t.shape)),
           "occupied": float(np.mean(t > 0)), "high": high_share(t)}
    for s in SIGMAS:
        out[f"blur{s:g}"] = rel(gaussian_filter(t, s, mode="constant"), t)
    for b in (2, 4):
        coarse = tuple(max(1, n // b) for n in t.shape)
        out[f"block{b}"] = rel(resample(resample(t, coarse), t.shape), t)
    return out


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--clouds", nargs="+", default=["shared", "b", "c", "d", "e"])
    ap.add_argument("--out", default=str(ROOT / "benchmarks/results/tomography/spectrum.md"))
    a = ap.parse_args(argv)
    rows = [row(c) for c in a.clouds]
    head = (["cloud", "grid", "cells with fog", "norm at λ < 4 cells"]
            + [f"blur σ = {s:g}" for s in SIGMAS] + ["blocks 2³", "blocks 4³"])
    body = [[r["cloud"], r["shape"], f"{r['occupied']:.1%}", f"{r['high']:.3f}"]
            + [f"{r[f'blur{s:g}']:.3f}" for s in SIGMAS]
            + [f"{r['block2']:.3f}", f"{r['block4']:.3f}"] for r in rows]
    lines = ["# What lies at the scale of the cells: each cloud's truth against its own "
             "smoothed versions", "",
             "Relative L2 error of the truth blurred (Gaussian, σ in cells) or averaged over "
             "blocks and resampled back, against the truth; and the share of its norm at "
             "wavelengths under 4 cells. `python benchmarks/tomography_spectrum.py` "
             "(module docstring).", ""]
    lines += C.md_table(head, body, "lllr" + "r" * (len(head) - 4))
    text = "\n".join(lines) + "\n"
    print(text)
    out = Path(a.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(text)
    print(f"wrote {out}")


if __name__ == "__main__":
    main()
