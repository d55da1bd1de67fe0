"""Benchmark the sweep solver: seconds and ray updates per Jacobi iteration against this machine's
memory bandwidth, compile time and memory, and a forward solve against its gradient.

One Jacobi iteration is six face sweeps (``difffog.forward.sweep._kernel``); each updates every
node along each of the face's (2M+1)² directions, so an iteration does 6·n_nodes·(2M+1)² ray
updates (n_nodes = N³ here: the lattice is voxelized without a vacuum margin).  A ray update
reads and writes one float32 of the carried radiance at least, so a copy's bandwidth / 8 bytes
bounds the rate ("roofline").

The iteration is timed as the solver runs it, through the solver's internals on purpose:
``difffog.forward.sweep._solver._jacobi`` (one iteration, for its HLO size) and ``_iterate``
(the Jacobi loop, via ``_common.jacobi_program``).  The forward/gradient case uses the public
model (``difffog.forward_model``).

Scene: the built-in ``fog-balls`` (fog, an open box and three balls: the surface path with its
segment-blocking mask runs).  ``--quick`` runs N = 16, M = 2 and a small gradient check.

    python benchmarks/bench_sweep.py [--quick] [--sizes 64 128] [--M 2 3 5] [--repeat 5]
        [--devices 2] [--out benchmarks/results/bench_sweep.md]

``--devices P`` on a CPU asks JAX for P host devices (``XLA_FLAGS`` is set in ``main`` before
JAX is imported, unless it already names a device count).
"""

from __future__ import annotations

import argparse
import os
import re
import resource
import sys

import _common as C


def _args(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    C.add_sizes(ap, [64, 128], [16])
    ap.add_argument("--M", type=int, nargs="+", default=None, dest="Ms",
                    help="direction half-widths (default 2 3 5; with --quick 2)")
    ap.add_argument("--repeat", type=int, default=5, help="timed iterations per case (median)")
    ap.add_argument("--scene", default="fog-balls")
    ap.add_argument("--devices", type=int, default=1, help="SweepSolver(devices=...) if > 1")
    ap.add_argument("--kernel", default="auto", choices=["auto", "loop", "batched", "pallas"],
                    help="SweepSolver(kernel=...): the face sweep's program (auto: the backend's)")
    ap.add_argument("--phase-order", nargs="+", default=["auto"],
                    help="SweepSolver(phase_order=...) values (anisotropic scattering; \"auto\": "
                         "the scene's)")
    ap.add_argument("--scheme", default="auto", choices=["auto", "step", "linear", "substep"],
                    help="SweepSolver(scheme=...): the transport along a segment")
    ap.add_argument("--grad-size", type=int, default=None, help="N of the forward/gradient case")
    ap.add_argument("--no-grad", action="store_true")
    ap.add_argument("--no-bandwidth", action="store_true")
    ap.add_argument("--out", default=None, help="write the markdown report here")
    a = C.parse(ap, argv)
    if a.Ms is None:
        a.Ms = [2] if a.quick else [2, 3, 5]
    if a.grad_size is None:
        a.grad_size = 12 if a.quick else 32
    if a.quick:
        a.repeat = min(a.repeat, 2)
    return a


def bandwidth(nbytes: int = 1 << 30, repeat: int = 7) -> dict:
    """Copy bandwidth in GB/s (bytes read + written per second) of ``nbytes`` of float32: NumPy
    ``copyto`` on 1 and 2 threads (``_common.copy_bandwidth``), and a jitted JAX elementwise
    loop (x → −x, which XLA cannot elide, in place)."""
    import jax
    import jax.numpy as jnp
    import numpy as np

    out = {f"numpy copy, {t} thread{'s' if t > 1 else ''}": C.copy_bandwidth(nbytes, repeat, t)
           for t in (1, 2)}
    x = jnp.asarray(np.random.default_rng(0).random(nbytes // 4, dtype=np.float32))
    k = 8  # x → −x eight times in a loop: XLA updates the buffer in place (no page faults)
    neg = jax.jit(lambda x: jax.lax.fori_loop(0, k, lambda i, y: -y, x))
    t = C.time_calls(lambda x=x: neg(x), max(3, repeat // 2))
    out[f"jax x → −x in a loop (XLA {jax.default_backend()})"] = 2 * nbytes * k / t.median / C.GB
    del x
    return out


def _hlo_ops(text: str) -> int:
    """Instructions in an HLO module's text (lines that assign a value)."""
    return sum(1 for line in text.splitlines() if re.match(r"\s*(ROOT\s+)?%?[\w.\-]+ = ", line))


def iteration_case(scene, N, M, repeat, devices=1, k_iter=4, kernel="auto", phase_order="auto",
                   scheme="auto"):
    """Seconds per Jacobi iteration as the solver runs it: the forward iteration (``_iterate``,
    a while loop over ``_jacobi``, tol = 0) timed at 1 and ``k_iter`` iterations; the
    difference per extra iteration is the marginal cost of an iteration (one-time work hoisted
    out of the loop by XLA, e.g. the static geometry's face layouts, is reported as setup)."""
    import jax

    from difffog.forward.sweep._solver import _jacobi, _zero_state  # the internals measured

    geom, pb, prep_s = C.sweep_problem(scene, N, M, devices, kernel=kernel,
                                       phase_order=phase_order, scheme=scheme)
    ops_pre = _hlo_ops(jax.jit(_jacobi).lower(_zero_state(pb), pb).as_text(dialect="hlo"))
    it = C.iteration_seconds(pb, k_iter, repeat)
    D = (2 * M + 1) ** 2
    updates = 6 * int(geom.free.size) * D
    return dict(N=N, M=M, D=D, L=geom.order, shape=tuple(geom.shape), prep_s=prep_s,
                compile_s=it["compile_s"], ops_pre=ops_pre,
                ops_opt=_hlo_ops(it["compiled"].as_text()),
                temp_mb=C.xla_mib(it["compiled"]), arg_mb=C.xla_mib(it["compiled"], "argument"),
                s_iter=it["s_iter"], s_best=it["s_best"], times=it["per"],
                setup_s=it["setup_s"], rate=updates / it["s_iter"], updates=updates)


def grad_case(scene, N, M, repeat=3, devices=1, kernel="auto"):
    """Forward images against ``jax.grad`` of an image loss, compiled ahead of time."""
    import jax
    import jax.numpy as jnp

    import difffog as df

    model = df.forward_model(scene, "sweep", accuracy=None, resolution=N, M=M, tol=1e-4,
                             devices=devices, supersample=1, kernel=kernel)
    p = model.params(jnp.float32)
    target = {k: 0.9 * v for k, v in model(p).items()}

    def loss(m, q):
        imgs = m.images(q)
        return sum(jnp.mean((imgs[k] - target[k]) ** 2) for k in imgs)

    out = {}
    for name, f in (("forward (solve + images)", lambda m, q: m.images(q)),
                    ("jax.grad of the image loss", lambda m, q: jax.grad(lambda x: loss(m, x))(q))):
        c, comp = C.compile_timed(f, model, p)
        t = C.time_calls(lambda: c(model, p), repeat)
        out[name] = dict(compile_s=comp, s=t.median, temp_mb=C.xla_mib(c))
        if name.startswith("jax.grad"):
            out["grad_finite"] = C.finite(c(model, p))
    out["iterations"] = int(model.light(p).iterations)
    out["shape"] = tuple(model.lattice.shape)
    return out


def main(argv=None):
    a = _args(argv)
    C.force_host_devices(a.devices)  # before JAX starts
    import difffog as df

    scene = df.load_scene(a.scene)
    lines = []

    def emit(s=""):
        print(s, flush=True)
        lines.append(s)

    info = C.machine(nbytes=(64 if a.quick else 256) * C.MIB)
    emit("# Sweep solver benchmark")
    emit()
    emit(f"- command: `{' '.join([os.path.basename(sys.executable)] + sys.argv)}`")
    for ln in C.machine_lines(info):
        emit(ln)
    from difffog.forward.sweep import _native

    emit(f"- sweep kernel `{df.SweepSolver(kernel=a.kernel).resolved_kernel()}` "
         f"(`--kernel {a.kernel}`); the step scheme's CPU sweep: {_native.status()}")
    emit(f"- scene `{a.scene}`, float32, lattice N³ (no vacuum margin), timings are medians of "
         f"{a.repeat} warm iterations")
    emit()

    roof = None
    if not a.no_bandwidth:
        nbytes = (64 if a.quick else 1024) * C.MIB
        bw = bandwidth(nbytes, 3 if a.quick else 7)
        emit(f"## Memory bandwidth ({nbytes // C.MIB} MiB float32, bytes read + written per "
             "second)")
        emit()
        for ln in C.md_table(["copy", "GB/s", "roofline (G ray updates/s at 8 B each)"],
                             [[k, f"{v:.1f}", f"{v / 8:.2f}"] for k, v in bw.items()]):
            emit(ln)
        roof = max(bw.values()) / 8 * C.GB
        emit()

    emit("## One Jacobi iteration (six sweeps)")
    emit()
    results, rows = [], []
    orders = [o if o == "auto" else int(o) for o in a.phase_order]
    for N in a.sizes:
        for M, order in ((m, o) for m in a.Ms for o in orders):
            r = iteration_case(scene, N, M, a.repeat, a.devices, kernel=a.kernel,
                               phase_order=order, scheme=a.scheme)
            results.append(r)
            pct = f"{100 * r['rate'] / roof:.0f}%" if roof else "–"
            rows.append([N, M, r["L"], r["D"], f"{r['s_iter']:.3f}", f"{r['s_best']:.3f}",
                         f"{r['rate'] / C.GB:.2f}", pct, f"{r['setup_s']:.2f}",
                         f"{r['compile_s']:.1f}", f"{r['ops_pre']} / {r['ops_opt']}",
                         f"{r['temp_mb']:.0f}", f"{r['arg_mb']:.0f}", f"{r['prep_s']:.1f}"])
            print(f"N={N} M={M} L={r['L']}: {r['s_iter']:.3f} s/iter", flush=True)
    for ln in C.md_table(["N", "M", "phase order L", "D", "s/iter (median)", "min",
                          "G ray updates/s", "% roofline", "setup s", "compile s",
                          "HLO ops: Jacobi step lowered / solve compiled", "XLA temp MiB",
                          "args MiB", "prepare s"], rows, "rrrrrrrrrrlrrr"):
        emit(ln)
    emit()
    emit("All runs (s/iter): " + "; ".join(
        f"N={r['N']} M={r['M']}: " + ", ".join(f"{t:.3f}" for t in r["times"]) for r in results))
    emit()

    if not a.no_grad:
        M = a.Ms[0] if a.quick else 3
        g = grad_case(scene, a.grad_size, M, devices=a.devices, kernel=a.kernel)
        emit(f"## Forward solve vs gradient (N = {a.grad_size}, lattice {g['shape']} with the "
             f"model's vacuum margin, M = {M}, tol 1e-4, {g['iterations']} iterations, "
             f"both cameras, supersample 1)")
        emit()
        keys = ("forward (solve + images)", "jax.grad of the image loss")
        for ln in C.md_table(["", "s (median of 3)", "compile s", "XLA temp MiB"],
                             [[k, f"{g[k]['s']:.2f}", f"{g[k]['compile_s']:.1f}",
                               f"{g[k]['temp_mb']:.0f}"] for k in keys]):
            emit(ln)
        emit()
        emit(f"Gradient finite: {g['grad_finite']}")
        emit()
    rss = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2**10
    emit(f"- process peak RSS: {rss:.0f} MiB; load average at end: {C.loadavg()}")
    if a.out:
        C.write_text(a.out, lines)


if __name__ == "__main__":
    main()
