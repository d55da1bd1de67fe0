"""Benchmark the sweep solver: seconds and ray updates per Jacobi iteration against this machine's
memory bandwidth, compile time and memory, and a forward solve against its gradient.

One Jacobi iteration is six face sweeps; each updates every node along each of the face's
(2M+1)² directions, so an iteration does 6·n_nodes·(2M+1)² ray updates (n_nodes = N³ here: the
lattice is voxelized without a vacuum margin).  A ray update reads and writes one float32 of the
carried radiance at least, so a copy's bandwidth / 8 bytes bounds the rate ("roofline").

Scene: the built-in ``fog-balls`` (fog, an open box and three balls: the surface path with its
segment-blocking mask runs).  ``--quick`` runs N = 64 only and a shorter gradient check.

    python benchmarks/bench_sweep.py [--quick] [--sizes 64 128] [--M 2 3 5] [--repeat 5]
        [--out benchmarks/results/bench_sweep.md]

XLA_FLAGS are read at start-up (before jax is imported), e.g.
``XLA_FLAGS=--xla_force_host_platform_device_count=2`` for ``--devices 2``.
"""

from __future__ import annotations

import argparse
import concurrent.futures as cf
import dataclasses
import os
import platform
import re
import resource
import statistics
import sys
import time

import numpy as np


def _args(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="N = 64 only, smaller gradient check")
    ap.add_argument("--sizes", type=int, nargs="+", default=None)
    ap.add_argument("--M", type=int, nargs="+", default=[2, 3, 5], dest="Ms")
    ap.add_argument("--repeat", type=int, default=5, help="timed iterations per case (median)")
    ap.add_argument("--scene", default="fog-balls")
    ap.add_argument("--devices", type=int, default=1, help="SweepSolver(devices=...) if > 1")
    ap.add_argument("--grad-size", type=int, default=None, help="N of the forward/gradient case")
    ap.add_argument("--no-grad", action="store_true")
    ap.add_argument("--no-bandwidth", action="store_true")
    ap.add_argument("--out", default=None, help="write the markdown report here")
    a = ap.parse_args(argv)
    if a.sizes is None:
        a.sizes = [64] if a.quick else [64, 128]
    if a.grad_size is None:
        a.grad_size = 24 if a.quick else 32
    return a


# jax is imported after the arguments so that --help is fast; XLA_FLAGS must be set before.
import jax  # noqa: E402
import jax.numpy as jnp  # noqa: E402

from difffog import Params, Renderer, SweepSolver, load_scene, voxelize  # noqa: E402
from difffog._solver import _iterate, _jacobi  # noqa: E402

GB = 1e9


def _median_times(fn, repeat):
    times = []
    for _ in range(repeat):
        t = time.perf_counter()
        jax.block_until_ready(fn())
        times.append(time.perf_counter() - t)
    return statistics.median(times), min(times), times


# ---------------------------------------------------------------- memory bandwidth
def bandwidth(nbytes=1 << 30, repeat=7):
    """Copy bandwidth in GB/s (bytes read + bytes written per second): NumPy ``copyto`` into a
    preallocated array on 1 and 2 threads, and a jitted JAX elementwise loop (x → −x, which XLA
    cannot elide, in place)."""
    n = nbytes // 4
    src = np.random.default_rng(0).random(n, dtype=np.float32)
    dst = np.empty_like(src)
    out = {}

    def np1():
        np.copyto(dst, src)

    halves = [(slice(0, n // 2)), slice(n // 2, n)]
    pool = cf.ThreadPoolExecutor(2)

    def np2():  # np.copyto releases the GIL: two threads copy one half each
        list(pool.map(lambda s: np.copyto(dst[s], src[s]), halves))

    for name, fn in (("numpy copy, 1 thread", np1), ("numpy copy, 2 threads", np2)):
        fn()
        med, best, _ = _median_times(lambda: fn() or 0, repeat)
        out[name] = 2 * nbytes / med / GB
    pool.shutdown()
    x = jnp.asarray(src)
    k = 8  # x → −x eight times in a loop: XLA updates the buffer in place (no page faults)
    neg = jax.jit(lambda x: jax.lax.fori_loop(0, k, lambda i, y: -y, x))
    jax.block_until_ready(neg(x))
    med, best, _ = _median_times(lambda: neg(x), max(3, repeat // 2))
    out["jax x → −x in a loop (XLA CPU)"] = 2 * nbytes * k / med / GB
    del x
    return out


# ---------------------------------------------------------------- one Jacobi iteration
def _hlo_ops(text: str) -> int:
    """Instructions in an HLO module's text (lines that assign a value)."""
    return sum(1 for line in text.splitlines() if re.match(r"\s*(ROOT\s+)?%?[\w.\-]+ = ", line))


def iteration_case(scene, N, M, repeat, devices=1, k_iter=4):
    """Seconds per Jacobi iteration as the solver runs it: the forward iteration (``_iterate``,
    a while loop over ``_jacobi``, tol = 0) timed at 1 and ``k_iter`` iterations; the
    difference per extra iteration is the marginal cost of an iteration (one-time work hoisted
    out of the loop by XLA, e.g. the static geometry's face layouts, is reported as setup)."""
    t = time.perf_counter()
    lat = voxelize(scene, N, M)
    kw = {"devices": devices} if devices > 1 else {}
    solver = SweepSolver(M=M, **kw)
    geom = solver.prepare(scene, lat)
    prep_s = time.perf_counter() - t
    params = Params.from_scene(scene, jnp.float32)
    pb = jax.jit(solver.problem)(geom, params)
    zero = jnp.zeros(geom.shape, jnp.float32)
    lowered_step = jax.jit(_jacobi).lower((zero, zero), pb)
    ops_pre = _hlo_ops(lowered_step.as_text(dialect="hlo"))

    def program(k):
        pbk = dataclasses.replace(pb, max_iterations=k, tol=0.0)
        fn = jax.jit(lambda pb: _iterate(pb)[0])
        t = time.perf_counter()
        c = fn.lower(pbk).compile()
        return c, pbk, time.perf_counter() - t

    c1, pb1, _ = program(1)
    ck, pbk, compile_s = program(k_iter)
    mem = ck.memory_analysis()
    ops_opt = _hlo_ops(ck.as_text())
    jax.block_until_ready(c1(pb1))
    jax.block_until_ready(ck(pbk))
    t1, tk = [], []
    for _ in range(repeat):  # interleaved, so that load changes hit both alike
        t1.append(_median_times(lambda: c1(pb1), 1)[0])
        tk.append(_median_times(lambda: ck(pbk), 1)[0])
    per = [(b - a) / (k_iter - 1) for a, b in zip(t1, tk)]
    med = statistics.median(per)
    n_nodes = int(np.prod(geom.shape))
    D = (2 * M + 1) ** 2
    updates = 6 * n_nodes * D
    return dict(
        N=N, M=M, D=D, shape=tuple(geom.shape), prep_s=prep_s, compile_s=compile_s,
        ops_pre=ops_pre, ops_opt=ops_opt,
        temp_mb=mem.temp_size_in_bytes / 2**20 if mem else float("nan"),
        arg_mb=mem.argument_size_in_bytes / 2**20 if mem else float("nan"),
        s_iter=med, s_best=min(per), times=per, setup_s=statistics.median(t1) - med,
        rate=updates / med, updates=updates,
    )


# ---------------------------------------------------------------- forward vs gradient
def grad_case(scene, N, M, repeat=3, devices=1):
    kw = {"devices": devices} if devices > 1 else {}
    r = Renderer(scene, resolution=N, solver=SweepSolver(M=M, tol=1e-4, **kw), supersample=1)
    p = r.params(jnp.float32)
    target = {k: 0.9 * v for k, v in jax.jit(r.__call__)(p).items()}

    def loss(p):
        imgs = r(p)
        return sum(jnp.mean((imgs[k] - target[k]) ** 2) for k in imgs)

    out = {}
    for name, f in (("forward (solve + images)", jax.jit(lambda p: r(p))),
                    ("jax.grad of the image loss", jax.jit(jax.grad(loss)))):
        t = time.perf_counter()
        c = f.lower(p).compile()
        comp = time.perf_counter() - t
        mem = c.memory_analysis()
        jax.block_until_ready(c(p))
        med, best, _ = _median_times(lambda: c(p), repeat)
        out[name] = dict(compile_s=comp, s=med,
                         temp_mb=mem.temp_size_in_bytes / 2**20 if mem else float("nan"))
    light = r.solve(p)
    out["iterations"] = int(light.iterations)
    out["shape"] = tuple(r.lattice.shape)
    g = jax.jit(jax.grad(loss))(p)
    out["grad_finite"] = bool(all(np.all(np.isfinite(np.asarray(x))) for x in jax.tree.leaves(g)))
    return out


def _loadavg():
    try:
        return " / ".join(f"{x:.2f}" for x in os.getloadavg())
    except OSError:
        return "n/a"


def main(argv=None):
    a = _args(argv)
    scene = load_scene(a.scene)
    lines = []

    def emit(s=""):
        print(s, flush=True)
        lines.append(s)

    cpu = "?"
    try:
        with open("/proc/cpuinfo") as f:
            cpu = next(line.split(":", 1)[1].strip() for line in f if line.startswith("model name"))
    except (OSError, StopIteration):
        pass
    emit("# Sweep solver benchmark")
    emit()
    emit(f"- command: `{' '.join([os.path.basename(sys.executable)] + sys.argv)}`")
    emit(f"- XLA_FLAGS: `{os.environ.get('XLA_FLAGS', '')}`")
    emit(f"- jax {jax.__version__}, {len(jax.devices())} × {jax.devices()[0].device_kind}; "
         f"{cpu}, {os.cpu_count()} cores, Python {platform.python_version()}")
    emit(f"- scene `{a.scene}`, float32, lattice N³ (no vacuum margin), timings are medians of "
         f"{a.repeat} warm iterations")
    emit(f"- load average at start (1/5/15 min): {_loadavg()}")
    emit()

    roof = None
    if not a.no_bandwidth:
        bw = bandwidth()
        emit("## Memory bandwidth (1 GiB float32, bytes read + written per second)")
        emit()
        emit("| copy | GB/s | roofline (G ray updates/s at 8 B each) |")
        emit("|---|---:|---:|")
        for k, v in bw.items():
            emit(f"| {k} | {v:.1f} | {v / 8:.2f} |")
        roof = max(bw.values()) / 8 * GB
        emit()

    emit("## One Jacobi iteration (six sweeps)")
    emit()
    emit("| N | M | D | s/iter (median) | min | G ray updates/s | % roofline | setup s "
         "| compile s | HLO ops: Jacobi step lowered / solve compiled | XLA temp MiB | args MiB "
         "| prepare s |")
    emit("|---:|---:|---:|---:|---:|---:|---:|---:|---:|---|---:|---:|---:|")
    results = []
    for N in a.sizes:
        for M in a.Ms:
            r = iteration_case(scene, N, M, a.repeat, a.devices)
            results.append(r)
            pct = f"{100 * r['rate'] / roof:.0f}%" if roof else "–"
            emit(f"| {N} | {M} | {r['D']} | {r['s_iter']:.3f} | {r['s_best']:.3f} "
                 f"| {r['rate'] / GB:.2f} | {pct} | {r['setup_s']:.2f} | {r['compile_s']:.1f} "
                 f"| {r['ops_pre']} / {r['ops_opt']} | {r['temp_mb']:.0f} | {r['arg_mb']:.0f} "
                 f"| {r['prep_s']:.1f} |")
    emit()
    emit("All runs (s/iter): " + "; ".join(
        f"N={r['N']} M={r['M']}: " + ", ".join(f"{t:.3f}" for t in r["times"]) for r in results))
    emit()

    if not a.no_grad:
        M = 3
        g = grad_case(scene, a.grad_size, M, devices=a.devices)
        emit(f"## Forward solve vs gradient (N = {a.grad_size}, lattice {g['shape']} with the "
             f"renderer's vacuum margin, M = {M}, tol 1e-4, {g['iterations']} iterations, "
             f"both cameras, supersample 1)")
        emit()
        emit("| | s (median of 3) | compile s | XLA temp MiB |")
        emit("|---|---:|---:|---:|")
        for k in ("forward (solve + images)", "jax.grad of the image loss"):
            v = g[k]
            emit(f"| {k} | {v['s']:.2f} | {v['compile_s']:.1f} | {v['temp_mb']:.0f} |")
        emit()
        emit(f"Gradient finite: {g['grad_finite']}")
        emit()
    rss = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2**10
    emit(f"- process peak RSS: {rss:.0f} MiB; load average at end: {_loadavg()}")
    if a.out:
        os.makedirs(os.path.dirname(a.out) or ".", exist_ok=True)
        with open(a.out, "w") as f:
            f.write("\n".join(lines) + "\n")


if __name__ == "__main__":
    main()
