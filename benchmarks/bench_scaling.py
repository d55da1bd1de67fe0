"""Scaling of the sharded sweep: seconds per Jacobi iteration and memory per device against the
device mesh (faces × u × v) and the lattice size N.

Every case runs in its own process, because the number of host devices is fixed when JAX
starts (``XLA_FLAGS=--xla_force_host_platform_device_count=P``).  On a CPU, P host devices
share the machine's cores: with more devices than cores the figures show the overhead of the
halo exchange, not a speed-up.  On a GPU machine pass ``--platform gpu`` and the mesh uses the
real devices.

Seconds per iteration are the marginal cost (iterations 1 → k, as in bench_sweep.py); memory per
device is XLA's compiled temporary + argument size of the SPMD program (per device).

    python benchmarks/bench_scaling.py [--sizes 64 128] [--M 3] \
        [--meshes 111 211 121 112 221 122] [--out benchmarks/results/scaling.md]
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import statistics
import subprocess
import sys
import time


def worker(N: int, M: int, mesh: tuple[int, int, int], repeat: int, k_iter: int, scene_name: str):
    import dataclasses

    import jax
    import jax.numpy as jnp
    import numpy as np

    from difffog import Params, SweepSolver, load_scene, voxelize
    from difffog._solver import _iterate

    scene = load_scene(scene_name)
    lat = voxelize(scene, N, M)
    devices = int(np.prod(mesh))
    solver = SweepSolver(M=M, devices=devices, mesh=mesh)
    geom = solver.prepare(scene, lat)
    params = Params.from_scene(scene, jnp.float32)
    pb = jax.jit(solver.problem)(geom, params)

    def program(k):
        pbk = dataclasses.replace(pb, max_iterations=k, tol=0.0)
        fn = jax.jit(lambda pb: _iterate(pb)[0])
        t = time.perf_counter()
        c = fn.lower(pbk).compile()
        return c, pbk, time.perf_counter() - t

    c1, pb1, _ = program(1)
    ck, pbk, compile_s = program(k_iter)
    mem = ck.memory_analysis()
    out_k = jax.block_until_ready(ck(pbk))
    jax.block_until_ready(c1(pb1))
    t1, tk = [], []
    for _ in range(repeat):
        t = time.perf_counter()
        jax.block_until_ready(c1(pb1))
        t1.append(time.perf_counter() - t)
        t = time.perf_counter()
        jax.block_until_ready(ck(pbk))
        tk.append(time.perf_counter() - t)
    per = [(b - a) / (k_iter - 1) for a, b in zip(t1, tk)]
    lam = np.asarray(out_k[0])
    return dict(
        N=N, M=M, mesh=list(mesh), devices=devices, shape=list(geom.shape),
        s_iter=statistics.median(per), s_best=min(per), compile_s=compile_s,
        temp_mib=(mem.temp_size_in_bytes / 2**20) if mem else None,
        arg_mib=(mem.argument_size_in_bytes / 2**20) if mem else None,
        checksum=float(lam.astype(np.float64).sum()),
        platform=jax.devices()[0].platform,
    )


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sizes", type=int, nargs="+", default=[64, 128])
    ap.add_argument("--M", type=int, default=3)
    ap.add_argument("--meshes", nargs="+", default=["111", "211", "121", "112", "221", "122"],
                    help="(faces, u, v) as three digits")
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--k-iter", type=int, default=4)
    ap.add_argument("--scene", default="fog-balls")
    ap.add_argument("--platform", default="cpu", choices=["cpu", "gpu"])
    ap.add_argument("--out", default=None)
    ap.add_argument("--worker", default=None, help=argparse.SUPPRESS)
    a = ap.parse_args(argv)
    if a.worker:
        N, M, mesh = json.loads(a.worker)
        print("RESULT " + json.dumps(worker(N, M, tuple(mesh), a.repeat, a.k_iter, a.scene)))
        return 0
    rows = []
    for N in a.sizes:
        for m in a.meshes:
            mesh = tuple(int(c) for c in m)
            P = mesh[0] * mesh[1] * mesh[2]
            env = dict(os.environ)
            if a.platform == "cpu":
                env["XLA_FLAGS"] = f"--xla_force_host_platform_device_count={P}"
                env["JAX_PLATFORMS"] = "cpu"
            cmd = [sys.executable, __file__, "--worker", json.dumps([N, a.M, list(mesh)]),
                   "--repeat", str(a.repeat), "--k-iter", str(a.k_iter), "--scene", a.scene]
            t = time.time()
            r = subprocess.run(cmd, env=env, capture_output=True, text=True)
            line = [s for s in r.stdout.splitlines() if s.startswith("RESULT ")]
            if r.returncode or not line:
                print(f"N={N} mesh={mesh}: failed\n{r.stderr[-1500:]}", file=sys.stderr)
                continue
            row = json.loads(line[0][7:])
            row["load"] = os.getloadavg()[0]
            rows.append(row)
            print(f"N={N} mesh={mesh}: {row['s_iter']:.3f} s/iter, compile {row['compile_s']:.1f} s,"
                  f" temp {row['temp_mib']:.0f} MiB/device ({time.time() - t:.0f} s)", flush=True)
    base = {r["N"]: r["s_iter"] for r in rows if r["devices"] == 1}
    lines = [
        f"# Sharded sweep scaling ({a.scene}, M = {a.M}, float32, {platform.processor() or platform.machine()},"
        f" {os.cpu_count()} cores, platform {a.platform})",
        "",
        f"`python benchmarks/bench_scaling.py --sizes {' '.join(map(str, a.sizes))} --M {a.M} "
        f"--meshes {' '.join(a.meshes)}`",
        "",
        "| N | lattice | mesh (faces, u, v) | devices | s / iteration | speed-up | compile s "
        "| XLA temp MiB / device | args MiB / device | load avg | checksum Σλ |",
        "|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        sp = base.get(r["N"], float("nan")) / r["s_iter"]
        lines.append(
            f"| {r['N']} | {'×'.join(map(str, r['shape']))} | {tuple(r['mesh'])} | {r['devices']} "
            f"| {r['s_iter']:.3f} | {sp:.2f}× | {r['compile_s']:.1f} | {r['temp_mib']:.0f} "
            f"| {r['arg_mib']:.0f} | {r['load']:.1f} | {r['checksum']:.6g} |")
    text = "\n".join(lines) + "\n"
    print(text)
    if a.out:
        with open(a.out, "w") as f:
            f.write(text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
