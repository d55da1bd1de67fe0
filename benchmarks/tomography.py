"""Density tomography of the shared cloud-tomo case: the density grid from the Mitsuba 3 images
of its views (independent targets), started from cloud-tomo-start's uniform box.

Prints, per grid level, the lattice, the images' size, the evaluations, the loss and where the
time went (compile and evaluations), then the estimate's relative L2 error and total-mass bias
against the truth (``cloud-tomo32.npz``).  Writes the estimate and fit.json to ``--out``.

    python benchmarks/tomography.py [--views top,view0,...] [--prior 1e-3]
        [--prior-kind tv|smooth|shape] [--grids 8,16] [--resolutions 16,24,32] [--downsample 4,2,2]
        [--steps 15,15,10] [--M 3] [--rtol 1e-3] [--supersample 2] [--targets mitsuba|sweep]
        [--cloud shared|b|c|d] [--balance 0.8|off] [--scheme auto|step|linear|substep]
        [--first-collision beam|deposit]
        [--out benchmarks/results/tomography]
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import time
import warnings
from pathlib import Path

import numpy as np

import _common as C
import difffog as df
from difffog.fit._density import DENSITY_SCHEME

ROOT = Path(__file__).resolve().parent.parent


def load_case(cloud: str):
    """(name, references' folder or None for the shipped ones, start scene, true scene) of
    the shared cloud-tomo ("shared") or one of data_synthetic's ("b", "c", "d", "e")."""
    if cloud == "shared":
        return "cloud-tomo", None, df.load_scene("cloud-tomo-start"), df.load_scene("cloud-tomo")
    name, refdir = f"cloud-tomo-{cloud}", ROOT / "data_synthetic"
    return (name, refdir, df.load_scene(refdir / name / f"{name}-start.toml"),
            df.load_scene(refdir / name / f"{name}.toml"))


def ints(text):
    return tuple(int(x) for x in text.split(",")) if text else None


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--views", default="top,view0,view1,view2,view3,view4")
    ap.add_argument("--prior", type=float, default=None, help="the prior's weight")
    ap.add_argument("--prior-kind", default=None, choices=["tv", "smooth", "shape"])
    ap.add_argument("--grids", default="8,16")
    ap.add_argument("--resolutions", default=None)
    ap.add_argument("--downsample", default=None)
    ap.add_argument("--steps", default=None)
    ap.add_argument("--rtol", type=float, default=None,
                    help="a level stops when an iteration gains less than this share of its "
                         "start loss (default: fit_density's)")
    ap.add_argument("--M", type=int, default=None,
                    help="the sweep's direction half-width (default: fit_density's)")
    ap.add_argument("--supersample", type=int, default=None,
                    help="the cameras' rays per reduced pixel side (default: fit_density's)")
    ap.add_argument("--targets", default="mitsuba", choices=["mitsuba", "sweep"],
                    help="mitsuba: the shared references; sweep: rendered by the sweep at "
                         "--target-N from the truth (no noise), with the fit's scheme")
    ap.add_argument("--target-N", type=int, default=48)
    ap.add_argument("--cloud", default="shared", choices=["shared", "b", "c", "d", "e"],
                    help="shared: cloud-tomo and its Mitsuba references; b, c, d, e: the clouds "
                         "of data_synthetic/cloud-tomo-b … -e (benchmarks/cloud_b.py)")
    ap.add_argument("--balance", default=None,
                    help="the balancing principle's prior/data share (a number), or off "
                         "(default: fit_density's: on unless --prior fixes the weight)")
    ap.add_argument("--balance-rounds", type=int, default=None,
                    help="how many times the final level may rebalance the prior's weight "
                         "(default: fit_density's)")
    ap.add_argument("--first-collision", default=None, choices=["beam", "deposit"],
                    help="the light solve's first collision (SweepSolver.first_collision)")
    ap.add_argument("--scheme", default=None, choices=["auto", "step", "linear", "substep"],
                    help="the light solve's transport scheme (default: fit_density's, "
                         "DENSITY_SCHEME; auto: the sweep's choice, linear where a step "
                         "through the level's start's densest cell is optically thicker "
                         "than 1)")
    ap.add_argument("--out", default="benchmarks/results/tomography")
    args = ap.parse_args(argv)
    info = C.machine()
    C.print_machine(info)
    name, refdir, start_scene, truth_scene = load_case(args.cloud)
    truth = np.asarray(truth_scene.fog.density, np.float64)
    views = args.views.split(",")
    if args.targets == "mitsuba":
        targets = {v: np.asarray(C.reference(name, v, refdir)[0], np.float64) for v in views}
    else:
        # the fit's own scheme (its default, or --scheme), a finer lattice
        m = df.forward_model(truth_scene, "sweep", resolution=args.target_N, M=3,
                             supersample=2, accuracy=None, cameras=views,
                             scheme=args.scheme or DENSITY_SCHEME,
                             first_collision=args.first_collision or "beam")
        targets = {v: np.asarray(img, np.float64) for v, img in m().items()}
    kw = {}
    for key, val in (("resolutions", ints(args.resolutions)),
                     ("downsample", ints(args.downsample)), ("max_steps", ints(args.steps))):
        if val is not None:
            kw[key] = val
    if args.prior is not None:
        kw["prior_weight"] = args.prior
    if args.balance is not None:
        kw["balance"] = False if args.balance == "off" else float(args.balance)
    if args.balance_rounds is not None:
        kw["balance_rounds"] = args.balance_rounds
    if args.prior_kind is not None:
        kw["prior"] = args.prior_kind
    if args.supersample is not None:
        kw["supersample"] = args.supersample
    if args.M is not None:
        kw["M"] = args.M
    if args.rtol is not None:
        kw["rtol"] = args.rtol
    settings = {}
    if args.scheme is not None:
        settings["scheme"] = args.scheme
    if args.first_collision is not None:
        settings["first_collision"] = args.first_collision
    if settings:
        kw["settings"] = settings
    t0 = time.perf_counter()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", df.ThickStepWarning)
        res = df.fit_density(start_scene, targets, grids=ints(args.grids), progress=True, **kw)
    wall = time.perf_counter() - t0
    start = np.asarray(start_scene.fog.density, np.float64)
    # each pass's estimate judged by DensityFit's own measures
    per_pass = [dataclasses.replace(res, density=g) for g in res.passes]
    rows = []
    for lv in res.levels:
        rows.append([f"{lv['grid'][0]}³", lv["resolution"], f"1/{lv['downsample']}",
                     lv["steps"], f"{lv['loss']:.3g}", lv["support_cells"],
                     f"{lv['compile_s']:.0f}", f"{lv['seconds']:.0f}"])
    lines = [f"# Density tomography, {name} from {len(views)} views ({args.targets} targets)",
             "", *C.machine_lines(info), "",
             *C.md_table(["grid", "N", "images", "evaluations", "loss", "support cells",
                          "first call s (compile + 1 evaluation)", "level s"], rows), "",
             f"- relative L2 error: start {np.linalg.norm(start - truth) / np.linalg.norm(truth):.3f}"
             f" → estimate {res.relative_error(truth):.3f}",
             f"- total-mass bias: start {start.sum() / truth.sum() - 1:+.3f} → estimate "
             f"{res.mass_bias(truth):+.3f}",
             *([f"- prior weight {' → '.join(f'{w:.3g}' for w in b['prior_weights'])} "
                f"(prior/data at each pass's end {', '.join(f'{r:.2g}' for r in b['shares'])};"
                f" aim {b['target']:g})"] if (b := res.levels[-1].get("balance")) else []),
             *([f"- each pass's estimate: relative L2 error "
                f"{', '.join(f'{p.relative_error(truth):.3f}' for p in per_pass)}, mass bias "
                f"{', '.join(f'{p.mass_bias(truth):+.3f}' for p in per_pass)}"]
               if len(per_pass) > 1 else []),
             f"- result {res.result}; wall time {wall:.0f} s",
             f"- settings: {json.dumps(res.settings)}"]
    print("\n".join(lines))
    out = Path(args.out)
    res.save(out)
    C.write_text(out / "summary.md", "\n".join(lines) + "\n")


if __name__ == "__main__":
    main()
