"""The independent references difffog measures itself against, shipped with the package
(``difffog/data/references``, under 1 MB; provenance in its README.md):

* Mitsuba 3.9.1 ``volpath`` images of the benchmark scenes (``<scene>/<camera>.npy``, float32
  linear radiance, 2048–4096 samples per pixel, with their per-pixel noise in
  ``<camera>_stats.json``) and Mitsuba's time against error on a 2-core CPU and an H100
  (``convergence.csv``, ``convergence_gpu.csv``);
* adding-doubling reflectance and transmittance of homogeneous slabs
  (``slab_adding_doubling.csv``, iadpython 0.5.3, 64 quadrature points).
"""

from __future__ import annotations

import csv
import json
from importlib import resources
from pathlib import Path

import numpy as np


def references_dir() -> Path:
    """The folder of the shipped references."""
    return Path(str(resources.files("difffog").joinpath("data", "references")))


def reference_scenes(refdir: Path | None = None) -> list[str]:
    """Scenes with reference images."""
    refdir = references_dir() if refdir is None else Path(refdir)
    return sorted(p.name for p in refdir.iterdir() if p.is_dir())


def reference(scene: str, camera: str, refdir: Path | None = None):
    """(image (H, W) float32, per-pixel noise RMSE or None) of a scene's camera, or None when
    there is no reference for it."""
    refdir = references_dir() if refdir is None else Path(refdir)
    img = refdir / scene / f"{camera}.npy"
    if not img.exists():
        return None
    stats = refdir / scene / f"{camera}_stats.json"
    noise = json.loads(stats.read_text())["ref_noise_rmse"] if stats.exists() else None
    return np.load(img), noise


def reference_stats(scene: str, camera: str, refdir: Path | None = None) -> dict:
    """The ``<camera>_stats.json`` of a reference (spp, noise, mean, ...)."""
    refdir = references_dir() if refdir is None else Path(refdir)
    return json.loads((refdir / scene / f"{camera}_stats.json").read_text())


def slab_table(refdir: Path | None = None) -> list[dict]:
    """The adding-doubling slab table as rows (numbers as floats)."""
    refdir = references_dir() if refdir is None else Path(refdir)
    rows = []
    with (refdir / "slab_adding_doubling.csv").open(newline="") as f:
        for r in csv.DictReader(f):
            rows.append({k: _num(v) for k, v in r.items()})
    return rows


def _num(v: str):
    try:
        return float(v)
    except ValueError:
        return v
