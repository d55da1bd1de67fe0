# ---
# jupyter:
#   jupytext:
#     text_representation:
#       extension: .py
#       format_name: percent
#       format_version: '1.3'
#       jupytext_version: 1.19.6
#   kernelspec:
#     display_name: Python 3
#     language: python
#     name: python3
# ---

# %% [markdown]
# # 03 — Speed against accuracy
#
# Every solver has knobs that trade time for accuracy, and difffog measures that trade instead of
# guessing it: `difffog bench` renders the benchmark scenes at a ladder of settings of both solvers,
# times them, and scores each image against the independent Mitsuba 3 references. This notebook
# explains the knobs, plots the study (its committed results when they are in
# `benchmarks/results/bench/`, otherwise a quick run of one scene made here), sets it beside
# Mitsuba's own time-versus-error curve, and shows what the accuracy presets (`--accuracy
# draft|default|high`) are.

# %%
import os

# "small": what the test suite runs (quick checks: minutes on 2 CPU cores, mostly compiling);
# "full": the default, for people (the times are in notebooks/README.md)
SIZE = os.environ.get("DIFFFOG_NOTEBOOK_SIZE", "full")
if SIZE not in ("small", "full"):
    raise ValueError(f"DIFFFOG_NOTEBOOK_SIZE must be 'small' or 'full', got {SIZE!r}")
SMALL = SIZE == "small"
N = 24 if SMALL else 64  # lattice nodes along the longest side of the domain
M = 2 if SMALL else 3  # direction half-width: (2M+1)^2 directions per cube face
TOL = 1e-2 if SMALL else 1e-4  # the solver's estimated remaining relative error
print(f"size {SIZE}: N = {N}, M = {M}, tol = {TOL:g}")

# %%
import csv
import math
import tempfile
from pathlib import Path

import matplotlib.pyplot as plt
import numpy as np
from IPython.display import Markdown, display

from difffog import SOLVERS, plot
from difffog.study._bench import read_rows, run_bench
from difffog.study.references import references_dir

# the Mitsuba 3 references ship with difffog (images, noise, Mitsuba's own convergence run)
REFS = references_dir()
print("references:", REFS)

# %% [markdown]
# ## 1. The knobs
#
# | solver | knob | what it buys | what it costs |
# |---|---|---|---|
# | sweep | `resolution` N: lattice nodes along the longest side | smaller voxels h = L/N: sharper shadows and edges, thin walls that do not leak | time and memory ∝ N³ per iteration |
# | sweep | `M`: direction half-width, (2M+1)² directions per cube face | finer angles: fewer ray effects, better grazing single scattering | time ∝ (2M+1)², compile time |
# | sweep | `tol`: the estimated remaining error where the iteration (GMRES by default) stops | a converged light field; 1e-3 already changes images by < 0.1% | iterations, more at high albedo |
# | splat | `resolution`: voxels splatted along the longest side | finer footprints and shadow buffer | time ∝ voxels, setup (host ray casting) |
# | splat | `sheets`: slices per camera pass (default one per voxel) | little: the splat's light model, not the slicing, sets its error | time ∝ sheets |
# | Mitsuba 3 | samples per pixel (spp) | noise ∝ 1/√spp, no bias | time ∝ spp |
#
# Each row of the study records the warm time of one forward pass (the light solve and every camera
# of the scene; `time_s`), the compile time paid once per process (`compile_s`), the host set-up
# paid once per scene (`setup_s`), XLA's memory for the pass (`xla_mib`), the sweep's iterations
# (applications of its six sweeps), and the relative RMSE against the reference with the reference's
# own noise removed (`error`) and the bias of the mean (`bias`).

# %% [markdown]
# ## 2. The study
#
# The committed study is `benchmarks/results/bench/bench.csv` (`difffog bench` over the four
# benchmark scenes and both solvers: about an hour on 2 CPU cores), read back with
# `read_rows`. When it is not there (an installed difffog without the repository),
# `run_bench(..., quick=True)` runs one small setting per solver on `cloud-plane` against the
# shipped references into a temporary folder (a minute or two): the same rows, fewer of them.
# Reading the study costs nothing, so this notebook is the same at both sizes.

# %%
BENCH_CSV = Path.cwd().parent / "benchmarks" / "results" / "bench" / "bench.csv"
# read_rows: bench.csv as a list of dicts, numbers as floats (NaN where a column does not apply)
committed = read_rows(BENCH_CSV) if BENCH_CSV.exists() else None
if committed is not None:
    rows, source = committed, f"the committed study ({BENCH_CSV.name})"
else:
    with tempfile.TemporaryDirectory() as tmp:
        quick = run_bench(scenes=["cloud-plane"], solvers=["sweep", "splat"],
                          out=Path(tmp) / "bench", quick=True)
        rows = read_rows(quick.csv_path)
    source = "a quick run on cloud-plane (one setting per solver)"
ours = [r for r in rows if not r["solver"].startswith("mitsuba")]
mitsuba = [r for r in rows if r["solver"].startswith("mitsuba")]
scenes = sorted({r["scene"] for r in ours})
print(f"{source}: {len(ours)} difffog rows, {len(mitsuba)} Mitsuba rows; scenes {scenes}")
header = ("| solver | scene | setting | warm s | compile s | setup s | XLA MiB | iterations "
          "| error % | bias % |")
table = [header, "|---|---|---|---:|---:|---:|---:|---:|---:|---:|"]
for r in ours:
    table.append(f"| {r['solver']} | {r['scene']} | {r['setting']} | {r['time_s']:.2f} | "
                 f"{r['compile_s']:.1f} | {r['setup_s']:.1f} | {r['xla_mib']:.0f} | "
                 f"{r['iterations']:.0f} | {100 * r['error']:.1f} | {100 * r['bias']:+.1f} |")
display(Markdown("\n".join(table)))


# %% [markdown]
# ## 3. Time against error: the Pareto plot
#
# One panel per scene; warm time per image set (every camera of the scene, compile excluded)
# against the error, both on log axes, one curve per solver, and the Pareto front: the
# settings that no other setting beats in both time and error. Mitsuba's curve is its own
# run on this machine at 4 … 1024 samples per pixel (the references' `convergence.csv`; it is
# not re-run here).

# %%
def pareto_panels(rows, title):
    scenes = sorted({r["scene"] for r in rows})
    fig, axes = plt.subplots(1, len(scenes), figsize=(4.6 * len(scenes), 3.8),
                             layout="constrained", squeeze=False)
    for ax, sc in zip(axes[0], scenes):
        rs = [dict(r, error=100 * r["error"]) for r in rows
              if r["scene"] == sc and np.isfinite(r["error"])]
        plot.pareto(rs, x="time_s", y="error", group="solver", annotate="setting", ax=ax,
                    xlabel="warm time per image set (s)",
                    ylabel="relative RMSE vs Mitsuba 3 reference (%)")
        ax.set_title(sc, fontsize=9)
    fig.suptitle(title)
    plt.close(fig)
    return fig


pareto_panels(rows, source)

# %% [markdown]
# ## 4. Mitsuba 3's curve, and what it takes to match difffog
#
# A Monte Carlo renderer has no bias, only noise, and its error falls as 1/√spp: four times the
# time for half the error. Below, the references' convergence run per camera against samples
# per pixel, with a 1/√spp line through each curve's first point. Then, for each difffog row,
# how long Mitsuba needs to reach the same error (interpolated on its curve, log-log), beside
# difffog's warm time and its first render in a fresh process (set-up and compilation
# included; Mitsuba's times are whole renders). The advantage is largest at coarse errors and
# shrinks as the error asked for falls: difffog's error stops falling at its model bias (a few
# to 30 per cent, depending on the scene and the view), Mitsuba's keeps falling as 1/√time.

# %%
curves = {}
with open(REFS / "convergence.csv", newline="") as f:
    for r in csv.DictReader(f):
        if r["scene"] in scenes:
            curves.setdefault(f"{r['scene']} / {r['camera']}", []).append(
                (float(r["spp"]), float(r["rel_rmse_corr"])))
fig, ax = plt.subplots(figsize=(5.6, 3.8), layout="constrained")
for label, pts in curves.items():
    spp, err = np.array(sorted(pts)).T
    line, = ax.loglog(spp, 100 * err, marker="o", ms=4, label=label)
    ax.loglog(spp, 100 * err[0] * np.sqrt(spp[0] / spp), ls=":", color=line.get_color())
ax.set_xlabel("samples per pixel")
ax.set_ylabel("relative RMSE vs reference (%)")
ax.set_title("Mitsuba 3 (dotted: 1/√spp)", fontsize=9)
ax.grid(True, which="both", alpha=0.3)
ax.legend(fontsize=7)
plt.close(fig)
fig


# %%
def mitsuba_time_at(scene, error):
    """Mitsuba's wall time (all cameras) to reach ``error`` on its curve, log-log
    interpolation; extrapolated with 1/√t beyond its last point."""
    pts = sorted((r["time_s"], r["error"]) for r in mitsuba if r["scene"] == scene)
    if not pts:
        return math.nan
    t, e = np.log(np.array(pts)).T
    if np.log(error) < e[-1]:  # below its lowest error: error ∝ t^-1/2
        return float(np.exp(t[-1] + 2 * (e[-1] - np.log(error))))
    return float(np.exp(np.interp(-np.log(error), -e, t)))


labels, ours_t, first_t, theirs_t = [], [], [], []
print(f"{'solver':6s} {'scene':17s} {'setting':18s} {'error %':>8s} {'difffog s':>10s} "
      f"{'Mitsuba s':>10s} {'speed-up':>9s}")
for r in ours:
    tm = mitsuba_time_at(r["scene"], r["error"])
    labels.append(f"{r['solver']} {r['scene']}\n{r['setting']}")
    ours_t.append(r["time_s"])
    first_t.append(r["time_s"] + r["compile_s"] + r["setup_s"])
    theirs_t.append(tm)
    print(f"{r['solver']:6s} {r['scene']:17s} {r['setting']:18s} {100 * r['error']:8.1f} "
          f"{r['time_s']:10.2f} {tm:10.1f} {tm / r['time_s']:8.0f}×")
fig, ax = plt.subplots(figsize=(min(16.0, max(5.0, 0.6 * len(labels))), 3.8),
                       layout="constrained")
x = np.arange(len(labels))
ax.bar(x - 0.27, ours_t, 0.27, label="difffog, warm")
ax.bar(x, first_t, 0.27, label="difffog, first render (set-up + compile)")
ax.bar(x + 0.27, theirs_t, 0.27, label="Mitsuba 3 to the same error")
ax.set_yscale("log")
ax.set_xticks(x, labels, fontsize=7, rotation=90 if len(labels) > 6 else 0)
ax.set_ylabel("time per image set (s)")
ax.set_title("time to reach each difffog row's error", fontsize=9)
ax.legend(fontsize=8)
plt.close(fig)
fig

# %% [markdown]
# ## 5. What a forward pass costs besides its warm time
#
# In a notebook the first render of a new renderer pays the host set-up (voxelizing, and for
# the splat ray casting its z-buffers and footprints) and XLA's compilation; after that only the
# warm time counts, which is what a fit or a slider pays per evaluation. Memory is XLA's for one
# forward pass (the sweep's grows with N³ and the directions, the splat's with the sheets'
# area).

# %%
labels = [f"{r['solver']} {r['scene']}\n{r['setting']}" for r in ours]
x = np.arange(len(ours))
rot = 90 if len(ours) > 6 else 0
fig, ax = plt.subplots(figsize=(min(16.0, max(5.0, 0.5 * len(ours))), 3.8), layout="constrained")
bottom = np.zeros(len(ours))
for key, name in [("setup_s", "host set-up"), ("compile_s", "compile"),
                  ("time_s", "warm forward pass")]:
    v = np.array([r[key] for r in ours])
    ax.bar(x, v, bottom=bottom, label=name)
    bottom += v
ax.set_xticks(x, labels, fontsize=7, rotation=rot)
ax.set_ylabel("time (s)")
ax.set_title("first render = set-up + compile + warm", fontsize=9)
ax.legend(fontsize=8)
plt.close(fig)
display(fig)
fig, ax = plt.subplots(figsize=(min(16.0, max(5.0, 0.5 * len(ours))), 3.6), layout="constrained")
ax.bar(x, [r["xla_mib"] for r in ours], color="tab:purple")
ax.set_xticks(x, labels, fontsize=7, rotation=rot)
ax.set_ylabel("XLA memory per forward pass (MiB)")
ax.set_title("memory of one forward pass", fontsize=9)
plt.close(fig)
fig

# %% [markdown]
# ## 6. Where the splat wins and where it loses
#
# From the rows above, per scene: each solver's most accurate setting and its fastest one.
# The measured picture at N = 64 (`benchmarks/results/splat_references.md` and the README's
# "Splat solver" section): the splat renders both cameras in 0.3–0.8 s against 5–14 s for the
# sweep's solve, with no iteration. It comes within a few points of the sweep on `cloud-plane`
# (13 / 37% against 11 / 31%, top / oblique) — the forward-scattering cloud under a polygon
# airplane it was designed for — but is 2–3× the sweep's error in the translucent cube and
# misses a fifth of the light in the walled `fog-balls` box (−19 to −24%), because light that
# bounces between surfaces and the fog is outside its light model. More sheets do not help.
# So: the splat for previews, for shadows' shapes, for clouds and for fits that need many
# renders; the sweep when the answer has to be within a few per cent.

# %%
for sc in scenes:
    print(sc)
    for solver in ("sweep", "splat"):
        rs = [r for r in ours if r["scene"] == sc and r["solver"] == solver
              and np.isfinite(r["error"])]
        if not rs:
            print(f"  {solver}: not in this study")
            continue
        best = min(rs, key=lambda r: r["error"])
        fast = min(rs, key=lambda r: r["time_s"])
        print(f"  {solver}: most accurate {best['setting']} ({100 * best['error']:.1f}% in "
              f"{best['time_s']:.2f} s); fastest {fast['setting']} ({fast['time_s']:.2f} s, "
              f"{100 * fast['error']:.1f}%)")

# %% [markdown]
# ## 7. The accuracy presets
#
# `--accuracy draft|default|high` on the command line, `accuracy=` in
# `difffog.forward_model` (and `df.render(scene, accuracy=...)`), pick a setting per solver
# from this study (`difffog.SOLVERS[solver].presets`): the sweep's draft
# is N = 32, M = 2 (seconds, about twice the default's error), its default N = 64, M = 3, its
# high N = 96, M = 4; the splat's presets vary the resolution only, since more sheets do not
# lower its error.

# %%
lines = ["| solver | preset | settings |", "|---|---|---|"]
for solver, entry in SOLVERS.items():
    for level, s in entry.presets.items():
        lines.append(f"| {solver} | {level} | "
                     + ", ".join(f"{k} = {'one per voxel' if v is None else v}"
                                 for k, v in s.items()) + " |")
display(Markdown("\n".join(lines)))

# %% [markdown]
# ## 8. Re-running the study
#
# ```bash
# difffog bench                                  # both solvers, the four benchmark scenes
# difffog bench --scenes cloud-plane --solvers splat --out bench-cloud
# difffog bench --quick --scenes fog-balls       # one small setting per solver (a smoke test)
# difffog bench --references /path/to/references # default: the ones shipped with difffog
# ```
#
# Each writes `bench.csv` (the rows above), `pareto.png` and `bench.md` into `--out` (default
# `bench/`; written to a temporary folder and renamed, so a killed run leaves nothing
# half-written). Times depend on the machine and on what else runs on it: compare settings
# measured in the same run, and record the load (`uptime`) beside any figure you quote.
