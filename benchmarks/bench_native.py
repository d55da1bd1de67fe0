"""One face sweep of a scene's lattice: the step scheme's native CPU kernel on 1 and 2 threads
against XLA's loop (``difffog.forward.sweep._native``, ``_kernel._sweep_face_loop``).

    python benchmarks/bench_native.py [--scene fog-balls] [--N 128] [--M 5] [--face 0]

Random sources and radiosity, optical depth 0..0.1 per half step in the fog, the scene's own
geometry (free, surface and solid nodes, normals, blocking bits); float32; the best of three
warm calls each, with the machine's copy bandwidth from the same run.
"""

from __future__ import annotations

import argparse
import time

import _common as C
import jax
import jax.numpy as jnp
import numpy as np

import difffog as df
from difffog.forward.sweep import _kernel as K
from difffog.forward.sweep import _native
from difffog.forward.sweep._solver import SweepSolver
from difffog.geometry._lattice import voxelize


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scene", default="fog-balls")
    ap.add_argument("--N", type=int, default=128)
    ap.add_argument("--M", type=int, default=5)
    ap.add_argument("--face", type=int, default=0)
    a = ap.parse_args(argv)
    scene = df.load_scene(a.scene)
    geom = SweepSolver(M=a.M).prepare(scene, voxelize(scene, a.N, a.M))
    geo, consts = geom.faces[a.face], geom.consts[a.face]
    shape = geo.free.shape
    rng = np.random.default_rng(0)
    f32 = lambda x: jnp.asarray(x, jnp.float32)  # noqa: E731
    args = (f32(rng.random(shape)), f32(rng.random(shape)),
            f32(0.1 * rng.random(shape) * np.asarray(geo.free)),
            f32(rng.random((2 * a.M + 1) ** 2)), geo, consts)
    kw = dict(M=a.M, periodic=(False,) * 3, warmup=0, surfaces=bool(scene.shapes),
              vol=(True, True, None))
    C.print_machine(C.machine())
    updates = int(np.prod(shape)) * (2 * a.M + 1) ** 2
    threads = _native._threads
    for mode in ("xla", "native 1 thread", "native 2 threads"):
        _native._STATE.clear()
        if mode == "xla":
            _native._STATE.update(ok=False, why="off (benchmark)")
        else:
            n = int(mode.split()[1])
            _native._threads = lambda n=n: n
            if not _native.available():
                print(f"{mode}: {_native.status()}")
                continue
        f = jax.jit(lambda *x: K._sweep_face_loop(*x, **kw))
        jax.block_until_ready(f(*args))
        best = np.inf
        for _ in range(3):
            t = time.perf_counter()
            jax.block_until_ready(f(*args))
            best = min(best, time.perf_counter() - t)
        print(f"{a.scene} N={a.N} M={a.M} face {a.face} {shape}: {mode}: {best * 1e3:.1f} ms, "
              f"{updates / best / 1e9:.2f} G updates/s", flush=True)
    _native._threads = threads


if __name__ == "__main__":
    main()
