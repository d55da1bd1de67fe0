"""The sun's direction as an unknown, against independent images: fits of the sun's zenith and
azimuth with the fog's ζ and γ to the Mitsuba 3 references of fog-balls and translucent-cube
(rendered at the scene files' sun; difffog never saw them), started with the sun off by
+3° in zenith and −4° in azimuth (ζ × 0.8, γ × 1.3).  Beside each, the same fit with the sun
known (started at the scene's): what freeing the sun costs ζ and γ.

Every fit is ``difffog.fit``'s defaults but the resolution (``--resolution``, default 24),
both cameras at 1/4 width and height, ``model_error="refine"`` (the command line's default):
the estimate corrected to the doubled lattice and M + 1, its total uncertainty.  Reports the
error of each estimate (degrees for the angles, % of the truth for ζ and γ), its total
uncertainty, the rounds (each rebuilds the model at the last estimated sun) and the wall time.

    PYTHONPATH=src python benchmarks/sun_recovery.py            # ~10-15 min on 2 cores
    PYTHONPATH=src python benchmarks/sun_recovery.py --scenes fog-balls --resolution 16
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import time
from pathlib import Path

import _common as C
import difffog as df
from difffog.study.references import reference

ROOT = Path(__file__).resolve().parents[1]
ANGLES = ("sun.zenith_deg", "sun.azimuth_deg")
FOG = ("fog.scattering", "fog.absorption")
OFFSET = {"sun.zenith_deg": 3.0, "sun.azimuth_deg": -4.0}


def one(scene, targets, truth, sun_free: bool, N: int) -> dict:
    start = {"fog.scattering": 0.8 * truth["fog.scattering"],
             "fog.absorption": 1.3 * truth["fog.absorption"]}
    unknowns = dict(start)
    if sun_free:
        unknowns = {p: truth[p] + OFFSET[p] for p in ANGLES} | unknowns
        scene = scene.replace(sun=dataclasses.replace(
            scene.sun, **{p[4:]: truth[p] + OFFSET[p] for p in ANGLES}))
    t = time.perf_counter()
    res = df.fit(scene, targets, unknowns, resolution=N, downsample=4, model_error="refine")
    wall = time.perf_counter() - t
    row = {"sun": "free" if sun_free else "known", "result": res.result,
           "rounds": len(res.sun_rounds) or 1, "iterations": res.iterations,
           "time_s": round(wall, 1), "warnings": res.warnings,
           "sun_rounds": [{"sun": r["sun"], "step_deg": r["step_deg"],
                           "moved_to": {p: r["estimates"][p] for p in ANGLES if p in
                                        r["estimates"]}} for r in res.sun_rounds]}
    for p in res.paths:
        est, unc = res.estimates[p], res.uncertainty.get(p, float("nan"))
        if p in ANGLES:
            row[p] = {"error": est - truth[p], "uncertainty": unc}
        else:
            row[p] = {"error": 100 * (est / truth[p] - 1), "uncertainty": 100 * unc / truth[p]}
    return row


def cell(row, p, unit) -> str:
    if p not in row:
        return "(known)"
    e, u = row[p]["error"], row[p]["uncertainty"]
    miss = "" if abs(e) <= 3 * u else " ✗"
    return f"{e:+.2f}{unit} ± {u:.2f}{unit}{miss}"


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--scenes", nargs="+", default=["fog-balls", "translucent-cube"])
    ap.add_argument("--resolution", type=int, default=24)
    ap.add_argument("--out", type=Path, default=ROOT / "benchmarks" / "results")
    args = ap.parse_args(argv)
    info = C.machine()
    C.print_machine(info)
    rows = []
    for name in args.scenes:
        scene = df.load_scene(name)
        targets = {c.name: reference(name, c.name)[0] for c in scene.cameras}
        truth = {"fog.scattering": scene.fog.scattering, "fog.absorption": scene.fog.absorption,
                 "sun.zenith_deg": scene.sun.zenith_deg, "sun.azimuth_deg": scene.sun.azimuth_deg}
        for free in (False, True):
            r = one(scene, targets, truth, free, args.resolution)
            r["scene"] = name
            print(json.dumps(r), flush=True)
            rows.append(r)
    lines = ["# The sun's direction as an unknown", "",
             f"`PYTHONPATH=src python benchmarks/sun_recovery.py --resolution {args.resolution}`"
             f": fits to the Mitsuba 3 references (the scene files' sun, ζ, γ as truth) at "
             f"N = {args.resolution}, M = 3, both cameras at 1/4 size, "
             f"`model_error=\"refine\"`; the sun started {OFFSET['sun.zenith_deg']:+g}° in "
             f"zenith and {OFFSET['sun.azimuth_deg']:+g}° in azimuth off, ζ × 0.8, γ × 1.3. "
             "Error ± total uncertainty (1 σ); ✗: the truth outside 3 of it. Time: the wall "
             "time of `difffog.fit`, every round's compile included.", "",
             *C.machine_lines(info), "",
             "| scene | sun | zenith | azimuth | ζ | γ | rounds | steps | result | time s |",
             "|---|---|---:|---:|---:|---:|---:|---:|---|---:|"]
    for r in rows:
        lines.append(f"| {r['scene']} | {r['sun']} | {cell(r, ANGLES[0], '°')} | "
                     f"{cell(r, ANGLES[1], '°')} | {cell(r, FOG[0], '%')} | "
                     f"{cell(r, FOG[1], '%')} | {r['rounds']} | {r['iterations']} | "
                     f"{r['result']} | {r['time_s']} |")
    C.write_text(args.out / "sun_recovery.md", lines)


if __name__ == "__main__":
    main()
