"""Fit ζ, γ and the Henyey–Greenstein g of cloud-plane to images rendered at a finer setting.

The targets: cloud-plane at its own parameters (ζ = 60, γ = 0.6, g = 0.85), rendered by the
sweep at ``--target-N`` (default 64, the default preset) with the anisotropic phase
(``phase_order`` 3); the fit: from ζ × 0.7, γ × 1.5, g = 0.7 at ``--N`` (default 48), both
cameras reduced ``--downsample`` times.  Prints each estimate's error (% of the truth) with its
stated standard error, the steps and the time.

    python benchmarks/fit_anisotropic.py [--N 48] [--target-N 64] [--downsample 4]
        [--phase-order 3] [--first-collision beam|deposit] [--scheme auto|substep]
        [--model-error refine]
        [--targets data_synthetic/cloud-plane/set0]
        [--out benchmarks/results/fit_anisotropic.md]

``--targets DIR`` fits the images ``DIR/<camera>.npy`` instead of rendering targets (the scene
file's parameters are their truth: ``data_synthetic/cloud-plane/set0``, rendered at N = 96,
M = 5, is that set, finer than what a fit at N = 32 corrects its estimate to).
"""

from __future__ import annotations

import argparse
import time

import _common as C


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--N", type=int, default=48)
    ap.add_argument("--target-N", type=int, default=64)
    ap.add_argument("--M", type=int, default=3)
    ap.add_argument("--downsample", type=int, default=4)
    ap.add_argument("--phase-order", type=int, default=3)
    ap.add_argument("--set", dest="overrides", action="append", default=[],
                    help="a scene override (PATH=VALUE) of the truth, e.g. fog.scattering=20")
    ap.add_argument("--model-error", default=None,
                    help="fit(model_error=...): \"refine\" or a finer resolution")
    ap.add_argument("--first-collision", default="beam", choices=["beam", "deposit"],
                    help="SweepSolver.first_collision, of the targets and the fit")
    ap.add_argument("--scheme", default="auto", choices=["auto", "step", "linear", "substep"],
                    help="SweepSolver.scheme, of the targets and the fit")
    ap.add_argument("--targets", default=None,
                    help="a folder of <camera>.npy targets rendered at the scene file's "
                         "parameters (instead of rendering them at --target-N)")
    ap.add_argument("--out", default=None)
    a = ap.parse_args(argv)
    import difffog as df

    scene = df.load_scene("cloud-plane", a.overrides)
    p0 = df.Params.from_scene(scene)
    truth = {k: float(df.get_param(p0, scene, k))
             for k in ("fog.scattering", "fog.absorption", "fog.g")}
    t = time.perf_counter()
    if a.targets:
        import json
        from pathlib import Path

        import numpy as np

        folder = Path(a.targets)
        targets = {c.name: np.load(folder / f"{c.name}.npy") for c in scene.cameras}
        made = folder.parent.parent / "truth.json"  # data_synthetic/: its render settings
        r = json.loads(made.read_text())["cloud-plane"]["render"] if made.exists() else {}
        described = (f"the files {a.targets}/<camera>.npy" + (
            f" (sweep N = {r['resolution']}, M = {r['directions']})" if r else ""))
    else:
        targets = df.render(scene, accuracy=None, resolution=a.target_N, M=a.M,
                            phase_order=a.phase_order, first_collision=a.first_collision,
                            scheme=a.scheme).images
        described = (f"sweep N = {a.target_N}, M = {a.M}, phase_order {a.phase_order}, "
                     f"scheme {a.scheme}")
    target_s = time.perf_counter() - t
    start = {"fog.scattering": 0.7 * truth["fog.scattering"],
             "fog.absorption": 1.5 * truth["fog.absorption"], "fog.g": 0.7}
    t = time.perf_counter()
    me = a.model_error
    res = df.fit(scene, targets, start, resolution=a.N, downsample=a.downsample,
                 model_settings={"M": a.M, "phase_order": a.phase_order,
                                 "first_collision": a.first_collision, "scheme": a.scheme},
                 progress=True,
                 model_error=int(me) if me and me.isdigit() else me)
    fit_s = time.perf_counter() - t
    lines = ["# Fit of ζ, γ and g to cloud-plane (anisotropic sweep)", "",
             *C.machine_lines(C.machine(bandwidth=False)),
             f"- scene: cloud-plane {' '.join(a.overrides)}",
             f"- targets: {described} ({target_s:.0f} s); fit: N = {a.N}, phase_order "
             f"{a.phase_order}, both cameras / {a.downsample}; start ζ × 0.7, γ × 1.5, "
             f"g = 0.7; first collision {a.first_collision}, scheme {a.scheme}", "",
             "| unknown | truth | estimate | error % | stated standard error % | model error % "
             "| total uncertainty % |",
             "|---|---:|---:|---:|---:|---:|---:|"]
    for path, v in truth.items():
        est = float(res.estimates[path])
        se = res.stderr.get(path)
        se = float("nan") if se is None else float(se)
        me_p = res.model_error.get(path, float("nan"))
        tot = res.uncertainty.get(path, float("nan"))
        lines.append(f"| {path} | {v:g} | {est:.4g} | {100 * (est / v - 1):+.2f} | "
                     f"{100 * se / v:.2f} | {100 * me_p / v:.2f} | {100 * tot / v:.2f} |")
    lines += ["", f"{res.result}, {res.iterations} steps, fit {fit_s:.0f} s"]
    if res.model_error_parts:
        lines += ["", "model error parts (% of the truth): " + "; ".join(
            f"{p.split('.')[-1]} " + ", ".join(f"{k} {100 * v / truth[p]:.2f}"
                                              for k, v in parts.items())
            for p, parts in res.model_error_parts.items())]
    if res.fitted and res.fitted != res.estimates:
        lines += ["", "the fit itself (before the correction): " + ", ".join(
            f"{p.split('.')[-1]} {100 * (res.fitted[p] / truth[p] - 1):+.2f}%" for p in truth)]
    lines += [f"- warning: {w}" for w in res.warnings]
    text = "\n".join(lines)
    print(text)
    if a.out:
        with open(a.out, "w") as f:
            f.write(text + "\n")


if __name__ == "__main__":
    main()
