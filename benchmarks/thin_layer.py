"""What a camera sees of a thin fog layer across a periodic domain, against the exact slab.

A layer of fog z ∈ [0.25, 0.75] of a periodic-xy unit domain (vertical optical depth τ,
albedo a), a sun at zenith θ₀, no sky, an orthographic camera looking straight down: its image
is the slab's reflected radiance at μ = 1.  The exact value comes from the slab's transfer
equation iterated to convergence on ``--cells`` cells × ``--mu`` Gauss–Legendre μ (the sun's
first collision as a source, its single scattering towards the camera exact).  The lattice's
horizontal directions never leave such a layer, so difffog's multiply scattered light comes
out too large (docs/validation.md; ``ThinLayerWarning``).

Writes ``thin_layer.md`` to ``--out`` (default ``benchmarks/results``), the machine last.

    python benchmarks/thin_layer.py                         # τ 0.01 0.1 0.3 0.5 1, N 32, M 2
    python benchmarks/thin_layer.py --taus 0.1 --m 2 3 5
    python benchmarks/thin_layer.py --quick --out /tmp/thin  # τ 0.1, N 12, coarse exact
"""

from __future__ import annotations

import argparse
import math
import warnings
from pathlib import Path

import numpy as np

import _common as C


def exact_radiance(tau, albedo, mu0, cells=400, n_mu=200, tol=1e-13, max_iterations=500):
    """(I(μ = 1) at the slab's top, its single-scattering part) for a sun of irradiance 1."""
    x, w = np.polynomial.legendre.leggauss(n_mu)
    mu, wmu = 0.5 * (x + 1.0), 0.5 * w
    dt = tau / cells
    depth = (np.arange(cells) + 0.5) * dt
    sun = np.exp(-depth / mu0) * (-np.expm1(-dt / mu0)) / (dt / mu0)  # cell mean of the beam
    e = np.exp(-dt / mu)[:, None]
    phi = (-np.expm1(-dt / mu) / (dt / mu))[:, None]
    lam = np.zeros(cells)
    for _ in range(max_iterations):
        q = albedo * (lam + sun) / (4 * math.pi)
        up, down = np.zeros((n_mu, cells)), np.zeros((n_mu, cells))
        r = np.zeros(n_mu)
        for k in range(cells - 1, -1, -1):  # upwards from the bottom
            up[:, k] = q[k] + (r - q[k]) * phi[:, 0]
            r = q[k] + (r - q[k]) * e[:, 0]
        r = np.zeros(n_mu)
        for k in range(cells):  # downwards from the top
            down[:, k] = q[k] + (r - q[k]) * phi[:, 0]
            r = q[k] + (r - q[k]) * e[:, 0]
        new = 2 * math.pi * (wmu[:, None] * (up + down)).sum(0)
        done = np.max(np.abs(new - lam)) < tol
        lam = new
        if done:
            break
    q_ms = albedo * lam / (4 * math.pi)
    multiple = float(np.sum(q_ms * (-math.expm1(-dt)) * np.exp(-(depth - dt / 2))))
    single = albedo / (4 * math.pi) * mu0 / (mu0 + 1) * (1 - math.exp(-tau * (1 / mu0 + 1)))
    return multiple + single, single


def haze(tau, albedo, zenith, boundary="periodic-xy"):
    from difffog.scene._description import Camera, Domain, Fog, Scene, Sun

    return Scene(
        title="haze", domain=Domain((0, 0, 0), (1, 1, 1), boundary),
        fog=Fog(scattering=albedo * tau / 0.5, absorption=(1 - albedo) * tau / 0.5,
                region=((0, 0, 0.25), (1, 1, 0.75))),
        sun=Sun(1.0, zenith, 0.0),
        cameras=(Camera("top", "orthographic", (0.5, 0.5, 2.0), (0.5, 0.5, 0.0), up=(0, 1, 0),
                        resolution=(8, 8), extent=(0.5, 0.5)),))


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--taus", type=float, nargs="+", default=[0.01, 0.1, 0.3, 0.5, 1.0])
    ap.add_argument("--albedo", type=float, default=0.999)
    ap.add_argument("--zenith", type=float, default=0.0)
    ap.add_argument("--n", type=int, nargs="+", default=[32])
    ap.add_argument("--m", type=int, nargs="+", default=[2])
    ap.add_argument("--cells", type=int, default=400)
    ap.add_argument("--mu", type=int, default=200)
    ap.add_argument("--quick", action="store_true", help="τ 0.1, N 12, a coarse exact value")
    ap.add_argument("--out", type=Path, default=C.RESULTS)
    a = ap.parse_args(argv)
    if a.quick:
        a.taus, a.n, a.cells, a.mu = [0.1], [12], 100, 48

    import difffog as df

    mu0 = math.cos(math.radians(a.zenith))
    rows = []
    for tau in a.taus:
        exact, single = exact_radiance(tau, a.albedo, mu0, a.cells, a.mu)
        for m in a.m:
            for n in a.n:
                model = df.forward_model(haze(tau, a.albedo, a.zenith), "sweep", accuracy=None,
                                         resolution=n, M=m, tol=1e-8, supersample=1)
                with warnings.catch_warnings(record=True) as said:
                    warnings.simplefilter("always")
                    out = df.render(model)
                warned = any(issubclass(w.category, df.ThinLayerWarning) for w in said)
                img = float(np.asarray(out.images["top"], np.float64).mean())
                rows.append((tau, n, m, img, exact, single, warned))
                print(f"τ={tau:<5g} N={n} M={m}: image {img:.5f}, exact {exact:.5f} "
                      f"({100 * (img / exact - 1):+.2f}%), multiply scattered share "
                      f"{100 * (1 - single / exact):.1f}%, warned: {warned}", flush=True)
    lines = [
        "# A thin fog layer across a periodic domain: the image against the exact slab",
        "",
        f"Albedo {a.albedo:g}, sun at zenith {a.zenith:g}°, the layer z ∈ [0.25, 0.75] of a "
        "periodic unit domain, an orthographic camera looking down; exact: the slab's transfer "
        f"equation on {a.cells} cells × {a.mu} μ.  `python benchmarks/thin_layer.py` (module "
        "docstring).",
        "",
        *C.md_table(["τ", "N", "M", "image", "exact", "error", "multiply scattered share",
                     "ThinLayerWarning"],
                    [[f"{t:g}", n, m, f"{i:.5f}", f"{e:.5f}", f"{100 * (i / e - 1):+.2f}%",
                      f"{100 * (1 - s / e):.1f}%", "yes" if wd else "no"]
                     for t, n, m, i, e, s, wd in rows]),
        "", "## Machine", "", *C.machine_lines(C.machine()),
    ]
    print("wrote", C.write_text(a.out / "thin_layer.md", "\n".join(lines) + "\n"))


if __name__ == "__main__":
    main()
