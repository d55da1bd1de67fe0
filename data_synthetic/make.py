"""Regenerate the synthetic fit targets in this folder, deterministically.

    PYTHONPATH=src python data_synthetic/make.py            # everything (~30-40 min on 2 cores)
    PYTHONPATH=src python data_synthetic/make.py --scene fog-balls
    PYTHONPATH=src python data_synthetic/make.py --quick --out /tmp/synthetic   # smoke test

For each scene and parameter set (``SETS`` below) it renders every camera of the built-in
scene at full camera resolution with the sweep solver at resolution ``N = 96`` and ``M = 5`` —
finer than the fits use (N = 24-32, M = 3) and than the model a fit's refine correction renders
at `difffog fit`'s defaults (N = 64, M = 4), so that a fit of these targets is not the "inverse
crime" and its model-error correction is judged against a finer lattice, as a photograph would
judge it (until stop 59 they were rendered at N = 48, M = 4, coarser than that correction) —
and writes, under ``<scene>/set<k>/``:

    <camera>.npy            noise-free float32 radiance (H, W), row 0 at the top
    <camera>_noise01.npy    plus i.i.d. Gaussian noise of σ = 1% of the image mean
    <camera>_noise05.npy    plus σ = 5% of the image mean

and ``truth.json`` with the parameters of every set, the render settings, σ per image and the
seed of every noise draw (a CRC32 of "<scene>/set<k>/<camera>/<level>"), so the same command
always writes the same bits on the same machine.  Each scene renders into a hidden folder
first and replaces its targets and its truth.json entry only when every set is done.  The
model is the public ``difffog.forward_model(scene, "sweep", ...)``, rendered with
``difffog.render``.

``--quick`` renders N = 16, M = 2, supersample 1, the first parameter set only (a smoke test,
not the committed targets: it must be written elsewhere with ``--out DIR``).
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import time
import zlib
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
N, M, SUPERSAMPLE, TOL = 96, 5, 3, 1e-5
QUICK = dict(N=16, M=2, supersample=1, sets=1)
NOISE = {"noise01": 0.01, "noise05": 0.05}

# scene -> list of parameter sets {path: value}; set 0 is the scene file's own values
SETS = {
    "fog-balls": [
        {"fog.scattering": 2.0, "fog.absorption": 0.5, "shape.walls.albedo": 0.7},
        {"fog.scattering": 1.2, "fog.absorption": 0.8, "shape.walls.albedo": 0.5},
        {"fog.scattering": 3.0, "fog.absorption": 0.3, "shape.walls.albedo": 0.85},
    ],
    "translucent-cube": [
        {"fog.scattering": 3.0, "fog.absorption": 1.0, "shape.ground.albedo": 0.6},
        {"fog.scattering": 2.0, "fog.absorption": 0.5, "shape.ground.albedo": 0.4},
        {"fog.scattering": 4.5, "fog.absorption": 1.5, "shape.ground.albedo": 0.75},
    ],
    "cloud-plane": [
        {"fog.scattering": 60.0, "fog.absorption": 0.6, "shape.ground.albedo": 0.6},
        {"fog.scattering": 40.0, "fog.absorption": 1.5, "shape.ground.albedo": 0.5},
        {"fog.scattering": 80.0, "fog.absorption": 3.0, "shape.ground.albedo": 0.7},
    ],
}


def seed_of(*parts: str) -> int:
    return zlib.crc32("/".join(parts).encode())


def make_scene(name: str, root: Path, N: int = N, M: int = M,
               supersample: int = SUPERSAMPLE, sets: int | None = None) -> dict:
    """Render ``name``'s sets into ``root`` (a new folder) and return its truth.json entry."""
    import jax

    import difffog as df

    scene = df.load_scene(name)
    model = df.forward_model(scene, "sweep", accuracy=None, resolution=N, M=M, tol=TOL,
                             max_iterations=2000, supersample=supersample)
    entry = {"render": {"solver": "sweep", "resolution": N, "directions": M,
                        "supersample": supersample, "tol": TOL, "jax": jax.__version__},
             "sets": []}
    for k, values in enumerate(SETS[name][:sets]):
        t = time.perf_counter()
        params = model.params()
        for path, v in values.items():
            params = df.set_param(params, scene, path, v)
        rendered = df.render(model, params)
        out = root / f"set{k}"
        out.mkdir(parents=True, exist_ok=True)
        info = {"params": values, "iterations": int(rendered.light.iterations), "images": {}}
        for cam, img in rendered.images.items():
            np.save(out / f"{cam}.npy", img.astype(np.float32))
            sig = {}
            for level, frac in NOISE.items():
                seed = seed_of(name, f"set{k}", cam, level)
                rng = np.random.default_rng(seed)
                sigma = frac * float(img.mean())
                noisy = img + rng.normal(0.0, sigma, img.shape)
                np.save(out / f"{cam}_{level}.npy", noisy.astype(np.float32))
                sig[level] = {"sigma": sigma, "seed": seed}
            info["images"][cam] = {"shape": list(img.shape), "mean": float(img.mean()), **sig}
        entry["sets"].append(info)
        print(f"{name} set{k}: {info['iterations']} iterations, "
              f"{time.perf_counter() - t:.1f} s", flush=True)
    return entry


def replace_scene(name: str, entry: dict, partial: Path, out: Path, truth: dict) -> None:
    """Put a scene's new targets (rendered into ``partial``) and its truth.json entry in place
    together, so that a run stopped part-way leaves the old targets and their truth.json entry
    (never new images under an old entry, or a scene half-rendered)."""
    truth[name] = entry
    path = out / "truth.json"
    tmp = out / "truth.json.partial"
    tmp.write_text(json.dumps(truth, indent=1, sort_keys=True))
    old = out / f".{name}.old"
    shutil.rmtree(old, ignore_errors=True)
    if (out / name).exists():
        (out / name).rename(old)
    partial.rename(out / name)
    os.replace(tmp, path)
    shutil.rmtree(old, ignore_errors=True)


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scene", action="append", choices=sorted(SETS),
                    help="only this scene (repeatable; default: all)")
    ap.add_argument("--quick", action="store_true",
                    help=f"N = {QUICK['N']}, M = {QUICK['M']}, supersample "
                         f"{QUICK['supersample']}, the first set only (needs --out)")
    ap.add_argument("--out", type=Path, default=HERE,
                    help="folder of the <scene>/set<k>/ targets and truth.json (default: here)")
    args = ap.parse_args(argv)
    if args.quick and args.out.resolve() == HERE:
        ap.error("--quick writes smaller targets than the committed ones: give --out DIR")
    kw = QUICK if args.quick else {}
    path = args.out / "truth.json"
    args.out.mkdir(parents=True, exist_ok=True)
    truth = json.loads(path.read_text()) if path.exists() else {}
    for name in args.scene or list(SETS):
        partial = args.out / f".{name}.partial"
        shutil.rmtree(partial, ignore_errors=True)
        try:
            entry = make_scene(name, partial, **kw)
        except BaseException:
            shutil.rmtree(partial, ignore_errors=True)
            raise
        replace_scene(name, entry, partial, args.out, truth)


if __name__ == "__main__":
    main()
