"""Time against error: difffog's sweep solver beside Mitsuba 3, per scene and camera.

Reads figures already measured, runs nothing:

* difffog: ``benchmarks/results/references.csv`` (``validate_references.py``): one point per
  lattice setting (N, M), time = warm light solve + render of all the scene's cameras
  (compilation excluded), error = relative RMSE against the Mitsuba reference with the
  reference's noise removed;
* Mitsuba 3: ``convergence.csv`` of the references shipped with difffog
  (``difffog.study.references.references_dir()``, or ``--references DIR``): one point per
  samples-per-pixel count, its wall time for that camera and the same noise-corrected error.

Both were measured on the project's shared 2-core CPU, at different times and loads (see the
two sources), so read factors of two in time as noise.  Writes
``benchmarks/results/pareto.png`` (``--out``).

    python benchmarks/plot_pareto.py [--ours references.csv] [--references DIR] [--out PNG]
"""

from __future__ import annotations

import argparse
import csv
import math
from pathlib import Path

from matplotlib.figure import Figure

from difffog import plot
from difffog.study import references

RESULTS = Path(__file__).resolve().parent / "results"


def read(path: Path) -> list[dict]:
    with open(path, newline="") as f:
        return list(csv.DictReader(f))


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--ours", type=Path, default=RESULTS / "references.csv",
                    help="validate_references.py's CSV")
    ap.add_argument("--references", type=Path, default=None,
                    help="folder of the Mitsuba references (default: the shipped ones)")
    ap.add_argument("--out", type=Path, default=RESULTS / "pareto.png")
    args = ap.parse_args(argv)
    peer_csv = (args.references or references.references_dir()) / "convergence.csv"
    if not peer_csv.exists():
        raise SystemExit(f"no Mitsuba convergence data at {peer_csv}")
    ours, peer = read(args.ours), read(peer_csv)
    shots = list(dict.fromkeys((r["scene"], r["camera"]) for r in ours))
    ncols = 3
    nrows = math.ceil(len(shots) / ncols)
    fig = Figure(figsize=(4.6 * ncols, 3.6 * nrows), layout="constrained")
    axes = fig.subplots(nrows, ncols, squeeze=False).ravel()
    for ax, (scene, cam) in zip(axes, shots):
        rows = [{"solver": "difffog sweep (N, M)", "time_s": float(r["solve_s"]) +
                 float(r["render_s"]), "error": float(r["rel_rmse_corr"]),
                 "label": f"{r['N']},{r['M']}"}
                for r in ours if (r["scene"], r["camera"]) == (scene, cam)]
        rows += [{"solver": "Mitsuba 3 (spp)", "time_s": float(r["wall_s"]),
                  "error": float(r["rel_rmse_corr"]), "label": r["spp"]}
                 for r in peer if (r["scene"], r["camera"]) == (scene, cam)]
        # an error of 0 (below the reference's own noise) cannot sit on a log axis
        rows = [r for r in rows if r["error"] > 0]
        plot.pareto(rows, annotate="label", ax=ax,
                    ylabel="relative RMSE (reference noise removed)")
        ax.set_title(f"{scene} / {cam}", fontsize=10)
    for ax in axes[len(shots):]:
        ax.set_visible(False)
    fig.suptitle("Time against error: difffog sweep (warm solve + render) and Mitsuba 3 "
                 "(wall time), 2-core CPU")
    args.out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(args.out, dpi=72)
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
