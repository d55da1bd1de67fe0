"""GMRES's Gram–Schmidt (one Arnoldi step, CGS2) by XLA's products and by the native kernel.

``_krylov.gmres`` orthogonalizes each Krylov vector against the live rows [0, j] of its basis
(restart + 1 rows).  XLA's program (``_krylov._cgs2``) reads every row four times whatever j;
the native kernel (``_native.gram_schmidt``) three times, the live rows only.  Times one call
per j at a state vector of ``--n`` values (default: cloud-plane's default light state, 72³
nodes × 17 channels) and ``--restart`` (default 30, the light solve's), float32, the median of
five warm calls, with the machine's copy bandwidth from the same run.

    python benchmarks/bench_gram_schmidt.py [--n 6345216] [--restart 30] [--js 0 3 10 20 30]
    python benchmarks/bench_gram_schmidt.py --renders cloud-plane fog-balls [--rounds 3]

``--renders``: a default render's light solve of each scene instead, the two Gram–Schmidts
alternated in one process (each round compiles each afresh, then times two renders).
"""

from __future__ import annotations

import argparse
import statistics

import _common as C
import jax
import jax.numpy as jnp

import difffog as df
from difffog.forward.sweep import _krylov, _native


def renders(scenes, rounds: int) -> None:
    native = _krylov._native_gram_schmidt
    times = {}
    for name in scenes:
        scene = df.load_scene(name)
        for _ in range(rounds):
            for how in ("XLA", "native"):
                _krylov._native_gram_schmidt = native if how == "native" else (
                    lambda dtype, asked: False)
                jax.clear_caches()  # the light program traced again, with this Gram–Schmidt
                model = df.forward_model(scene)
                df.render(model)
                for _ in range(2):
                    out = df.render(model)
                    times.setdefault((name, how), []).append(out.timings["light_s"])
                    means = {k: round(float(v.mean()), 5) for k, v in out.images.items()}
                    times.setdefault((name, how, "means"), means)
        _krylov._native_gram_schmidt = native
        for how in ("XLA", "native"):
            ts = times[(name, how)]
            print(f"{name}, {how} Gram–Schmidt: light solve median {statistics.median(ts):.2f} s, "
                  f"min {min(ts):.2f} s ({len(ts)} renders); image means "
                  f"{times[(name, how, 'means')]}", flush=True)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--n", type=int, default=72 ** 3 * 17)
    ap.add_argument("--restart", type=int, default=30)
    ap.add_argument("--js", type=int, nargs="+", default=[0, 3, 10, 20, 30])
    ap.add_argument("--renders", nargs="+", default=None, help="scenes: time default renders")
    ap.add_argument("--rounds", type=int, default=3)
    a = ap.parse_args(argv)
    C.print_machine(C.machine())
    if not _native.available():
        print(f"the native kernel is not built: {_native.status()}")
        return
    if a.renders:
        renders(a.renders, a.rounds)
        return
    V = jax.random.normal(jax.random.key(0), (a.restart + 1, a.n), jnp.float32)
    x = jax.random.normal(jax.random.key(1), (a.n,), jnp.float32)
    xla = jax.jit(_krylov._cgs2)
    native = jax.jit(lambda V, x, j: _native.gram_schmidt(V, x, j + 1))
    mb = V.dtype.itemsize * a.n / 1e6
    print(f"basis {a.restart + 1} rows × {a.n} values ({mb:.1f} MB a row), float32")
    print("| j (live rows − 1) | XLA, ms | native, ms | native, GB/s (3 passes over j + 1 rows) |")
    print("|---:|---:|---:|---:|")
    for j in a.js:
        tx = C.time_calls(lambda: xla(V, x, j), repeat=5).median
        tn = C.time_calls(lambda: native(V, x, j), repeat=5).median
        print(f"| {j} | {tx * 1e3:.1f} | {tn * 1e3:.1f} | {3 * (j + 1) * mb / 1e3 / tn:.1f} |",
              flush=True)


if __name__ == "__main__":
    main()
