"""Validation ladder step 3: difffog's sweep solver against the Mitsuba 3 reference images.

For every scene and camera with a Mitsuba reference (those shipped with difffog,
``difffog.study.references``, or ``--references DIR``) and every lattice setting (N nodes along
the longest axis, direction half-width M) this renders the scene with the sweep model
(``difffog.forward_model(scene, "sweep", ...)`` and ``difffog.render``) and reports, against
the Monte Carlo reference (``_common.compare``):

* ``bias``: mean(difffog) / mean(reference) − 1;
* ``rel_rmse``: RMSE / mean(reference);
* ``rel_rmse_corr``: the same with the reference's own per-pixel noise (``ref_noise_rmse`` of
  ``<camera>_stats.json``) removed in quadrature, sqrt(max(RMSE² − noise², 0)) / mean(ref);
* ``rel_rmse_s3``: RMSE / mean(ref) after a 3×3 box smoothing of both images (the reference
  noise left after smoothing is about a third of ``ref_noise_rel``; one-pixel edge offsets
  count less);
* wall times of the light solve and of the render of all the scene's cameras (one jitted call),
  compile excluded (``difffog.render`` compiles each ahead of time, then times one run), and
  the iterations.

furnace, fog-balls, ring-box and cloud-plane are what the sweep solver is meant for
(cloud-plane's strongly forward-scattering cloud, Henyey–Greenstein g = 0.85, through the
light solve's δ-M angular moments, ``SweepSolver.phase_order``).  translucent-cube is rendered
too and labelled "outside the sweep's intended use".

Writes ``references.csv``, ``references.md`` (with the machine: JAX backend and devices, copy
bandwidth, measured in the same run) and, per scene and camera, a PNG
``references_<scene>_<camera>.png`` at the best setting (lowest noise-corrected error):
difffog | Mitsuba | signed error, to ``--out`` (default ``benchmarks/results``).

    python benchmarks/validate_references.py                       # (32,3) (64,3) (64,5)
    python benchmarks/validate_references.py --full                # adds (96,3)
    python benchmarks/validate_references.py --settings 64,3 --scenes fog-balls ring-box
    python benchmarks/validate_references.py --quick --out /tmp/refs   # (16,2), fog-balls
"""

from __future__ import annotations

import argparse
import csv
import time
import warnings
from pathlib import Path

import numpy as np

import _common as C
import difffog as df

INTENDED = ("furnace", "fog-balls", "ring-box", "cloud-plane")
OUTSIDE = ("translucent-cube",)
OUTSIDE_NOTE = {
    "translucent-cube": "outside the sweep's intended use (fog box in open air, mesh ring, "
                        "two-sided quad ground)",
}
DEFAULT_SETTINGS = [(32, 3), (64, 3), (64, 5)]
FULL_EXTRA = [(96, 3)]
QUICK_SETTINGS = [(16, 2)]


def run_setting(scene_name: str, N: int, M: int, tol: float, max_iterations: int,
                phase_order="auto", scheme="auto", first_collision="beam", once_M=None):
    """Images and timings of one (N, M) setting.

    ``difffog.render`` compiles the light solve and the images ahead of time
    (``lower().compile()``) and then times one run of each, so the times exclude compilation
    without paying for a second solve.  The columns keep their names: solve = the light,
    render = the images of every camera.
    """
    scene = df.load_scene(scene_name)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        model = df.forward_model(scene, "sweep", accuracy=None, resolution=N, M=M, tol=tol,
                                 max_iterations=max_iterations, phase_order=phase_order,
                                 scheme=scheme, first_collision=first_collision,
                                 once_M=once_M)
    notes = sorted({str(w.message).split(":")[0] for w in caught})
    out = df.render(model)
    t = out.timings
    images = {k: np.asarray(v, np.float64) for k, v in out.images.items()}
    info = {
        "lattice": "x".join(str(s) for s in model.lattice.shape),
        "iterations": int(out.light.iterations),
        "error_estimate": float(out.light.error_estimate),
        "setup_s": t["voxelize_s"] + t["prepare_s"],
        "solve_compile_s": t["light_compile_s"],
        "render_compile_s": t["images_compile_s"],
        "solve_s": t["light_s"],
        "render_s": t["images_s"],
        "warnings": "; ".join(notes),
        "phase_order": model.geometry.order,
        "scheme": out.settings["solver_options"]["scheme"],
        "first_collision": first_collision,
        "once_M": model.solver.resolved_once_M(scene),
    }
    return images, info


def fmt_pct(x: float) -> str:
    return f"{100 * x:+.1f}"


def write_markdown(path: Path, rows: list[dict], settings, tol: float, machine: dict):
    lines = [
        "# difffog (sweep solver) against the Mitsuba 3 references",
        "",
        f"Settings (N, M): {', '.join(f'({n},{m})' for n, m in settings)}; SweepSolver tol = "
        f"{tol:g}; float32; supersample 2. Errors in % of the reference mean. `rmse_corr`: the "
        "reference's own noise (`noise`) removed in quadrature; `rmse_s3`: after a 3×3 box "
        "smoothing of both images (about noise/3 of reference noise left in it); `worst 5%`: "
        "the share of the squared error in the worst 5% of pixels. Times: warm "
        "(compile excluded) seconds on the machine below; `render` covers all cameras of "
        "the scene in one call."
        + ("".join(sorted({f" {r['scene']}: the sun's once-scattered light on M = "
                           f"{r['once_M']} (`--once-m`)." for r in rows if r.get("once_M")}))),
        "",
        *C.machine_lines(machine),
        "",
    ]
    lines += C.md_table(
        ["scene", "camera", "N", "M", "bias %", "rmse %", "rmse_corr %", "rmse_s3 %", "noise %",
         "worst 5%", "iters", "solve s", "render s"],
        [[r["scene"] + (" †" if r["scene"] in OUTSIDE else ""), r["camera"], r["N"], r["M"],
          fmt_pct(r["bias"]), f"{100 * r['rel_rmse']:.1f}", f"{100 * r['rel_rmse_corr']:.1f}",
          f"{100 * r['rel_rmse_s3']:.1f}", f"{100 * r['ref_noise_rel']:.1f}",
          f"{100 * r['worst5']:.0f}%", r["iterations"],
          f"{r['solve_s']:.2f}", f"{r['render_s']:.2f}"] for r in rows],
        "llrrrrrrrrrrr")
    out = sorted({r["scene"] for r in rows} & set(OUTSIDE))
    if out:
        lines += ["", "† " + "; ".join(f"{s}: {OUTSIDE_NOTE[s]}" for s in out) + "."]
    warn = sorted({(r["scene"], r["N"], r["warnings"]) for r in rows if r["warnings"]})
    if warn:
        lines += ["", "Voxelizer warnings: " + "; ".join(f"{s} N={n}: {w}" for s, n, w in warn)]
    lines += ["", "Best setting per camera (lowest rmse_corr), shown in "
              "`references_<scene>_<camera>.png`:", ""]
    best = best_rows(rows)
    for (s, c), r in best.items():
        lines.append(f"- {s}/{c}: N={r['N']}, M={r['M']}: bias {fmt_pct(r['bias'])}%, "
                     f"rmse_corr {100 * r['rel_rmse_corr']:.1f}%, rmse_s3 "
                     f"{100 * r['rel_rmse_s3']:.1f}%")
    path.write_text("\n".join(lines) + "\n")
    return "\n".join(lines)


def best_rows(rows):
    best = {}
    for r in rows:
        k = (r["scene"], r["camera"])
        if k not in best or r["rel_rmse_corr"] < best[k]["rel_rmse_corr"]:
            best[k] = r
    return best


def parse_setting(s: str) -> tuple[int, int]:
    n, m = s.split(",")
    return int(n), int(m)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--settings", nargs="+", type=parse_setting, default=None,
                    help="N,M pairs (default: 32,3 64,3 64,5; with --quick 16,2)")
    ap.add_argument("--full", action="store_true", help="also (96,3)")
    ap.add_argument("--scenes", nargs="+", default=None,
                    help="default: all five; with --quick fog-balls")
    ap.add_argument("--tol", type=float, default=1e-3)
    ap.add_argument("--max-iterations", type=int, default=400)
    ap.add_argument("--references", type=Path, default=None,
                    help="folder of the Mitsuba references (default: the shipped ones)")
    ap.add_argument("--out", type=Path, default=C.RESULTS)
    ap.add_argument("--no-png", action="store_true")
    ap.add_argument("--scheme", default="auto", choices=("auto", "step", "linear", "substep"),
                    help="SweepSolver.scheme")
    ap.add_argument("--first-collision", default="beam", choices=("beam", "deposit"),
                    help="SweepSolver.first_collision")
    ap.add_argument("--phase-order", nargs="+", default=["auto"],
                    help="SweepSolver.phase_order values to run (\"auto\" or integers)")
    ap.add_argument("--once-m", type=int, default=None,
                    help="SweepSolver.once_M: the sun's once-scattered light on this direction "
                         "set (Henyey-Greenstein scenes)")
    C.add_quick(ap)
    args = C.parse(ap, argv)
    scenes = args.scenes or (["fog-balls"] if args.quick else list(INTENDED + OUTSIDE))
    settings = list(args.settings or (QUICK_SETTINGS if args.quick else DEFAULT_SETTINGS))
    if args.full:
        settings += [s for s in FULL_EXTRA if s not in settings]
    args.out.mkdir(parents=True, exist_ok=True)
    mach = C.machine()
    C.print_machine(mach)

    rows, kept = [], {}
    orders = [o if o == "auto" else int(o) for o in args.phase_order]
    for scene in scenes:
        for (N, M), order in ((s, o) for s in settings for o in orders):
            t = time.perf_counter()
            images, info = run_setting(scene, N, M, args.tol, args.max_iterations, order,
                                       args.scheme, args.first_collision, args.once_m)
            for cam, img in images.items():
                ref, noise = C.reference(scene, cam, args.references)
                m = C.compare(img, ref, noise)
                row = {"scene": scene, "camera": cam, "N": N, "M": M, "tol": args.tol,
                       "intended": scene in INTENDED, **m, **info}
                rows.append(row)
                kept[(scene, cam, N, M)] = (img, ref)
                print(f"{scene:16s} {cam:8s} N={N:3d} M={M} L={row['phase_order']} "
                      f"bias {100 * m['bias']:+6.1f}% "
                      f"rmse_corr {100 * m['rel_rmse_corr']:5.1f}% s3 "
                      f"{100 * m['rel_rmse_s3']:5.1f}%  iters {info['iterations']:3d} "
                      f"solve {info['solve_s']:.2f}s render {info['render_s']:.2f}s "
                      f"(all {time.perf_counter() - t:.0f}s)", flush=True)

    fields = list(rows[0].keys())
    with open(args.out / "references.csv", "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=fields)
        w.writeheader()
        for r in rows:
            w.writerow({k: (f"{v:.6g}" if isinstance(v, float) else v) for k, v in r.items()})
    if not args.no_png:
        for (s, c), r in best_rows(rows).items():
            img, ref = kept[(s, c, r["N"], r["M"])]
            C.save_comparison_png(args.out / f"references_{s}_{c}.png", s, c, img, ref,
                                  f"N={r['N']}, M={r['M']}", r,
                                  C.reference(s, c, args.references)[1])
    print()
    print(write_markdown(args.out / "references.md", rows, settings, args.tol, mach))


if __name__ == "__main__":
    main()
