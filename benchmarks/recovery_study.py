"""Recovery study: how well ``difffog.fit`` recovers ζ, γ and an albedo from images.

For each scene (fog-balls, translucent-cube, cloud-plane) it fits the three unknowns
fog.scattering, fog.absorption and the albedo of the largest surface (walls / ground) with
Levenberg–Marquardt at fit resolution N (default 24), M = 3, both cameras at 1/4 width and
height (32×32 and 40×30 pixels), from a start away from the truth (ζ × 0.6, γ × 1.6,
albedo − 0.15), to these targets:

* ``crime``: the fit's own model at the truth (the "inverse crime": a sanity check only);
* ``hires``: ``data_synthetic/`` noise-free (N = 96, M = 5; N = 48, M = 4 before stop 59: the
  `targets` column), every parameter set;
* ``noise01`` / ``noise05``: the same with 1% / 5% Gaussian noise (set 0);
* ``mc``: the Mitsuba 3 references shipped with difffog (``difffog.study.references``, or
  ``--references DIR``) with the scene file's parameters as truth (their own noise ≈ 2–6% per
  pixel).

and reports the relative error of each unknown, its stated standard error (relative), the
iterations and the wall time (compile of the first fit of a scene included in that fit only),
plus ``misfit_truth``: the image RMS of the fit's model *at the true parameters* against the
target, relative to the target mean — the model bias that no fit can remove.  ``--resolutions``
repeats the hires and mc fits at other N to show how that bias, and the error, change with N.

    PYTHONPATH=src python benchmarks/recovery_study.py                    # ~30-60 min, 2 cores
    PYTHONPATH=src python benchmarks/recovery_study.py --scenes fog-balls --resolutions 16 24 32
    PYTHONPATH=src python benchmarks/recovery_study.py --quick --out /tmp/recovery

(``--quick``: fog-balls, N = 12, the crime and mc cases, at most 3 steps per fit.)  One model
per scene and N (``_common.fit_model``: the public ``difffog.forward_model`` at the registry's
fit defaults) serves all of its fits (``difffog.fit(..., forward=model)``).  Writes
``recovery.csv`` and ``recovery.md`` to ``--out`` (default ``benchmarks/results``), appending
rows of new settings to an existing CSV, replacing rows with the same scene/case/set/N; the
markdown names the machine of the latest run (JAX backend and devices, copy bandwidth).
"""

from __future__ import annotations

import argparse
import csv
import json
import os
import time
import warnings
from pathlib import Path

import numpy as np

import _common as C
import difffog as df

ROOT = Path(__file__).resolve().parents[1]
DATA = ROOT / "data_synthetic"
SURFACE = {"fog-balls": "walls", "translucent-cube": "ground", "cloud-plane": "ground"}
CAMERAS = ["top", "oblique"]
FIELDS = ["scene", "case", "set", "N", "M", "unknown", "truth", "estimate", "rel_error_pct",
          "rel_stderr_pct", "covered_2se", "iterations", "result", "time_s", "misfit_truth_pct",
          "residual_rms_pct", "load", "rel_model_error_pct", "rel_uncertainty_pct", "covered_3u",
          "edge_weight", "refine_steps", "targets"]

#: the lattice of data_synthetic/'s targets before stop 59 (rows written before "targets" was
#: a column: their synthetic cases were fit to these)
OLD_TARGETS = "N48 M4"


def targets_of(case: str, render: dict | None) -> str:
    """What a case's targets are: the synthetic sets' lattice ("N96 M5", from truth.json's
    "render"), "Mitsuba 3", or the fit's own model ("crime")."""
    if case == "mc":
        return "Mitsuba 3"
    if case == "crime":
        return "own model"
    return f"N{render['resolution']} M{render['directions']}" if render else OLD_TARGETS


def _targets(r) -> str:
    """A row's targets (rows written before it was a column: see ``OLD_TARGETS``)."""
    return r.get("targets") or targets_of(r["case"], None)


def _ew(r) -> float:
    """A row's edge weight (rows written before it was a setting: 1)."""
    return float(r.get("edge_weight") or 1.0)


def start_of(truth: dict) -> dict:
    out = {}
    for p, v in truth.items():
        if p == "fog.scattering":
            out[p] = 0.6 * v
        elif p == "fog.absorption":
            out[p] = 1.6 * v
        else:
            out[p] = max(0.05, v - 0.15)
    return out


def misfit(fwd, scene, truth, targets, downsample) -> float:
    """Image RMS of the model at the truth against the (reduced) targets, % of their mean."""
    p = fwd.params()
    for k, v in truth.items():
        p = df.set_param(p, fwd.scene, k, v)
    imgs = fwd(p)
    num, den, cnt = 0.0, 0.0, 0
    for name, tgt in targets.items():
        t = np.asarray(tgt, np.float64)
        model = np.asarray(imgs[name], np.float64)
        if t.shape != model.shape:  # a reduced pixel is the mean of k×k full ones
            k = t.shape[0] // model.shape[0]
            t = t.reshape(t.shape[0] // k, k, t.shape[1] // k, k).mean(axis=(1, 3))
        num += float(np.sum((model - t) ** 2))
        den += float(np.sum(t))
        cnt += t.size
    return 100 * np.sqrt(num / cnt) / (den / cnt)


def run_case(fwd, scene, case, k, truth, targets, N, M, downsample, rows, load, max_steps,
             model_error=None, edge_weight=1.0, refine_steps=4, made=""):
    t = time.perf_counter()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", df.IdentifiabilityWarning)
        res = df.fit(scene, targets, start_of(truth), forward=fwd, downsample=downsample,
                     max_steps=max_steps, model_error=model_error, edge_weight=edge_weight,
                     refine_steps=refine_steps,
                     callback=lambda e: print(
                         f"    step {e['step']}: loss {e['loss']:.4g} at {e['time_s']:.0f} s",
                         flush=True))
    wall = time.perf_counter() - t
    mis = misfit(fwd, scene, truth, targets, downsample)
    mean = np.mean([np.mean(v) for v in res.targets.values()])
    for p, v in truth.items():
        est, se = res.estimates[p], res.stderr[p]
        me = res.model_error.get(p, float("nan"))
        tot = res.uncertainty.get(p, se)
        rows.append({
            "rel_model_error_pct": 100 * me / v, "rel_uncertainty_pct": 100 * tot / v,
            "covered_3u": bool(abs(est - v) <= 3 * tot),
            "scene": scene.title, "case": case, "set": k, "N": N, "M": M, "unknown": p,
            "truth": v, "estimate": est, "rel_error_pct": 100 * (est - v) / v,
            "rel_stderr_pct": 100 * se / v, "covered_2se": bool(abs(est - v) <= 2 * se),
            "iterations": res.iterations, "result": res.result, "time_s": round(wall, 1),
            "edge_weight": edge_weight, "targets": made,
            # (no correction where it failed: the model error is then NaN and the ladder short)
            "refine_steps": res.ladder[1].get("steps", "") if len(res.ladder) > 1 else "",
            "misfit_truth_pct": round(mis, 3),
            "residual_rms_pct": round(float(100 * res.residual_rms / mean), 3), "load": load,
        })
    print(f"{scene.title:17s} {case:8s} set{k} N={N}: {res.result} in {res.iterations} steps, "
          f"{wall:.0f} s; errors % " + " ".join(
              f"{p.split('.')[-1]}={100 * (res.estimates[p] / v - 1):+.2f}±"
              f"{100 * res.stderr[p] / v:.2f}" for p, v in truth.items())
          + f"; misfit at truth {mis:.2f}%", flush=True)


def study(scene_name, N, M, downsample, cases, rows, all_sets=True, max_steps=40,
          refdir=None, model_error=None, edge_weight=1.0, refine_steps=4):
    truth_all = json.loads((DATA / "truth.json").read_text())[scene_name]
    scene = df.load_scene(scene_name)
    fwd = C.fit_model(scene, CAMERAS, N, M, downsample)
    load = round(os.getloadavg()[0], 1)
    sets = truth_all["sets"]
    for case in cases:
        ks = [0] if case != "hires" else (range(len(sets)) if all_sets else [0])
        for k in ks:
            truth = dict(sets[k]["params"])
            if case == "crime":
                p = fwd.params()
                for a, v in truth.items():
                    p = df.set_param(p, fwd.scene, a, v)
                targets = {c: np.asarray(v) for c, v in fwd(p).items()}
            elif case == "mc":
                sc = df.load_scene(scene_name)
                truth = {a: float(df.get_param(df.Params.from_scene(sc), sc, a)) for a in truth}
                targets = {c: C.reference(scene_name, c, refdir)[0] for c in CAMERAS}
            else:
                suffix = "" if case == "hires" else f"_{case}"
                targets = {c: np.load(DATA / scene_name / f"set{k}" / f"{c}{suffix}.npy")
                           for c in CAMERAS}
            run_case(fwd, scene, case, k, truth, targets, N, M, downsample, rows, load,
                     max_steps, model_error, edge_weight, refine_steps,
                     made=targets_of(case, truth_all["render"]))


def write(rows, out: Path, info: dict):
    out.mkdir(parents=True, exist_ok=True)
    path = out / "recovery.csv"
    old = []
    if path.exists():
        with path.open() as f:
            old = list(csv.DictReader(f))
    key = lambda r: (r["scene"], r["case"], str(r["set"]), str(r["N"]), _ew(r),  # noqa: E731
                     _targets(r), r["unknown"])
    new_keys = {key(r) for r in rows}
    merged = [r for r in old if key(r) not in new_keys] + rows
    with path.open("w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=FIELDS)
        w.writeheader()
        for r in merged:
            w.writerow({k: r.get(k) for k in FIELDS})
    lines = ["# Recovery study", "",
             "`PYTHONPATH=src python benchmarks/recovery_study.py` — relative error of each "
             "estimate and its stated standard error (both % of the truth), LM from ζ×0.6, "
             "γ×1.6, albedo−0.15; both cameras at 1/4 size; M = 3. `misfit@truth`: image RMS "
             "of the fit's model at the true parameters, % of the target mean (model bias + "
             "target noise). `load`: 1-min load average when the scene started. `steps`: the fit's, "
             "+ the renders of the finer model its correction took (`--model-error refine`; "
             "rows before stop 58: one).", "",
             "Machine of the latest run:", "", *C.machine_lines(info), "",
             "| scene | case | set | N | ζ error % (±se) | γ error % (±se) | albedo error % "
             "(±se) | steps | result | time s | misfit@truth % | residual % | load |",
             "|---|---|---:|---:|---:|---:|---:|---:|---|---:|---:|---:|---:|"]
    made = {targets_of("hires", v.get("render"))
            for v in json.loads((DATA / "truth.json").read_text()).values()}
    current = made.pop() if len(made) == 1 else None  # rows fit to other targets say so
    if current:
        lines[-2:-2] = [f"Synthetic targets (`hires`, `noise01`, `noise05`): `data_synthetic/` "
                        f"as rendered now, {current.replace('N', 'N = ').replace(' M', ', M = ')}"
                        "; rows fit to earlier targets name theirs.", ""]
    groups = {}
    for r in merged:
        case = r["case"] + (f" (edge weight {_ew(r):g})" if _ew(r) != 1.0 else "")
        if r["case"] not in ("mc", "crime") and _targets(r) != current:
            case += f" (targets {_targets(r)})"
        groups.setdefault((r["scene"], case, str(r["set"]), str(r["N"])), []).append(r)
    order = {"crime": 0, "hires": 1, "noise01": 2, "noise05": 3, "mc": 4}
    for (sc, case, k, N), rs in sorted(groups.items(), key=lambda kv: (
            kv[0][0], int(kv[0][3]), order.get(kv[0][1].split()[0], 9), kv[0][1], kv[0][2])):
        cells = []
        for prefix in ("fog.scattering", "fog.absorption", "albedo"):
            r = next(x for x in rs if x["unknown"].startswith(prefix) or
                     x["unknown"].endswith(prefix))
            tiny = abs(float(r["rel_error_pct"])) < 0.01
            u = r.get("rel_uncertainty_pct")
            with_model = u not in (None, "", "nan") and str(r.get("rel_model_error_pct")) not in (
                "", "nan", "None")
            if with_model:  # the total uncertainty (noise and the model's own error)
                mark = "" if str(r["covered_3u"]) == "True" or tiny else " ✗"
                cells.append(f"{float(r['rel_error_pct']):+.2f} (±{float(r['rel_stderr_pct']):.2f}"
                             f"; total ±{float(u):.2f}){mark}")
            else:
                mark = "" if str(r["covered_2se"]) == "True" or tiny else " ✗"
                cells.append(f"{float(r['rel_error_pct']):+.2f} "
                             f"(±{float(r['rel_stderr_pct']):.2f}){mark}")
        r0 = rs[0]
        fine = str(r0.get("refine_steps") or "")  # renders of the correction's finer model
        lines.append(f"| {sc} | {case} | {k} | {N} | " + " | ".join(cells) +
                     f" | {r0['iterations']}{' + ' + fine if fine else ''} | {r0['result']} | {r0['time_s']} | "
                     f"{float(r0['misfit_truth_pct']):.2f} | {float(r0['residual_rms_pct']):.2f} | "
                     f"{r0['load']} |")
    lines += ["", "✗: the truth lies outside ±2 stated standard errors (the standard error "
              "measures noise, not model bias), or, where a total uncertainty is given "
              "(`--model-error refine`: noise and the model's own error), outside ±3 of it."]
    C.write_text(out / "recovery.md", lines)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scenes", nargs="+", default=None,
                    help="default fog-balls translucent-cube cloud-plane; with --quick fog-balls")
    C.add_sizes(ap, [24], [12], flag="--resolutions", what="fit resolutions N")
    ap.add_argument("--cases", nargs="+", default=None,
                    help="default crime hires noise01 noise05 mc; with --quick crime mc")
    ap.add_argument("-M", type=int, default=3)
    ap.add_argument("--downsample", type=int, default=4)
    ap.add_argument("--max-steps", type=int, default=None,
                    help="per fit (default 40; with --quick 3)")
    ap.add_argument("--set0-only", action="store_true",
                    help="hires: fit parameter set 0 only (not all sets)")
    ap.add_argument("--references", type=Path, default=None,
                    help="folder of the Mitsuba references (default: the shipped ones)")
    ap.add_argument("--out", type=Path, default=C.RESULTS, help="folder of the reports")
    ap.add_argument("--model-error", default=None,
                    help="fit(model_error=...): \"refine\" (or a finer resolution) adds the "
                         "model's own error to each estimate's uncertainty")
    ap.add_argument("--refine-steps", type=int, default=4,
                    help="fit(refine_steps=...): the most renders of the finer model the "
                         "correction takes (default 4; 1: one Gauss-Newton step)")
    ap.add_argument("--edge-weight", type=float, default=1.0,
                    help="fit(edge_weight=...): the weight of pixels that straddle a geometric "
                         "or a shadow edge (default 1: as any pixel)")
    args = C.parse(ap, argv)
    scenes = args.scenes or (["fog-balls"] if args.quick else
                             ["fog-balls", "translucent-cube", "cloud-plane"])
    cases = args.cases or (["crime", "mc"] if args.quick else
                           ["crime", "hires", "noise01", "noise05", "mc"])
    max_steps = args.max_steps or (3 if args.quick else 40)
    info = C.machine()
    C.print_machine(info)
    for name in scenes:
        for N in args.resolutions:
            rows = []
            me = args.model_error
            study(name, N, args.M, args.downsample, cases, rows, not args.set0_only, max_steps,
                  args.references, int(me) if me and me.isdigit() else me, args.edge_weight,
                  args.refine_steps)
            write(rows, args.out, info)  # after every scene, so a killed run keeps its rows


if __name__ == "__main__":
    main()
