"""A fog that does not absorb: fits of γ whose truth is its bound 0.

Targets: fog-balls with γ = 0 rendered at N = 48 (noise-free and with 1% Gaussian noise of
the image mean, seeded); fits of ζ, γ and the walls' albedo at the README example's settings
(N = 28, downsample 4, ``model_error="refine"``) from ζ = 1, γ = 0.8, albedo 0.5.  Until stop
76 such a fit ran to max_steps (γ creeping towards 0 in log coordinates, "not converged", exit
status 1); now it holds γ at 0, fits the others again and states how far above 0 the images
allow γ (``fit/_bound.py``).

    PYTHONPATH=src python benchmarks/fit_at_bound.py    # writes results/fit_at_bound.md (~4 min)
"""

from __future__ import annotations

import time

import numpy as np

import _common as C
import difffog as df

TRUTH = {"fog.scattering": 2.0, "fog.absorption": 0.0, "shape.walls.albedo": 0.7}
START = {"fog.scattering": 1.0, "fog.absorption": 0.8, "shape.walls.albedo": 0.5}


def main():
    info = C.machine()
    C.print_machine(info)
    model = df.forward_model(df.load_scene("fog-balls", ["fog.absorption=0"]), "sweep",
                             resolution=48)
    clean = {k: np.asarray(v) for k, v in df.render(model).images.items()}
    rng = np.random.default_rng(1)
    rows = []
    for noise in (0.0, 0.01):
        targets = {k: (v + noise * v.mean() * rng.standard_normal(v.shape)).astype(np.float32)
                   for k, v in clean.items()}
        t0 = time.perf_counter()
        r = df.fit(df.load_scene("fog-balls"), targets, START, resolution=28, downsample=4,
                   model_error="refine")
        wall = time.perf_counter() - t0
        print(r.summary(TRUTH), flush=True)
        held = r.at_bound.get("fog.absorption", {})
        rows.append([f"{noise:.0%}", r.result, r.iterations, f"{wall:.0f}",
                     f"{r.estimates['fog.absorption']:.3g}",
                     f"{held.get('upper_95', float('nan')):.3g}",
                     f"{100 * (r.estimates['fog.scattering'] / 2.0 - 1):+.2f} ± "
                     f"{100 * r.uncertainty['fog.scattering'] / 2.0:.2f}",
                     f"{100 * (r.estimates['shape.walls.albedo'] / 0.7 - 1):+.2f} ± "
                     f"{100 * r.uncertainty['shape.walls.albedo'] / 0.7:.2f}"])
    lines = ["# Fits of γ whose truth is its bound 0 (fog-balls, γ = 0)", "",
             "`PYTHONPATH=src python benchmarks/fit_at_bound.py` (targets at N = 48; fits at "
             "N = 28, downsample 4, `model_error=\"refine\"`)", ""]
    lines += C.machine_lines(info) + [""]
    lines += C.md_table(["noise", "result", "steps", "wall s", "γ", "γ ≤ (95%)",
                         "ζ error ± total %", "walls error ± total %"], rows, "llrrrrrr")
    C.write_text(C.RESULTS / "fit_at_bound.md", "\n".join(lines) + "\n")


if __name__ == "__main__":
    main()
