"""The speed–accuracy study behind ``difffog bench`` and the accuracy presets.

For each solver and each setting of its knobs (sweep: lattice resolution N, direction
half-width M, iteration tolerance; splat: resolution and sheet count) and each scene that has
a Monte Carlo reference (``../shared/references``, or ``--references DIR``), this renders every
camera of the scene and records:

* ``time_s``: wall time of one warm forward pass (light solve + every camera), compile excluded;
* ``compile_s``: the first call minus a warm one (XLA compilation and one-time setup);
* ``setup_s``: host work before the first call (voxelization, solver geometry, splat plans);
* ``xla_mib``: XLA's compiled memory for the forward pass (temporaries + arguments + outputs);
* ``error``: relative RMSE against the reference with the reference's own noise removed in
  quadrature, averaged over the scene's cameras; ``bias``: mean(image)/mean(ref) − 1.

Mitsuba 3 (the peer a user would pick instead) enters with the time-versus-error curve the
references' authors measured on this project's 2-core machine (``convergence.csv``: samples per
pixel as its knob; wall time summed over the scene's cameras).  It is not re-run here: the
``bench`` extra does not install Mitsuba, and these scene files would need a converter.
"""

from __future__ import annotations

import csv
import json
import math
import sys
import time
import warnings
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ._errors import DifffogError

# The knobs of each solver, cheapest first.  ``quick`` is a smoke-test subset.
SWEEP_SETTINGS = [
    dict(resolution=32, M=2, tol=1e-3),
    dict(resolution=48, M=3, tol=1e-3),
    dict(resolution=64, M=3, tol=1e-4),
    dict(resolution=96, M=4, tol=1e-4),
]
SPLAT_SETTINGS = [
    dict(resolution=32, sheets=None),
    dict(resolution=64, sheets=34),
    dict(resolution=64, sheets=None),
    dict(resolution=128, sheets=None),
]
QUICK = {"sweep": [dict(resolution=16, M=2, tol=1e-3)], "splat": [dict(resolution=16, sheets=None)]}
FIELDS = ["solver", "scene", "setting", "resolution", "M", "tol", "sheets", "spp", "time_s",
          "compile_s", "setup_s", "xla_mib", "iterations", "error", "bias", "cameras"]


def default_references() -> Path | None:
    """``../shared/references`` beside the repository or the working directory, if present."""
    here = Path(__file__).resolve()
    for base in [Path.cwd(), *here.parents]:
        p = base.parent / "shared" / "references"
        if (p / "convergence.csv").exists():
            return p
    return None


def _reference(refdir: Path, scene: str, camera: str):
    img = refdir / scene / f"{camera}.npy"
    stats = refdir / scene / f"{camera}_stats.json"
    if not img.exists():
        return None
    noise = json.loads(stats.read_text())["ref_noise_rmse"] if stats.exists() else None
    return np.load(img), noise


def scene_errors(images: dict, refdir: Path, scene: str) -> tuple[float, float, list[str]]:
    """Mean relative RMSE (noise-corrected) and bias over the cameras that have a reference."""
    from .plot import image_errors

    errs, biases, cams = [], [], []
    for cam, img in images.items():
        ref = _reference(refdir, scene, cam)
        if ref is None:
            continue
        e = image_errors(np.asarray(img), ref[0], ref[1])
        errs.append(e.get("rel_rmse_corr", e["rel_rmse"]))
        biases.append(e["bias"])
        cams.append(cam)
    if not errs:
        return math.nan, math.nan, []
    return float(np.mean(errs)), float(np.mean(biases)), cams


def _xla_mib(jitted, *args) -> float:
    try:
        mem = jitted.lower(*args).compile().memory_analysis()
        return (mem.temp_size_in_bytes + mem.argument_size_in_bytes
                + mem.output_size_in_bytes) / 2**20
    except Exception:  # memory analysis is not available on every backend
        return math.nan


def build(solver: str, scene, setting: dict):
    """A forward model for one setting: a ``Renderer`` (sweep) or a ``SplatRenderer``."""
    if solver == "sweep":
        from ._render import Renderer
        from ._solver import SweepSolver

        return Renderer(scene, resolution=setting["resolution"],
                        solver=SweepSolver(M=setting["M"], tol=setting["tol"],
                                           max_iterations=1000))
    if solver == "splat":
        from ._splat import SplatRenderer

        return SplatRenderer(scene, resolution=setting["resolution"], sheets=setting["sheets"])
    raise DifffogError(f"unknown solver {solver!r}: choose sweep or splat")


def measure(solver: str, scene, setting: dict, refdir: Path, repeat: int = 2) -> dict:
    import jax

    t = time.perf_counter()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        r = build(solver, scene, setting)
    setup = time.perf_counter() - t
    params = r.params()
    t = time.perf_counter()
    imgs = jax.block_until_ready(r(params))
    first = time.perf_counter() - t
    warm = []
    for _ in range(repeat):
        t = time.perf_counter()
        imgs = jax.block_until_ready(r(params))
        warm.append(time.perf_counter() - t)
    time_s = min(warm)
    if solver == "sweep":
        mib = _xla_mib(r._forward, r.geometry, r.cam_geometry, r.density, params)
        iters = int(r.solve(params).iterations)
    else:
        mib = _xla_mib(r._forward, r.plans, params)
        iters = 0
    err, bias, cams = scene_errors(imgs, refdir, scene.title)
    return dict(solver=solver, scene=scene.title, setting=setting_label(solver, setting),
                resolution=setting["resolution"], M=setting.get("M", ""),
                tol=setting.get("tol", ""), sheets=setting.get("sheets") or "auto", spp="",
                time_s=time_s, compile_s=max(first - time_s, 0.0), setup_s=setup, xla_mib=mib,
                iterations=iters, error=err, bias=bias, cameras=" ".join(cams))


def setting_label(solver: str, s: dict) -> str:
    if solver == "sweep":
        return f"N{s['resolution']} M{s['M']} tol{s['tol']:g}"
    return f"N{s['resolution']} sheets {s['sheets'] or 'auto'}"


def mitsuba_rows(refdir: Path, scenes: list[str]) -> list[dict]:
    """Mitsuba 3's curve from the references' ``convergence.csv``: per scene and spp, the wall
    time summed over the cameras and the mean noise-corrected relative RMSE."""
    path = refdir / "convergence.csv"
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


def run_bench(*, scenes: list[str], solvers: list[str], out: Path, references: Path | None,
              quick: bool = False, progress: bool = False) -> BenchResult:
    """Run the study and write ``bench.csv``, ``pareto.png`` and ``bench.md`` into ``out``
    (atomically: a temporary folder renamed into place)."""
    import os
    import shutil
    import tempfile

    from ._scene_io import load_scene

    refdir = references or default_references()
    if refdir is None or not Path(refdir).is_dir():
        raise DifffogError("no reference images found: pass --references DIR (the folder with "
                           "<scene>/<camera>.npy and convergence.csv)")
    refdir = Path(refdir)
    for s in solvers:
        if s not in ("sweep", "splat"):
            raise DifffogError(f"--solver {s}: choose sweep or splat")
    loaded = {n: load_scene(n) for n in scenes}
    missing = [n for n in scenes if not (refdir / n).is_dir()]
    if missing:
        raise DifffogError(f"no reference images for {', '.join(missing)} in {refdir}; "
                           f"scenes with references: "
                           f"{', '.join(sorted(p.name for p in refdir.iterdir() if p.is_dir()))}")
    jobs = []
    for s in solvers:
        for n in scenes:
            if s == "splat" and (loaded[n].sun is None or loaded[n].domain.boundary != "open"):
                continue  # outside the splat's light model (it says so when asked directly)
            for st in (QUICK[s] if quick else (SWEEP_SETTINGS if s == "sweep" else SPLAT_SETTINGS)):
                jobs.append((s, n, st))
    rows = []
    bar = None
    if progress:
        from tqdm import tqdm

        bar = tqdm(total=len(jobs), unit="run", file=sys.stderr)
    for s, n, st in jobs:
        if bar is not None:
            bar.set_description(f"{s} {n} {setting_label(s, st)}")
        rows.append(measure(s, loaded[n], st, refdir))
        if bar is not None:
            bar.update()
    if bar is not None:
        bar.close()
    rows += mitsuba_rows(refdir, scenes)

    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=".difffog-bench-", dir=out.parent))
    try:
        with (tmp / "bench.csv").open("w", newline="") as f:
            w = csv.DictWriter(f, fieldnames=FIELDS)
            w.writeheader()
            for r in rows:
                w.writerow({k: _fmt(r.get(k, "")) for k in FIELDS})
        fig = pareto_figure(rows)
        fig.savefig(tmp / "pareto.png", dpi=120)
        (tmp / "bench.md").write_text(summary_markdown(rows))
        out.mkdir(parents=True, exist_ok=True)
        for f in tmp.iterdir():
            os.replace(f, out / f.name)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
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
    from . import plot

    import matplotlib.figure

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


def summary_markdown(rows: list[dict]) -> str:
    lines = ["| solver | scene | setting | warm s | compile s | setup s | XLA MiB | iterations "
             "| error % | bias % |", "|---|---|---|---:|---:|---:|---:|---:|---:|---:|"]
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
    from ._presets import LEVELS, PRESETS

    out = ["| solver | preset | setting | warm s (mean) | compile s (mean) | error % (mean) "
           "| scenes |", "|---|---|---|---:|---:|---:|---:|"]
    for solver in ("sweep", "splat"):
        for level in LEVELS:
            label = setting_label(solver, PRESETS[solver][level])
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
