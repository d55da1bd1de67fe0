"""The cost model (``difffog.estimate``) against what renders measure: peak memory, time per
light iteration and set-up, in a fresh process per row.

    python benchmarks/bench_cost.py                               # sweep N 32 64 96, M 2 3 5; splat
    python benchmarks/bench_cost.py --sizes 32 64 128 --ms 2 3 5
    python benchmarks/bench_cost.py --quick --out /tmp/cost       # N 16, M 2

Each row runs ``difffog render <scene> -N N -M M --iterations K --force`` in a new process (so
the peak resident memory is that render's alone) and reads its report.json: the measured peak
(ru_maxrss), the light solve's time over its K iterations (compilation apart) and the set-up
(voxelize + prepare + camera hits); the estimate is ``difffog.estimate`` with the same
settings (what the render recorded in report.json before building anything).  Writes cost.md (with the machine: backend, copy bandwidth measured in the same run)
and cost.csv to ``--out`` (default benchmarks/results).
"""

from __future__ import annotations

import argparse
import csv
import json
import subprocess
import sys
import tempfile
from pathlib import Path

import _common as C
import difffog as df


def run_row(scene: str, solver: str, N: int, M: int | None, iterations: int) -> dict | None:
    with tempfile.TemporaryDirectory() as tmp:
        cmd = [sys.executable, "-m", "difffog", "render", scene, "--solver", solver,
               "-N", str(N), "--out", str(Path(tmp) / "out"), "-q", "--force"]
        if solver == "sweep":
            cmd += ["-M", str(M), "--iterations", str(iterations)]
        p = subprocess.run(cmd, capture_output=True, text=True)
        rep_path = Path(tmp) / "out" / "report.json"
        if not rep_path.exists():
            print(f"{solver} N={N} M={M}: failed ({p.returncode}): {p.stderr.strip()[-300:]}")
            return None
        rep = json.loads(rep_path.read_text())
    t = rep["timings_s"]
    setup = sum(t.get(k, 0.0) for k in ("voxelize_s", "prepare_s", "camera_hits_s", "setup_s"))
    k = max(int(rep.get("iterations", 1)), 1)
    per_iter = t.get("light_s", 0.0) / k if solver == "sweep" else None
    row = with_estimate(dict(scene=scene, solver=solver, N=N, M=M or "",
                             peak_mb=round(rep["peak_memory_mb"]),
                             s_per_iter=None if per_iter is None else round(per_iter, 4),
                             setup_s=round(setup, 2)))
    print(row, flush=True)
    return row


def with_estimate(row: dict) -> dict:
    """The measured row with ``difffog.estimate``'s figures for the same settings (the
    model's constants as they are now; report.json holds the one the render made)."""
    sweep = row["solver"] == "sweep"
    est = df.estimate(df.load_scene(row["scene"]), row["solver"], resolution=int(row["N"]),
                      **({"M": int(row["M"])} if sweep else {}))
    peak = est.peak_bytes / 2**20
    per_iter = float(row["s_per_iter"]) if sweep and row["s_per_iter"] not in ("", None) else None
    out = dict(scene=row["scene"], solver=row["solver"], N=int(row["N"]),
               M=int(row["M"]) if sweep else "", lattice="x".join(map(str, est.shape)),
               peak_mb=int(float(row["peak_mb"])), est_peak_mb=round(peak),
               mem_ratio=round(peak / float(row["peak_mb"]), 2),
               s_per_iter=per_iter, est_s_per_iter=round(est.seconds_per_iteration, 4)
               if sweep else None,
               time_ratio=round(est.seconds_per_iteration / per_iter, 2) if per_iter else None,
               setup_s=float(row["setup_s"]), est_setup_s=round(est.setup_s, 2))
    return out


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    C.add_sizes(ap, [32, 64, 96], [16])
    ap.add_argument("--ms", type=int, nargs="+", default=None, help="default 2 3 5")
    ap.add_argument("--scene", default="fog-balls")
    ap.add_argument("--iterations", type=int, default=4)
    ap.add_argument("--no-splat", action="store_true")
    ap.add_argument("--from-csv", action="store_true",
                    help="re-estimate the measured rows of OUT/cost.csv (no renders)")
    ap.add_argument("--out", type=Path, default=C.RESULTS)
    C.add_quick(ap)
    args = C.parse(ap, argv)
    ms = args.ms or ([2] if args.quick else [2, 3, 5])
    info = C.machine()
    C.print_machine(info)
    rows = []
    if args.from_csv:
        with open(args.out / "cost.csv") as f:
            rows = [with_estimate(r) for r in csv.DictReader(f)]
    for N in ([] if args.from_csv else args.sizes):
        for M in ms:
            r = run_row(args.scene, "sweep", N, M, args.iterations)
            rows += [r] if r else []
        if not args.no_splat:
            r = run_row(args.scene, "splat", N, None, 1)
            rows += [r] if r else []
    args.out.mkdir(parents=True, exist_ok=True)
    with open(args.out / "cost.csv", "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=list(rows[0]))
        w.writeheader()
        w.writerows(rows)
    table = [[r["solver"], str(r["N"]), str(r["M"]), r["lattice"], str(r["peak_mb"]),
              str(r["est_peak_mb"]), f"{r['mem_ratio']:.2f}",
              "" if r["s_per_iter"] is None else f"{r['s_per_iter']:.3f}",
              "" if r["est_s_per_iter"] is None else f"{r['est_s_per_iter']:.3f}",
              "" if r["time_ratio"] is None else f"{r['time_ratio']:.2f}",
              f"{r['setup_s']:.1f}", f"{r['est_setup_s']:.1f}"] for r in rows]
    lines = ["# The cost model against measured renders (benchmarks/bench_cost.py)", "",
             f"Scene {args.scene}, float32, `difffog render -N N -M M --iterations "
             f"{args.iterations}` in a fresh process per row; peak = the process's maximum "
             "resident memory; s/iter = light solve time / iterations (compilation apart); "
             "set-up = voxelize + prepare + camera hits; est = what `difffog.estimate` said "
             "before anything was built (recorded in report.json).", "",
             *C.machine_lines(info), "",
             *C.md_table(["solver", "N", "M", "lattice", "peak MiB", "est. MiB", "est/meas",
                          "s/iter", "est. s/iter", "est/meas", "set-up s", "est. set-up s"],
                         table, "lrrlrrrrrrrr")]
    C.write_text(args.out / "cost.md", lines)
    print("\n".join(lines))


if __name__ == "__main__":
    main()
