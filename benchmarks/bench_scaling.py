"""Scaling of the sharded sweep: seconds per Jacobi iteration and memory per device against the
device mesh (faces × u × v) and the lattice size N.

Every case runs in its own process, because the number of host devices is fixed when JAX
starts (``XLA_FLAGS=--xla_force_host_platform_device_count=P``).  On a CPU, P host devices
share the machine's cores: with more devices than cores the figures show the overhead of the
halo exchange, not a speed-up.  On a GPU machine pass ``--platform gpu`` and the mesh uses the
real devices.

Seconds per iteration are the marginal cost (iterations 1 → k, as in bench_sweep.py, through
the solver's internal ``difffog.forward.sweep._solver._iterate`` on purpose:
``_common.iteration_seconds``); memory per device is XLA's compiled temporary + argument size
of the SPMD program (per device).  The report starts with the machine (JAX backend and devices,
copy bandwidth) measured in the same run.

    python benchmarks/bench_scaling.py [--quick] [--sizes 64 128] [--M 3] \
        [--meshes 111 211 121 112 221 122] [--out benchmarks/results/scaling.md]
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time

import _common as C


def worker(N: int, M: int, mesh: tuple[int, int, int], repeat: int, k_iter: int, scene_name: str):
    import jax
    import numpy as np

    import difffog as df

    scene = df.load_scene(scene_name)
    devices = int(np.prod(mesh))
    geom, pb, _ = C.sweep_problem(scene, N, M, devices, mesh)
    it = C.iteration_seconds(pb, k_iter, repeat)
    lam = np.asarray(it["out"][0])
    return dict(
        N=N, M=M, mesh=list(mesh), devices=devices, shape=list(geom.shape),
        s_iter=it["s_iter"], s_best=it["s_best"], compile_s=it["compile_s"],
        temp_mib=C.xla_mib(it["compiled"]), arg_mib=C.xla_mib(it["compiled"], "argument"),
        checksum=float(lam.astype(np.float64).sum()),
        platform=jax.devices()[0].platform,
    )


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    C.add_sizes(ap, [64, 128], [16])
    ap.add_argument("--M", type=int, default=None, help="default 3; with --quick 2")
    ap.add_argument("--meshes", nargs="+", default=None,
                    help="(faces, u, v) as three digits (default 111 211 121 112 221 122; "
                         "with --quick 111 211)")
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--k-iter", type=int, default=4)
    ap.add_argument("--scene", default="fog-balls")
    ap.add_argument("--platform", default="cpu", choices=["cpu", "gpu"])
    ap.add_argument("--out", default=None)
    ap.add_argument("--worker", default=None, help=argparse.SUPPRESS)
    a = C.parse(ap, argv)
    a.M = a.M or (2 if a.quick else 3)
    a.meshes = a.meshes or (["111", "211"] if a.quick else
                            ["111", "211", "121", "112", "221", "122"])
    if a.worker:
        N, M, mesh = json.loads(a.worker)
        C.emit_result(worker(N, M, tuple(mesh), a.repeat, a.k_iter, a.scene))
        return 0
    info = C.machine()
    C.print_machine(info)
    rows = []
    for N in a.sizes:
        for m in a.meshes:
            mesh = tuple(int(c) for c in m)
            P = mesh[0] * mesh[1] * mesh[2]
            cmd = [sys.executable, __file__, "--worker", json.dumps([N, a.M, list(mesh)]),
                   "--repeat", str(a.repeat), "--k-iter", str(a.k_iter), "--scene", a.scene]
            t = time.time()
            row = C.run_worker(cmd, C.host_devices_env(P, a.platform), f"N={N} mesh={mesh}")
            if row is None:
                continue
            row["load"] = os.getloadavg()[0]
            rows.append(row)
            print(f"N={N} mesh={mesh}: {row['s_iter']:.3f} s/iter, compile {row['compile_s']:.1f} s,"
                  f" temp {row['temp_mib']:.0f} MiB/device ({time.time() - t:.0f} s)", flush=True)
    base = {r["N"]: r["s_iter"] for r in rows if r["devices"] == 1}
    lines = [
        f"# Sharded sweep scaling ({a.scene}, M = {a.M}, float32, platform {a.platform})",
        "",
        f"`python benchmarks/bench_scaling.py --sizes {' '.join(map(str, a.sizes))} --M {a.M} "
        f"--meshes {' '.join(a.meshes)}`",
        "",
        *C.machine_lines(info),
        "- (the devices above are the parent process's; each case ran in its own process with "
        "the devices of its row)",
        "",
    ]
    lines += C.md_table(
        ["N", "lattice", "mesh (faces, u, v)", "devices", "s / iteration", "speed-up",
         "compile s", "XLA temp MiB / device", "args MiB / device", "load avg", "checksum Σλ"],
        [[r["N"], "×".join(map(str, r["shape"])), tuple(r["mesh"]), r["devices"],
          f"{r['s_iter']:.3f}", f"{base.get(r['N'], float('nan')) / r['s_iter']:.2f}×",
          f"{r['compile_s']:.1f}", f"{r['temp_mib']:.0f}", f"{r['arg_mib']:.0f}",
          f"{r['load']:.1f}", f"{r['checksum']:.6g}"] for r in rows],
        "l" * 11)
    text = "\n".join(lines) + "\n"
    print(text)
    if a.out:
        C.write_text(a.out, text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
