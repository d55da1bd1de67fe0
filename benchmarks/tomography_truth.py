"""What the images can tell: the true density's own misfit to the Mitsuba 3 targets, and how
much the density fit's data term changes when the truth is scaled, clipped or blurred.

For each lattice / image reduction / rays-per-pixel setting, the density fit's level loss
(``fit._density.level_loss``: the images' relative mean squared misfit, the same program the
fit evaluates) at the truth and at altered truths.  An alteration whose data term is within
the truth's own misfit (the forward model's error plus the targets' noise) cannot be told
from the truth by the images: only the prior can.

    python benchmarks/tomography_truth.py [--cloud shared|b] [--settings 32:2:2,32:2:4,48:2:4]
        [--scheme auto|step|linear]

(``N:downsample:supersample``).
"""

from __future__ import annotations

import argparse
import time
import warnings

import jax.numpy as jnp
import numpy as np
from scipy.ndimage import gaussian_filter

import _common as C
import difffog as df
from difffog.fit import _density as D
from tomography import load_case

VIEWS = ["top", "view0", "view1", "view2", "view3", "view4"]


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cloud", default="shared", choices=["shared", "b"])
    ap.add_argument("--settings", default="32:2:2,32:2:4,48:2:4")
    ap.add_argument("--scheme", default=None, choices=["auto", "step", "linear"],
                    help="the light solve's scheme (default: the density fit's, "
                         "DENSITY_SCHEME; auto is judged at the start box's density, 0.25, "
                         "which is the step scheme at N >= 32, where the fit's finer levels "
                         "would start denser and take the linear one)")
    args = ap.parse_args(argv)
    C.print_machine(C.machine())
    name, refdir, start, truth_scene = load_case(args.cloud)
    truth = np.asarray(truth_scene.fog.density, np.float64)
    seed = np.asarray(start.fog.density, np.float64)
    targets = {v: C.reference(name, v, refdir)[0] for v in VIEWS}
    alts = {"truth": truth, "truth × 0.9": 0.9 * truth, "truth × 1.1": 1.1 * truth,
            "truth clipped at 0.64 of its peak": np.minimum(truth, 0.64 * truth.max()),
            "truth blurred (Gaussian, σ = 0.7 cells)": gaussian_filter(truth, 0.7) * (seed > 0)}
    rows = []
    for spec in args.settings.split(","):
        n, ds, ss = (int(v) for v in spec.split(":"))
        t0 = time.perf_counter()
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", df.ThickStepWarning)
            loss, x0, _, _ = D.level_loss(start, targets, seed, n, ds, 0.0, 3, ss,
                                          None if args.scheme is None
                                          else {"scheme": args.scheme})
        idx = np.asarray(loss.support)
        out = []
        for g in alts.values():
            x = jnp.asarray(np.log(np.maximum(g.reshape(-1)[idx], 1e-13)), x0.dtype)
            (_, (data, _, code, _)), _ = D._value_and_grad(x, loss)
            if int(code) != 0:
                raise SystemExit(f"{spec}: the light solve did not converge")
            out.append(float(data))
        rows.append([f"{n}", f"1/{ds}", f"{ss}²",
                     *[f"{v:.3g} ({np.sqrt(2 * v):.1%})" for v in out],
                     f"{time.perf_counter() - t0:.0f}"])
        print(rows[-1], flush=True)
    print(f"\n# {name}: the data term (½ relative mean squared misfit; its RMS in brackets)\n")
    print("\n".join(C.md_table(["N", "images", "rays per pixel", *alts, "s"], rows)))


if __name__ == "__main__":
    main()
