"""A thick fog's top inside the domain: a sharp face against a density grid's ramp.

Issue 14's cube (``difffog.study._semi_infinite.thick_cube``) without its sphere, three ways
(M = 2, the image mean against the semi-infinite conservative value 0.773):

* the fog fills the domain (its top is the domain's boundary);
* a domain 1/6 taller, the fog's ``region`` ending at z = 1 (a sharp face inside the domain);
* the same taller domain, a density grid of ones below z = 1 and zeros above (cell-centred,
  one grid cell per lattice spacing: the density ramps from the last fog node to the first
  empty one, as a cloud's top does).

In a half-space whose density varies only with depth the reflectance is that of the uniform
one, so all three should agree where the fog is thick.

    python benchmarks/thick_top.py --zeta 100 1000 --resolutions 12 24 [--first-collision deposit]

Measured 2026-11-27 (2-core CPU), fills / region / grid, since the cameras' slopes stop where
the fog does (``_model.side_slopes``): ζ = 10: 0.505 / 0.505 / 0.503 (N = 12), 0.495 / 0.495 /
0.494 (N = 24, step scheme); ζ = 100: 0.784 / 0.784 / 0.760 (N = 12), 0.784 / 0.784 / 0.765
(N = 24); ζ = 1000: 0.800 / 0.800 / 0.774 (N = 12), 0.798 / 0.798 / 0.773 (N = 24); before, the
grid was 0.866 / 0.834 / 0.925 / 0.932 at ζ = 100 and 1000 (docs/validation.md).
"""

from __future__ import annotations

import argparse
import dataclasses
import time
import warnings

import numpy as np

import difffog as df
from difffog import Domain
from difffog.study._semi_infinite import semi_infinite_value, thick_cube

VARIANTS = ("fog fills the domain", "region ends at z = 1", "grid falls to 0 above z = 1")


def scene(zeta: float, N: int, variant: str):
    """The cube and the resolution to voxelize it at (one node per 1/N of the fog's height)."""
    sc = thick_cube(zeta).replace(shapes=())
    if variant == VARIANTS[0]:
        return sc, N
    n = N + N // 6
    dom = Domain(min=(0, 0, 0), max=(1, 1, n / N))
    if variant == VARIANTS[1]:
        fog = dataclasses.replace(sc.fog, region=((0, 0, 0), (1, 1, 1)))
    else:
        g = np.ones((N, N, n))
        g[:, :, N:] = 0.0
        fog = dataclasses.replace(sc.fog, density=g)
    return dataclasses.replace(sc, domain=dom, fog=fog), n


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--zeta", nargs="+", type=float, default=[100.0, 1000.0])
    ap.add_argument("--resolutions", nargs="+", type=int, default=[12, 24])
    ap.add_argument("--first-collision", default="beam", choices=["beam", "deposit"],
                    help="SweepSolver.first_collision")
    a = ap.parse_args(argv)
    print(f"semi-infinite conservative value {semi_infinite_value():.4f}")
    for zeta in a.zeta:
        for N in a.resolutions:
            for variant in VARIANTS:
                sc, n = scene(zeta, N, variant)
                t = time.perf_counter()
                with warnings.catch_warnings():
                    warnings.simplefilter("ignore", df.ThickStepWarning)
                    m = df.forward_model(sc, "sweep", accuracy=None, resolution=n, M=2,
                                         tol=1e-4, max_iterations=2000, supersample=1,
                                         first_collision=a.first_collision)
                    out = df.render(m)
                mean = float(out.images["top"].mean())
                scheme = m.settings()["solver_options"]["scheme"]
                print(f"zeta={zeta:g} N={N} {variant:30s} mean {mean:.4f} ({scheme}, "
                      f"{time.perf_counter() - t:.0f} s)", flush=True)


if __name__ == "__main__":
    main()
