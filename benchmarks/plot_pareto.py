"""Time against error: difffog's sweep solver beside Mitsuba 3, per scene and camera.

Reads figures already measured, runs nothing:

* difffog: ``benchmarks/results/references.csv`` (``validate_references.py``): one point per
  lattice setting (N, M), time = warm light solve + render of all the scene's cameras
  (compilation excluded), error = relative RMSE against the Mitsuba reference with the
  reference's noise removed;
* Mitsuba 3: ``../shared/references/convergence.csv``: one point per samples-per-pixel count,
  its wall time for that camera and the same noise-corrected error.

Both were measured on the project's shared 2-core CPU, at different times and loads (see the
two sources), so read factors of two in time as noise.  Writes
``benchmarks/results/pareto.png``.

    python benchmarks/plot_pareto.py
"""

from __future__ import annotations

import csv
import math
from pathlib import Path

from matplotlib.figure import Figure

from difffog import plot

ROOT = Path(__file__).resolve().parents[1]
OURS = ROOT / "benchmarks" / "results" / "references.csv"
PEER = ROOT.parent / "shared" / "references" / "convergence.csv"
OUT = ROOT / "benchmarks" / "results" / "pareto.png"


def read(path: Path) -> list[dict]:
    with open(path, newline="") as f:
        return list(csv.DictReader(f))


def main():
    if not PEER.exists():
        raise SystemExit(f"no Mitsuba convergence data at {PEER}")
    ours, peer = read(OURS), read(PEER)
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
    fig.savefig(OUT, dpi=72)
    print(f"wrote {OUT}")


if __name__ == "__main__":
    main()
