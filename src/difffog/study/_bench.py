"""The speed–accuracy study behind ``difffog bench`` and the accuracy presets.

For each solver of the registry and each setting of its knobs (its ``study`` settings: sweep
N, M and tolerance; splat N and sheets) and each scene that has a Monte Carlo reference (the
references shipped with difffog, ``difffog.study.references``, or ``--references DIR``), this
renders every camera of the scene and records:

* ``time_s``: wall time of one warm forward pass (light + every camera), compile excluded;
* ``compile_s``: the first call minus a warm one (XLA compilation and one-time setup);
* ``setup_s``: host work before the first call (voxelization, solver geometry, sheets);
* ``xla_mib``: XLA's compiled memory for the forward pass (temporaries + arguments + outputs);
* ``error``: relative RMSE against the reference with the reference's own noise removed in
  quadrature, averaged over the scene's cameras; ``bias``: mean(image)/mean(ref) − 1.

``bench.md`` opens with the machine: JAX's backend and devices, the CPU, and its copy bandwidth
(one thread and all cores) measured at the start and at the end of the run, the roofline the
times are to be read against (a busy machine shows as a drop between the two).

Mitsuba 3 (the peer a user would pick instead) enters with the time-versus-error curve the
references' authors measured on this project's 2-core machine (``convergence.csv``: samples per
pixel as its knob; wall time summed over the scene's cameras).  It is not re-run here.
"""

from __future__ import annotations

import csv
import math
import time
import warnings
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from .._errors import DifffogError, SceneError
from .._image import image_errors
from .._output import atomic_folder
from .._progress import as_meter
from ..forward._model import images_jit, light_jit
from ..forward._registry import LEVELS, forward_model, preset, solver_entry, solver_names
from . import references as refs

FIELDS = ["solver", "scene", "setting", "resolution", "M", "tol", "sheets", "spp", "time_s",
          "compile_s", "setup_s", "xla_mib", "iterations", "error", "bias", "cameras"]


def scene_errors(images: dict, refdir: Path, scene: str) -> tuple[float, float, list[str]]:
    """Mean relative RMSE (noise-corrected) and bias over the cameras that have a reference."""
    errs, biases, cams = [], [], []
    for cam, img in images.items():
        ref = refs.reference(scene, cam, refdir)
        if ref is None:
            continue
        e = image_errors(np.asarray(img), ref[0], ref[1])
        errs.append(e.get("rel_rmse_corr", e["rel_rmse"]))
        biases.append(e["bias"])
        cams.append(cam)
    if not errs:
        return math.nan, math.nan, []
    return float(np.mean(errs)), float(np.mean(biases)), cams


def _xla_mib(model, params) -> float:
    try:
        # equinox's Compiled wraps JAX's, which has the memory analysis
        mem = images_jit.lower(model, params, False).compile().compiled.memory_analysis()
        return (mem.temp_size_in_bytes + mem.argument_size_in_bytes
                + mem.output_size_in_bytes) / 2**20
    except Exception:  # memory analysis is not available on every backend
        return math.nan


def measure(solver: str, scene, setting: dict, refdir: Path, repeat: int = 2) -> dict:
    """One row of the study: build the model, time a first and ``repeat`` warm renders."""
    import gc

    import jax

    # every row compiles its own programs; without this a study keeps all of them, and after
    # ~25 rows of large lattices LLVM failed to map memory for the next one (a segfault)
    jax.clear_caches()
    gc.collect()
    t = time.perf_counter()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        model = forward_model(scene, solver, accuracy=None, **setting)
    setup = time.perf_counter() - t
    params = model.params()
    t = time.perf_counter()
    imgs = jax.block_until_ready(model(params))
    first = time.perf_counter() - t
    warm = []
    for _ in range(repeat):
        t = time.perf_counter()
        imgs = jax.block_until_ready(model(params))
        warm.append(time.perf_counter() - t)
    time_s = min(warm)
    mib = _xla_mib(model, params)
    iters = int(light_jit(model, params).iterations)
    err, bias, cams = scene_errors(imgs, refdir, scene.title)
    return dict(solver=solver, scene=scene.title, setting=setting_label(setting),
                resolution=setting["resolution"], M=setting.get("M", ""),
                tol=setting.get("tol", ""), sheets=setting.get("sheets") or "auto", spp="",
                time_s=time_s, compile_s=max(first - time_s, 0.0), setup_s=setup, xla_mib=mib,
                iterations=iters, error=err, bias=bias, cameras=" ".join(cams))


def setting_label(s: dict) -> str:
    """A short label of a setting: ``N64 M3 tol0.0001``, ``N64 sheets 34``."""
    parts = [f"N{s['resolution']}"]
    for k, v in s.items():
        if k == "resolution":
            continue
        parts.append(f"{k}{v:g}" if isinstance(v, (int, float)) and k != "sheets"
                     else f"{k} {v if v is not None else 'auto'}")
    return " ".join(parts)


def mitsuba_rows(refdir: Path, scenes: list[str]) -> list[dict]:
    """Mitsuba 3's curve from the references' ``convergence.csv``: per scene and spp, the wall
    time summed over the cameras and the mean noise-corrected relative RMSE."""
    path = Path(refdir) / "convergence.csv"
    if not path.exists():
        return []
    acc: dict[tuple[str, int], list[tuple[float, float]]] = {}
    with path.open() as f:
        for row in csv.DictReader(f):
            if row["scene"] in scenes:
                acc.setdefault((row["scene"], int(row["spp"])), []).append(
                    (float(row["wall_s"]), float(row["rel_rmse_corr"])))
    out = []
    for (scene, spp), v in sorted(acc.items()):
        out.append(dict(solver="mitsuba3 (references' run)", scene=scene, setting=f"{spp} spp",
                        resolution="", M="", tol="", sheets="", spp=spp,
                        time_s=sum(t for t, _ in v), compile_s="", setup_s="", xla_mib="",
                        iterations="", error=float(np.mean([e for _, e in v])), bias="",
                        cameras=len(v)))
    return out


@dataclass
class BenchResult:
    rows: list[dict]
    csv_path: Path
    plot_path: Path
    summary_path: Path


def run_bench(*, scenes: list[str], solvers: list[str], out: Path,
              references: Path | None = None, quick: bool = False,
              progress=None) -> BenchResult:
    """Run the study and write ``bench.csv``, ``pareto.png`` and ``bench.md`` into ``out``
    (atomically: a temporary folder renamed into place).

    scenes: built-in scene names with references; solvers: registry names; references: a
    folder of ``<scene>/<camera>.npy`` and ``convergence.csv`` (default: the shipped ones);
    quick: one small setting per solver (a smoke test); progress: True or a progress meter.
    """
    from ..scene._toml import load_scene

    refdir = Path(references) if references is not None else refs.references_dir()
    if not refdir.is_dir():
        raise DifffogError(f"--references {refdir}: no such folder (it should hold "
                           "<scene>/<camera>.npy and convergence.csv)")
    for s in solvers:
        solver_entry(s)
    loaded = {n: load_scene(n) for n in scenes}
    missing = [n for n in scenes if not (refdir / n).is_dir()]
    if missing:
        raise DifffogError(f"no reference images for {', '.join(missing)} in {refdir}; "
                           f"scenes with references: "
                           f"{', '.join(sorted(p.name for p in refdir.iterdir() if p.is_dir()))}")
    jobs = []
    for s in solvers:
        entry = solver_entry(s)
        for n in scenes:
            for st in (entry.quick if quick else entry.study):
                jobs.append((s, n, dict(st)))
    rows = []
    machine = {"start": run_machine()}
    meter = as_meter(progress, "bench")
    for i, (s, n, st) in enumerate(jobs):
        try:
            rows.append(measure(s, loaded[n], st, refdir))
        except SceneError:
            pass  # outside this solver's light model (it says so when asked directly)
        meter.update(i + 1, len(jobs), run=f"{s} {n} {setting_label(st)}")
    meter.close()
    machine["end"] = run_machine()
    rows += mitsuba_rows(refdir, scenes)
    with atomic_folder(out) as tmp:
        with (tmp / "bench.csv").open("w", newline="") as f:
            w = csv.DictWriter(f, fieldnames=FIELDS)
            w.writeheader()
            for r in rows:
                w.writerow({k: _fmt(r.get(k, "")) for k in FIELDS})
        fig = pareto_figure(rows)
        fig.savefig(tmp / "pareto.png", dpi=120)
        (tmp / "bench.md").write_text(summary_markdown(rows, machine))
    out = Path(out)
    return BenchResult(rows, out / "bench.csv", out / "pareto.png", out / "bench.md")


def _fmt(v):
    if isinstance(v, float):
        return "" if math.isnan(v) else f"{v:.5g}"
    return v


def aggregate(rows: list[dict]) -> list[dict]:
    """Per solver and setting: time summed over the scenes, error averaged (scenes that every
    setting of that solver ran)."""
    groups: dict[tuple[str, str], list[dict]] = {}
    for r in rows:
        groups.setdefault((r["solver"], r["setting"]), []).append(r)
    out = []
    for (solver, setting), rs in groups.items():
        err = [r["error"] for r in rs if isinstance(r["error"], float) and not math.isnan(r["error"])]
        out.append(dict(solver=solver, setting=setting, scenes=len(rs),
                        time_s=sum(float(r["time_s"]) for r in rs),
                        error=float(np.mean(err)) if err else math.nan))
    return out


def pareto_figure(rows: list[dict]):
    import matplotlib.figure

    from .. import plot

    scenes = sorted({r["scene"] for r in rows})
    ncols = min(len(scenes), 3)
    nrows = math.ceil(len(scenes) / ncols)
    fig = matplotlib.figure.Figure(figsize=(4.2 * ncols, 3.4 * nrows), layout="constrained")
    axes = fig.subplots(nrows, ncols, squeeze=False)
    for ax, sc in zip(axes.flat, scenes):
        rs = [dict(r, error=100 * r["error"]) for r in rows
              if r["scene"] == sc and isinstance(r["error"], float) and not math.isnan(r["error"])]
        if rs:
            plot.pareto(rs, x="time_s", y="error", group="solver", annotate="setting", ax=ax,
                        xlabel="time per image set (s, warm)",
                        ylabel="relative RMSE vs Monte Carlo (%)")
        ax.set_title(sc, fontsize=9)
    for ax in list(axes.flat)[len(scenes):]:
        ax.set_visible(False)
    return fig


def run_machine() -> dict:
    """Where a study runs, measured now: ``_cost.machine`` (backend, devices, JAX), the CPU's
    name and cores, the load average, and the copy bandwidth in GB/s on one thread and on all
    cores."""
    import os

    from .._cost import copy_bandwidth, cpu_name, load_average, machine

    info = machine()
    info["cpu"] = cpu_name()
    info["cores"] = os.cpu_count() or 1
    info["load"] = load_average()
    info["copy_1"] = copy_bandwidth(threads=1)
    info["copy_all"] = copy_bandwidth(threads=info["cores"])
    return info


def machine_markdown(machine: dict) -> list[str]:
    """The run's machine as markdown lines (``run_machine`` at the start and the end)."""
    from .._cost import machine_line

    s, e = machine["start"], machine.get("end", machine["start"])
    return [f"- {machine_line(s)}; {s['cpu']}, {s['cores']} cores",
            f"- copy bandwidth (NumPy copy of 256 MiB float32, bytes read + written): "
            f"{s['copy_1']:.1f} GB/s on one thread, {s['copy_all']:.1f} GB/s on {s['cores']} "
            f"at the start; {e['copy_1']:.1f} / {e['copy_all']:.1f} GB/s at the end",
            f"- load average (1/5/15 min) {s['load']} at the start, {e['load']} at the end"]


def summary_markdown(rows: list[dict], machine: dict | None = None) -> str:
    head = (["# difffog bench", "", *machine_markdown(machine), ""] if machine else [])
    lines = head + ["| solver | scene | setting | warm s | compile s | setup s | XLA MiB "
                    "| iterations | error % | bias % |",
                    "|---|---|---|---:|---:|---:|---:|---:|---:|---:|"]
    for r in rows:
        if r["solver"].startswith("mitsuba"):
            continue
        lines.append(
            f"| {r['solver']} | {r['scene']} | {r['setting']} | {r['time_s']:.2f} "
            f"| {r['compile_s']:.1f} | {r['setup_s']:.1f} | {r['xla_mib']:.0f} | {r['iterations']} "
            f"| {100 * r['error']:.1f} | {100 * r['bias']:+.1f} |")
    lines += ["", "Mitsuba 3 (the references' own convergence run on this machine):", "",
              "| scene | spp | s (all cameras) | error % |", "|---|---:|---:|---:|"]
    for r in rows:
        if r["solver"].startswith("mitsuba"):
            lines.append(f"| {r['scene']} | {r['spp']} | {r['time_s']:.2f} | {100 * r['error']:.1f} |")
    return "\n".join(lines + ["", "## The presets", "", *preset_table(rows), "",
                              "## Mitsuba 3 at equal error", "", *equal_error_table(rows)]) + "\n"


def _measured(r) -> bool:
    return isinstance(r.get("error"), float) and not math.isnan(r["error"])


def preset_table(rows: list[dict]) -> list[str]:
    """Each --accuracy preset's setting: warm time (mean over the scenes) and error (mean)."""
    out = ["| solver | preset | setting | warm s (mean) | compile s (mean) | error % (mean) "
           "| scenes |", "|---|---|---|---:|---:|---:|---:|"]
    for solver in solver_names():
        for level in LEVELS:
            label = setting_label(preset(solver, level))
            rs = [r for r in rows if r["solver"] == solver and r["setting"] == label
                  and _measured(r)]
            if rs:
                out.append(f"| {solver} | {level} | {label} "
                           f"| {np.mean([r['time_s'] for r in rs]):.2f} "
                           f"| {np.mean([r['compile_s'] for r in rs]):.1f} "
                           f"| {100 * np.mean([r['error'] for r in rs]):.1f} | {len(rs)} |")
    return out


def mitsuba_time_at(rows: list[dict], scene: str, error: float) -> float:
    """Mitsuba's wall time (all cameras) to reach ``error`` on ``scene``: log-log interpolation
    of its measured curve (error ∝ spp^-1/2 beyond its ends); NaN without a curve."""
    pts = sorted((r["error"], r["time_s"]) for r in rows
                 if r["solver"].startswith("mitsuba") and r["scene"] == scene and _measured(r))
    if len(pts) < 2 or not error > 0:
        return math.nan
    e = np.log([p[0] for p in pts])
    t = np.log([p[1] for p in pts])
    x = math.log(error)
    if x < e[0]:  # below the curve's smallest error: t ∝ error^-2
        return float(math.exp(t[0] + 2.0 * (e[0] - x)))
    if x > e[-1]:
        return float(math.exp(t[-1] - 2.0 * (x - e[-1])))
    return float(math.exp(np.interp(x, e, t)))


def equal_error_table(rows: list[dict]) -> list[str]:
    out = ["| solver | scene | setting | error % | difffog warm s | difffog first s "
           "| Mitsuba s at that error | warm speed-up |", "|---|---|---|---:|---:|---:|---:|---:|"]
    for r in rows:
        if r["solver"].startswith("mitsuba") or not _measured(r):
            continue
        tm = mitsuba_time_at(rows, r["scene"], r["error"])
        first = r["time_s"] + r["compile_s"] + r["setup_s"]
        out.append(f"| {r['solver']} | {r['scene']} | {r['setting']} | {100 * r['error']:.1f} "
                   f"| {r['time_s']:.2f} | {first:.1f} | {tm:.2f} | {tm / r['time_s']:.1f}× |")
    return out


_NUMERIC = ("resolution", "M", "tol", "sheets", "spp", "time_s", "compile_s", "setup_s",
            "xla_mib", "iterations", "error", "bias")


def read_rows(path) -> list[dict]:
    """A ``bench.csv`` back as rows (numbers as floats, NaN where a column does not apply), e.g.
    to redo ``bench.md`` and the plot without re-running: ``summary_markdown(read_rows(p))``."""
    rows = []
    with open(path, newline="") as f:
        for r in csv.DictReader(f):
            for k in _NUMERIC:
                try:
                    r[k] = float(r[k])
                except (TypeError, ValueError):
                    r[k] = math.nan
            rows.append(r)
    return rows
