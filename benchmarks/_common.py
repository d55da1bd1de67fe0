"""What the benchmark scripts share: size arguments, timing, the machine they ran on, markdown
tables, worker processes, the Mitsuba comparison and the sweep's k-iteration programs.

Importing this module has no side effects: it imports neither JAX nor difffog at the top
(so a script can still set ``XLA_FLAGS`` before JAX starts) and sets no environment.  The
scripts import it as ``import _common`` (``python benchmarks/<script>.py`` puts this folder on
``sys.path``).
"""

from __future__ import annotations

import json
import os
import platform
import statistics
import subprocess
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
RESULTS = HERE / "results"
GB = 1e9
MIB = 2**20


# ----------------------------------------------------------------------------- arguments
def add_sizes(ap, default, quick, *, flag: str = "--sizes", what: str = "lattice sizes N"):
    """Add ``flag`` (ints, nargs +) and ``--quick`` (once) to an argparse parser.  After
    :func:`parse`, the sizes are the ones given, else ``quick`` with ``--quick``, else
    ``default``."""
    dest = flag.lstrip("-").replace("-", "_")
    fmt = lambda xs: " ".join(map(str, xs))  # noqa: E731
    ap.add_argument(flag, dest=dest, type=int, nargs="+", default=None, metavar="N",
                    help=f"{what} (default {fmt(default)}; with --quick {fmt(quick)})")
    add_quick(ap)
    specs = list(ap.get_default("_sizes") or [])
    ap.set_defaults(_sizes=specs + [(dest, list(default), list(quick))])


def add_quick(ap, help: str = "smallest sizes: a smoke test that the script runs"):
    if "--quick" not in ap._option_string_actions:
        ap.add_argument("--quick", action="store_true", help=help)


def parse(ap, argv=None):
    """``ap.parse_args(argv)`` with the sizes of :func:`add_sizes` resolved."""
    a = ap.parse_args(argv)
    for dest, default, quick in getattr(a, "_sizes", None) or ():
        if getattr(a, dest) is None:
            setattr(a, dest, list(quick if a.quick else default))
    return a


# ----------------------------------------------------------------------------- timing
@dataclass
class Times:
    """Wall times of repeated calls: ``first`` (the first call, with compilation when the
    function compiles on first use; None when not measured), ``times`` (the later calls) and
    ``value``, what the last call returned."""

    first: float | None
    times: list[float]
    value: object = None

    @property
    def median(self) -> float:
        return statistics.median(self.times)

    @property
    def best(self) -> float:
        return min(self.times)


def time_calls(fn, repeat: int = 3, *, first: bool = True) -> Times:
    """Time ``fn()`` ``repeat`` times, each until its result is ready
    (``jax.block_until_ready``); with ``first``, one call before them (compile, warm-up) is
    timed apart."""
    import jax

    out = Times(None, [])

    def once():
        t = time.perf_counter()
        out.value = jax.block_until_ready(fn())
        return time.perf_counter() - t

    out.first = once() if first else None
    out.times = [once() for _ in range(repeat)]
    return out


def compile_timed(fn, *args):
    """(compiled ``fn``, seconds): ``equinox.filter_jit(fn)`` lowered and compiled ahead of
    time for ``args`` (modules and non-array leaves are static, arrays arguments); call the
    result with the same ``args``."""
    import equinox as eqx

    t = time.perf_counter()
    c = eqx.filter_jit(fn).lower(*args).compile()
    return c, time.perf_counter() - t


def xla_mib(compiled, what: str = "temp") -> float:
    """XLA's ``memory_analysis`` of a compiled function (JAX's or equinox's) in MiB:
    ``what`` = "temp" or "argument"; NaN where the backend does not report it."""
    c = getattr(compiled, "compiled", compiled)
    try:
        mem = c.memory_analysis()
    except Exception:  # not available on every backend
        mem = None
    if mem is None:
        return float("nan")
    return getattr(mem, f"{what}_size_in_bytes") / MIB


# ----------------------------------------------------------------------------- the machine
def copy_bandwidth(nbytes: int = 256 * MIB, repeat: int = 5, threads: int = 1) -> float:
    """The machine's copy bandwidth in GB/s (``difffog._cost.copy_bandwidth``; imported here,
    not at the top, so that a script can set XLA_FLAGS before JAX loads)."""
    from difffog._cost import copy_bandwidth as measure

    return measure(nbytes, repeat, threads)


def device_copy_bandwidth(nbytes: int = 256 * MIB, repeat: int = 5) -> float:
    """The default JAX device's copy bandwidth in GB/s (bytes read + written per second, median
    of ``repeat``): a jitted copy (x + 0 of a float32 array of ``nbytes``) on the device.  On a
    GPU this is the roofline of the sweep; on a CPU it is XLA's own copy (compare with
    :func:`copy_bandwidth`)."""
    import jax
    import jax.numpy as jnp

    x = jnp.ones(nbytes // 4, jnp.float32)
    f = jax.jit(lambda a: a + 0.0)
    f(x).block_until_ready()
    times = []
    for _ in range(repeat):
        t = time.perf_counter()
        f(x).block_until_ready()
        times.append(time.perf_counter() - t)
    return 2 * nbytes / statistics.median(times) / GB


def loadavg() -> str:
    """``difffog._cost.load_average`` (imported here, not at the top: see copy_bandwidth)."""
    from difffog._cost import load_average

    return load_average()


def machine(bandwidth: bool = True, nbytes: int = 256 * MIB) -> dict:
    """Where and how this run ran, measured now: JAX version, backend and devices, CPU,
    cores, load average, and (``bandwidth``) the NumPy copy bandwidth in GB/s."""
    import jax

    from difffog._cost import cpu_name

    devs = jax.devices()
    kinds = sorted({d.device_kind for d in devs})
    info = {
        "jax": jax.__version__,
        "backend": jax.default_backend(),
        "devices": f"{len(devs)} × {', '.join(kinds)}",
        "cpu": cpu_name(),
        "cores": os.cpu_count(),
        "python": platform.python_version(),
        "xla_flags": os.environ.get("XLA_FLAGS", ""),
        "load": loadavg(),
    }
    if bandwidth:
        info["copy_GBps"] = round(copy_bandwidth(nbytes), 2)
        info["copy_MiB"] = nbytes // MIB
        if info["backend"] != "cpu":  # the accelerator's own roofline
            info["device_copy_GBps"] = round(device_copy_bandwidth(nbytes), 1)
    return info


def machine_lines(info: dict) -> list[str]:
    """:func:`machine` as markdown bullet lines."""
    lines = [f"- JAX {info['jax']}, backend `{info['backend']}`, devices {info['devices']}"
             + (f", XLA_FLAGS `{info['xla_flags']}`" if info.get("xla_flags") else ""),
             f"- {info['cpu']}, {info['cores']} cores, Python {info['python']}; load average "
             f"(1/5/15 min) {info['load']} at the start"]
    if "copy_GBps" in info:
        lines.append(f"- copy bandwidth (NumPy copy of {info['copy_MiB']} MiB float32, bytes "
                     f"read + written, this run): {info['copy_GBps']:.1f} GB/s")
    if "device_copy_GBps" in info:
        lines.append(f"- {info['backend']} device copy bandwidth (jitted copy of "
                     f"{info['copy_MiB']} MiB, this run): {info['device_copy_GBps']:.1f} GB/s")
    return lines


def print_machine(info: dict) -> None:
    print("\n".join(machine_lines(info)), flush=True)


# ----------------------------------------------------------------------------- reports
def md_table(header, rows, align: str | None = None) -> list[str]:
    """Markdown table lines; ``align`` one letter per column, "l" or "r" (default: the first
    column left, the others right)."""
    align = align or "l" + "r" * (len(header) - 1)
    sep = ["---" if a == "l" else "---:" for a in align]
    out = ["| " + " | ".join(map(str, header)) + " |", "|" + "|".join(sep) + "|"]
    out += ["| " + " | ".join(map(str, r)) + " |" for r in rows]
    return out


def write_text(path, text: str) -> Path:
    """Write ``text`` (a string or lines) to ``path``, creating its folder."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    if not isinstance(text, str):
        text = "\n".join(text) + "\n"
    path.write_text(text)
    return path


# ----------------------------------------------------------------------------- workers
def cli_render(args, out, cache, src=None) -> tuple[dict, float]:
    """``python -m difffog render ARGS --out OUT --quiet`` in a new process with
    ``DIFFFOG_CACHE_DIR=cache`` (and ``PYTHONPATH=src`` where given: another source tree);
    returns (its report.json, the command's wall seconds)."""
    env = dict(os.environ, DIFFFOG_CACHE_DIR=str(cache))
    if src is not None:
        env["PYTHONPATH"] = str(src)
    t = time.perf_counter()
    subprocess.run([sys.executable, "-m", "difffog", "render", *args, "--out", str(out),
                    "--quiet"], env=env, check=True, capture_output=True, text=True)
    wall = time.perf_counter() - t
    return json.loads((Path(out) / "report.json").read_text()), wall


def emit_result(row: dict) -> None:
    """What a worker process prints for :func:`run_worker`."""
    print("RESULT " + json.dumps(row), flush=True)


def run_worker(cmd: list[str], env: dict | None = None, label: str = "") -> dict | None:
    """Run a worker in a fresh process; its :func:`emit_result` row, or None (with its stderr
    tail on our stderr) when it failed."""
    r = subprocess.run(cmd, env=env, capture_output=True, text=True)
    line = [s for s in r.stdout.splitlines() if s.startswith("RESULT ")]
    if r.returncode or not line:
        print(f"{label or ' '.join(cmd)}: failed\n{r.stderr[-1500:]}", file=sys.stderr)
        return None
    return json.loads(line[-1][len("RESULT "):])


def host_devices_env(devices: int, platform_: str = "cpu") -> dict:
    """The environment of a worker that needs ``devices`` JAX devices: on a CPU,
    ``XLA_FLAGS=--xla_force_host_platform_device_count=<devices>`` (read when JAX starts)."""
    env = dict(os.environ)
    if platform_ == "cpu":
        env["XLA_FLAGS"] = f"--xla_force_host_platform_device_count={devices}"
        env["JAX_PLATFORMS"] = "cpu"
    return env


def force_host_devices(devices: int) -> None:
    """Ask for ``devices`` host (CPU) devices before JAX starts, unless ``XLA_FLAGS`` already
    says how many; a no-op for 1.  Call it from ``main`` before anything imports JAX."""
    if devices <= 1 or "xla_force_host_platform_device_count" in os.environ.get("XLA_FLAGS", ""):
        return
    if "jax" in sys.modules:
        raise RuntimeError("force_host_devices: JAX is already imported; set XLA_FLAGS="
                           f"--xla_force_host_platform_device_count={devices} before it starts")
    flags = os.environ.get("XLA_FLAGS", "")
    os.environ["XLA_FLAGS"] = f"{flags} --xla_force_host_platform_device_count={devices}".strip()


# ----------------------------------------------------------------------------- references
def reference(scene: str, camera: str, refdir=None):
    """(image float64 (H, W), per-pixel noise RMSE) of a Mitsuba reference (the ones shipped
    with difffog, or those under ``refdir``); SystemExit when there is none."""
    from difffog.study import references

    got = references.reference(scene, camera, refdir)
    if got is None:
        where = refdir or references.references_dir()
        raise SystemExit(f"no reference for {scene}/{camera} under {where}")
    img, noise = got
    return np.asarray(img, np.float64), float(noise or 0.0)


def compare(img, ref, noise_rmse: float) -> dict:
    """Errors of ``img`` against the noisy reference ``ref`` (both (H, W)):
    ``difffog.plot.image_errors`` (bias, rel_rmse, rel_rmse_corr: the reference's noise removed
    in quadrature, ref_noise_rel), the means, and ``rel_rmse_s3``: RMSE / mean(ref) after a
    3×3 box smoothing of both images (one-pixel edge offsets count less), and ``worst5``: the
    share of the squared error in the worst 5% of pixels (edges that land off show as a share
    near 1; noise alone gives ~0.2)."""
    from scipy import ndimage

    from difffog.plot import image_errors

    img = np.asarray(img, np.float64)
    ref = np.asarray(ref, np.float64)
    m = image_errors(img, ref, noise_rmse)
    box = lambda a: ndimage.uniform_filter(a, size=3, mode="nearest")  # noqa: E731
    rmse_s3 = float(np.sqrt(np.mean((box(img) - box(ref)) ** 2)))
    se = np.sort(((img - ref) ** 2).ravel())[::-1]
    worst5 = float(se[:max(1, len(se) // 20)].sum() / max(se.sum(), 1e-300))
    return {"worst5": worst5, "ref_mean": float(ref.mean()), "img_mean": float(img.mean()), "bias": m["bias"],
            "rel_rmse": m["rel_rmse"], "rel_rmse_corr": m["rel_rmse_corr"],
            "rel_rmse_s3": rmse_s3 / float(ref.mean()), "ref_noise_rel": m["ref_noise_rel"]}


def save_comparison_png(path, scene: str, camera: str, ours, ref, label: str, m: dict,
                        noise: float | None = None) -> None:
    """ours | Mitsuba (one tone map) | signed error, titled by ``m["rel_rmse_s3"]``."""
    from matplotlib.figure import Figure

    from difffog import plot

    fig = Figure(figsize=(13, 3.9), layout="compressed")
    axes = fig.subplots(1, 3)
    plot.image_grid({f"difffog ({label})": ours, "Mitsuba 3 reference": ref}, axes=axes[:2])
    plot.error_map(ours, ref, noise=noise, ax=axes[2],
                   title=f"difffog vs Mitsuba; {100 * m['rel_rmse_s3']:.1f}% smoothed 3×3")
    fig.suptitle(f"{scene} / {camera}")
    fig.savefig(path, dpi=72)


# ----------------------------------------------------------------------------- fits
def fit_model(scene, cameras, resolution: int, M: int, downsample: int):
    """The sweep model a fit of ``cameras`` uses (the registry's fit defaults at
    ``resolution`` and ``M``, each camera reduced by ``downsample``, 16·downsample rays in a
    pixel that straddles an edge), built once so that
    several fits (``difffog.fit(..., forward=model)``) share its compiled step."""
    import dataclasses

    import difffog as df

    cams = []
    for name in cameras:
        c = scene.camera(name)
        cams.append(dataclasses.replace(c, resolution=(c.width // downsample,
                                                       c.height // downsample)))
    from difffog._cost import fit_edge_samples

    settings = {**df.SOLVERS["sweep"].fit_defaults, "resolution": resolution, "M": M,
                "edge_samples": fit_edge_samples(downsample)}  # as difffog.fit's own model
    return df.forward_model(scene, "sweep", accuracy=None, cameras=cams, **settings)


# ----------------------------------------------------------------------------- sweep internals
def sweep_problem(scene, N: int, M: int, devices: int = 1, mesh=None, kernel: str = "auto",
                  phase_order="auto", scheme: str = "step"):
    """(geometry, problem, prepare seconds) of the sweep's light problem on an N³ lattice with
    no vacuum margin (float32, the scene's parameters): ``SweepSolver.problem``, the input of
    one Jacobi iteration."""
    import jax
    import jax.numpy as jnp

    import difffog as df

    t = time.perf_counter()
    lat = df.voxelize(scene, N, M)
    kw = {"devices": devices} if devices > 1 else {}
    if mesh is not None:
        kw["mesh"] = tuple(mesh)
    solver = df.SweepSolver(M=M, kernel=kernel, phase_order=phase_order, scheme=scheme, **kw)
    geom = solver.prepare(scene, lat)
    prep_s = time.perf_counter() - t
    pb = jax.jit(solver.problem)(geom, df.Params.from_scene(scene, jnp.float32))
    return geom, pb, prep_s


def jacobi_program(pb, k: int):
    """(compiled, problem, compile seconds): exactly ``k`` Jacobi iterations of a sweep problem
    (the solver's forward iteration ``_iterate`` with tol = 0), compiled ahead of time; call
    ``compiled(problem)``, which returns (Λ, E) and the iteration history."""
    import dataclasses

    import jax

    from difffog.forward.sweep._solver import _iterate  # the internal being measured

    pbk = dataclasses.replace(pb, max_iterations=k, tol=0.0)
    fn = jax.jit(lambda pb: _iterate(pb)[0])
    t = time.perf_counter()
    c = fn.lower(pbk).compile()
    return c, pbk, time.perf_counter() - t


def iteration_seconds(pb, k_iter: int, repeat: int) -> dict:
    """The marginal seconds of one Jacobi iteration: the programs of 1 and ``k_iter``
    iterations timed ``repeat`` times, interleaved (so that load changes hit both alike);
    one-time work that XLA hoists out of the loop shows as ``setup_s``.

    Returns per (list of s/iteration per repeat), s_iter (median), s_best, setup_s,
    compile_s (of the k-iteration program), compiled (it) and out (its last output)."""
    import jax

    c1, pb1, _ = jacobi_program(pb, 1)
    ck, pbk, compile_s = jacobi_program(pb, k_iter)
    jax.block_until_ready(c1(pb1))
    out = jax.block_until_ready(ck(pbk))
    t1, tk = [], []
    for _ in range(repeat):
        t1.append(time_calls(lambda: c1(pb1), 1, first=False).times[0])
        tk.append(time_calls(lambda: ck(pbk), 1, first=False).times[0])
    per = [(b - a) / (k_iter - 1) for a, b in zip(t1, tk)]
    s_iter = statistics.median(per)
    # the best from the two programs' fastest calls (a pair's difference, min(per), can read
    # negative when one call of the pair hit a slow moment); setup from the same, 0 where the
    # noise exceeds it
    s_best = (min(tk) - min(t1)) / (k_iter - 1)
    return dict(per=per, s_iter=s_iter, s_best=s_best, setup_s=max(0.0, min(t1) - s_best),
                compile_s=compile_s, compiled=ck, out=out)


def finite(tree) -> bool:
    """Every leaf of a pytree is finite."""
    import jax

    return bool(all(np.all(np.isfinite(np.asarray(x))) for x in jax.tree.leaves(tree)))

