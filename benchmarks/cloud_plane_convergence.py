"""How cloud-plane's images converge with the lattice: the sweep at N = 24 … 64 (M = 3, the
scene's own parameters, full-size views) against ``data_synthetic/cloud-plane/set0`` (rendered
as its truth.json says: N = 96, M = 5, supersample 3 today), the mean and RMS difference of
each view in % of the target's mean.  What a fit's model-error correction (first order in 1/N) assumes about the lattice error
can be read off the means.

    PYTHONPATH=src python benchmarks/cloud_plane_convergence.py [--sizes 24 32 48 64] [-M 3]
"""

from __future__ import annotations

import argparse
import json
import time
import warnings
from pathlib import Path

import numpy as np

import _common as C

SET0 = Path(__file__).resolve().parents[1] / "data_synthetic" / "cloud-plane" / "set0"


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    C.add_sizes(ap, [24, 32, 48, 64], [12, 16])
    ap.add_argument("-M", type=int, default=3)
    ap.add_argument("--out", default=str(C.RESULTS / "cloud_plane_convergence.md"))
    a = C.parse(ap, argv)
    info = C.machine()
    import difffog as df

    scene = df.load_scene("cloud-plane")
    target = {c: np.load(SET0 / f"{c}.npy").astype(np.float64) for c in ("top", "oblique")}
    made = json.loads((SET0.parents[1] / "truth.json").read_text())["cloud-plane"]["render"]
    rows = []
    for N in a.sizes:
        t = time.perf_counter()
        model = df.forward_model(scene, "sweep", accuracy=None, resolution=N, M=a.M, tol=1e-5,
                                 max_iterations=2000)
        with warnings.catch_warnings():  # its steps are thick at every N here (it says so)
            warnings.simplefilter("ignore", df.ThickStepWarning)
            images = model(model.params())
        cells = []
        for cam, T in target.items():
            img = np.asarray(images[cam], np.float64)
            cells += [f"{100 * (img.mean() / T.mean() - 1):+.2f}",
                      f"{100 * np.sqrt(np.mean((img - T) ** 2)) / T.mean():.2f}"]
        rows.append(f"| {N} | {a.M} | " + " | ".join(cells) + f" | {time.perf_counter() - t:.0f} |")
        print(rows[-1], flush=True)
    lines = [f"# cloud-plane's images against its N = {made['resolution']}, "
             f"M = {made['directions']} target, by lattice", "",
             "`PYTHONPATH=src python benchmarks/cloud_plane_convergence.py` (supersample 1, "
             f"tol 1e-5; the target: supersample {made['supersample']}, tol {made['tol']:g})", "",
             *C.machine_lines(info), "",
             "| N | M | top mean % | top RMS % | oblique mean % | oblique RMS % | s |",
             "|---:|---:|---:|---:|---:|---:|---:|", *rows]
    C.write_text(a.out, lines)


if __name__ == "__main__":
    main()
