"""Where cloud-plane's absorption estimate γ loses its accuracy: the shift of the estimates
(ζ, γ, the ground's albedo) that each change of the sweep's settings causes, one setting at a
time, from the fit's model (N = 32, M = 3, supersample 2) to the settings the
``data_synthetic`` targets were rendered at (N = 96, M = 5, supersample 3).

For each setting s the images y_s are rendered at the truth (a parameter set of
``data_synthetic/truth.json``), and the Gauss–Newton step J⁺(targets − y_s) with the fit
model's Jacobian J at the truth (as ``--model-error refine`` steps; the unknowns in the fit's
coordinates) is, to first order, the error of a fit with the model at s to those targets
(the full-size images box-averaged to the fit's 1/4 size, as a fit does); what the last row
leaves is the supersampling's part.  The report starts with the machine
and its copy bandwidth.

    PYTHONPATH=src python benchmarks/cloud_plane_gamma_budget.py [--set 0]
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import _common as C
import numpy as np

DATA = Path(__file__).resolve().parents[1] / "data_synthetic"
CAMERAS = ("oblique", "top")
#: (label, resolution, M, supersample) from the fit's model to the targets' settings
LADDER = (("fit model", 32, 3, 2), ("the correction's model", 64, 4, 2), ("N 64 → 96", 96, 4, 2),
          ("M 4 → 5", 96, 5, 2))


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--set", type=int, default=0, help="parameter set of truth.json")
    ap.add_argument("--downsample", type=int, default=4)
    ap.add_argument("--out", default=None)
    a = ap.parse_args(argv)
    info = C.machine()
    import equinox as eqx
    import jax.numpy as jnp

    import difffog as df
    from difffog.fit import _driver as D
    from difffog.fit._residuals import FitProblem
    from difffog.fit._targets import prepare_targets
    from difffog.fit._unknowns import as_unknowns, coordinates

    truth_all = json.loads((DATA / "truth.json").read_text())["cloud-plane"]
    made = truth_all["render"]
    truth = dict(truth_all["sets"][a.set]["params"])
    scene = df.load_scene("cloud-plane")
    names = list(CAMERAS)
    rows, ys, times = [], {}, {}
    J = prob = u = fit_model = None
    for label, N, M, ss in LADDER:
        t = time.perf_counter()
        model = D.make_model(scene, "sweep", cameras=names, downsample=a.downsample,
                             resolution=N, model_settings={"M": M, "supersample": ss},
                             unknowns=3 if J is None else 0)
        base = model.params(jnp.float32)
        for p, v in truth.items():
            base = df.set_param(base, model.scene, p, v)
        if J is None:
            coords, _ = coordinates(model.scene, base, as_unknowns(list(truth)))
            prob = FitProblem(model.scene, tuple(coords), tuple(names), "linear")
            u = jnp.asarray([c.to_u(truth[c.path]) for c in coords], jnp.float32)
            y, Jm, code, *_ = eqx.filter_jit(prob.model_and_jacobian)(model, u, base)
            J, fit_model = np.asarray(Jm, np.float64), model
        else:
            y, code, *_ = eqx.filter_jit(prob.model)(model, u, base)
        assert int(code) == df.RESULTS.successful, (label, int(code))
        ys[label] = np.asarray(y, np.float64)
        times[label] = time.perf_counter() - t
        print(f"{label}: N = {N}, M = {M}, supersample {ss}: {times[label]:.0f} s", flush=True)
    tg = {c: np.load(DATA / "cloud-plane" / f"set{a.set}" / f"{c}.npy") for c in names}
    tgt, _ = prepare_targets(scene, fit_model, tg, None, a.downsample)
    label = (f"supersample 2 → 3 (the targets: N = {made['resolution']}, "
             f"M = {made['directions']}, supersample {made['supersample']})")
    ys[label] = np.concatenate([np.asarray(tgt[n], np.float64).ravel() for n in names])
    T = ys.pop(label)
    scale = float(np.sqrt(np.mean(T ** 2)))
    pinv = np.linalg.pinv(J / scale)
    prev = None
    for lab, y in ys.items():
        du = pinv @ ((T - y) / scale)
        est = {c.path: float(c.to_v(u[i] + du[i])) for i, c in enumerate(prob.coords)}
        err = {p: 100 * (est[p] / truth[p] - 1) for p in truth}
        step = {p: (err[p] - prev[p]) if prev is not None else float("nan") for p in truth}
        mean = {c: 100 * (float(np.mean(y[sl])) / float(np.mean(T[sl])) - 1)
                for c, sl in _slices(fit_model, names).items()}
        rows.append([lab] + [f"{err[p]:+.2f} ({step[p]:+.2f})" for p in truth]
                    + [f"{mean[c]:+.2f}" for c in names])
        prev = err
        print(rows[-1], flush=True)
    lines = ["# cloud-plane: what each setting does to the estimates", "",
             "`PYTHONPATH=src python benchmarks/cloud_plane_gamma_budget.py` (see its "
             "docstring)", "", *C.machine_lines(info), "",
             f"Parameter set {a.set} ({', '.join(f'{p} = {v:g}' for p, v in truth.items())}); "
             f"both views at 1/{a.downsample}; the fit model's Jacobian at the truth.  Each "
             "row: the error of the estimates a fit with that model would read from the "
             f"targets ({label}; the Gauss–Newton step J⁺(targets − model) from the truth), % "
             "of the truth, and in brackets the change from the row above, that setting's "
             "part; then each view's mean against the targets'.  What the last row leaves is "
             "the supersampling's part (and the box filter of the full-size targets).", ""]
    lines += C.md_table(["setting"] + [f"{p} %" for p in truth]
                        + [f"{c} mean %" for c in names], rows)
    lines += ["", "Render times: " + ", ".join(f"{k} {v:.0f} s" for k, v in times.items())]
    out = a.out or str(C.RESULTS / f"cloud_plane_gamma_budget_set{a.set}.md")
    C.write_text(out, lines)


def _slices(model, names):
    out, start = {}, 0
    for n in names:
        cam = next(c for c in model.cameras if c.name == n)
        out[n] = slice(start, start + cam.width * cam.height)
        start += cam.width * cam.height
    return out


if __name__ == "__main__":
    main()
