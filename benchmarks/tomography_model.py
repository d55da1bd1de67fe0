"""How close the sweep renders the true cloud-tomo cloud, per lattice resolution N and direction
half-width M, against the Mitsuba 3 images, and where its light is off: the forward model's
own error, which a density fit cannot get below.

Prints, for each ``N:M[:scheme]`` (scheme default step), the relative RMS difference (RMS of the difference over the RMS of
the targets, all six views) of the truth's images (full size, 2² rays per pixel, step scheme,
then averaged 2×2 as the fit's final level sees them) from the Mitsuba images, and between
the settings; then the collided fluence Λ of the light solve at the cloud's cells (its nodes
interpolated to the cell centres) against the finest setting's, by depth below the cloud's
surface.

    python benchmarks/tomography_model.py [--cloud shared|b]
        [--settings 32:3,48:3,64:3,96:3,32:2,48:2] [--first-collision beam|deposit]
"""

from __future__ import annotations

import argparse
import time
import warnings

import numpy as np
from scipy.ndimage import distance_transform_edt, map_coordinates

import _common as C
import difffog as df
from difffog.fit._targets import _block_mean
from tomography import load_case

VIEWS = ["top", "view0", "view1", "view2", "view3", "view4"]


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cloud", default="shared", choices=["shared", "b"])
    ap.add_argument("--settings", default="32:3,48:3,64:3,96:3,32:2,48:2")
    ap.add_argument("--first-collision", default="beam", choices=["beam", "deposit"],
                    help="the light solve's first collision (SweepSolver.first_collision)")
    args = ap.parse_args(argv)
    C.print_machine(C.machine())
    name, refdir, _, truth_scene = load_case(args.cloud)
    rho = np.asarray(truth_scene.fog.density, np.float64)
    n = rho.shape[0]
    refs = {v: C.reference(name, v, refdir) for v in VIEWS}  # (image, noise RMSE)
    T = {v: _block_mean(refs[v][0], 2) for v in VIEWS}
    bright = np.sqrt(np.mean(np.concatenate([T[v].ravel() for v in VIEWS]) ** 2))
    cells = np.argwhere(rho > 0.02)
    depth = distance_transform_edt(rho > 0.05)[tuple(cells.T)]
    centres = (cells + 0.5) / n  # the unit domain of both clouds
    imgs, flu = {}, {}
    for spec in args.settings.split(","):
        N, M, *rest = spec.split(":")  # N:M[:scheme]
        N, M, scheme = int(N), int(M), (rest[0] if rest else "step")
        t0 = time.perf_counter()
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", df.ThickStepWarning)
            m = df.forward_model(truth_scene, "sweep", resolution=N, M=M, supersample=2,
                                 accuracy=None, cameras=VIEWS, scheme=scheme,
                                 first_collision=args.first_collision)
            p = m.params()
            light = m.light(p)
            imgs[spec] = {v: _block_mean(np.asarray(i, np.float64), 2)
                          for v, i in m.images_from(light, p).items()}
        u = (centres - np.asarray(light.origin)) / float(light.h) - 0.5
        flu[spec] = map_coordinates(np.asarray(light.fluence, np.float64), u.T, order=1)
        d = np.concatenate([(imgs[spec][v] - T[v]).ravel() for v in VIEWS])
        print(f"N = {N}, M = {M}, {scheme} (M·h = 1/{N / M:.0f}): {np.sqrt(np.mean(d ** 2)) / bright:.2%} "
              f"from Mitsuba ({time.perf_counter() - t0:.0f} s)", flush=True)
    specs = list(imgs)
    print("\nbetween settings (relative RMS of the difference):")
    for i, a in enumerate(specs):
        for b in specs[i + 1:]:
            d = np.concatenate([(imgs[a][v] - imgs[b][v]).ravel() for v in VIEWS])
            print(f"  {a} vs {b}: {np.sqrt(np.mean(d ** 2)) / bright:.2%}")
    ref = max(specs, key=lambda s: (int(s.split(":")[0]) / int(s.split(":")[1]),
                                    s.endswith("substep")))
    print(f"\ncollided fluence Λ at the cloud's cells against {ref}'s, by depth in cells below "
          f"the cloud's surface (density > 0.05):")
    bands = [(depth >= lo) & (depth < hi) for lo, hi in ((0, 1.5), (1.5, 2.5), (2.5, np.inf))]
    for s in specs:
        if s == ref:
            continue
        parts = [f"{flu[s][b].mean() / flu[ref][b].mean():.3f}" for b in bands]
        print(f"  {s}: depth < 1.5: {parts[0]}, 1.5-2.5: {parts[1]}, > 2.5: {parts[2]}")
    print(f"\n(the targets' noise at this size: about "
          f"{np.sqrt(np.mean([refs[v][1] ** 2 for v in VIEWS])) / 2 / bright:.2%})")


if __name__ == "__main__":
    main()
