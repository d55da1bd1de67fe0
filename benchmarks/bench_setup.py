"""Everything before the sweep's first iteration: host set-up (voxelize, prepare, the cameras'
exact hits) and the solve's fixed passes (the first-collision sun and sky, segment depths:
``SweepSolver.problem``), against the time of one iteration.

    python benchmarks/bench_setup.py                       # fog-balls, N 64 128, M 3 5
    python benchmarks/bench_setup.py --scenes fog-balls ring-box --sizes 128 --ms 5
    python benchmarks/bench_setup.py --quick --out /tmp/setup   # N 16, M 2

Per row, in this process: ``forward_model(scene, "sweep", resolution=N, M=M)`` builds the model
and records its set-up stages (``model.host.setup_s``: voxelize, prepare, camera hits; best of
``--repeat`` builds); the fixed passes are ``jax.jit(solver.problem)`` warm (median of 3); an
iteration is the marginal time of Jacobi iterations (``_common.iteration_seconds``).  Writes
setup.md (with the machine: backend, devices, copy bandwidth measured in the same run) to
``--out`` (default benchmarks/results).
"""

from __future__ import annotations

import argparse
import os
import sys
import time

import _common as C


def row(scene_name: str, N: int, M: int, repeat: int) -> dict:
    import jax
    import jax.numpy as jnp

    import difffog as df

    scene = df.load_scene(scene_name)
    stages = None
    for _ in range(repeat):
        t = time.perf_counter()
        model = df.forward_model(scene, "sweep", accuracy=None, resolution=N, M=M, force=True)
        total = time.perf_counter() - t
        s = dict(model.host.setup_s, total_s=total)
        if stages is None or s["total_s"] < stages["total_s"]:
            stages = s
    geom, solver = model.geometry, model.solver
    p = model.params(jnp.float32)
    problem = jax.jit(solver.problem)
    problem(geom, p).ssa.block_until_ready()
    fixed = C.time_calls(lambda: problem(geom, p), 3)
    it = C.iteration_seconds(problem(geom, p), 3, 3)
    before_first = stages["total_s"] + fixed.median
    r = dict(scene=scene_name, N=N, M=M, shape="×".join(map(str, model.lattice.shape)),
             voxelize_s=stages["voxelize_s"], prepare_s=stages["prepare_s"],
             camera_hits_s=stages["camera_hits_s"], host_s=stages["total_s"],
             fixed_s=fixed.median, iteration_s=it["s_iter"], before_first_s=before_first,
             kernel=getattr(solver, "resolved_kernel", lambda: "loop")())  # (older commits)
    print({k: (round(v, 3) if isinstance(v, float) else v) for k, v in r.items()}, flush=True)
    return r


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    C.add_sizes(ap, [64, 128], [16])
    ap.add_argument("--ms", type=int, nargs="+", default=None, help="M values (default 3 5)")
    ap.add_argument("--scenes", nargs="+", default=["fog-balls"])
    ap.add_argument("--repeat", type=int, default=2, help="model builds per row (best)")
    ap.add_argument("--out", default=str(C.RESULTS))
    a = C.parse(ap, argv)
    ms = a.ms or ([2] if a.quick else [3, 5])
    info = C.machine()
    rows = [row(s, N, M, a.repeat) for s in a.scenes for N in a.sizes for M in ms]
    lines = ["# Set-up before the first iteration", "",
             f"- command: `{' '.join([os.path.basename(sys.executable)] + sys.argv)}`",
             *C.machine_lines(info),
             "- host set-up: best of the model builds; fixed passes (first-collision sun and sky, "
             "segment depths: `SweepSolver.problem`) warm, median of 3; one iteration: the "
             "marginal time of a Jacobi iteration", ""]
    lines += C.md_table(
        ["scene", "N", "M", "lattice", "voxelize s", "prepare s", "camera hits s", "host total s",
         "fixed passes s", "1 iteration s", "before the first iteration s", "fixed / iteration"],
        [[r["scene"], r["N"], r["M"], r["shape"], f"{r['voxelize_s']:.2f}",
          f"{r['prepare_s']:.2f}", f"{r['camera_hits_s']:.2f}", f"{r['host_s']:.2f}",
          f"{r['fixed_s']:.2f}", f"{r['iteration_s']:.3f}", f"{r['before_first_s']:.2f}",
          f"{r['fixed_s'] / r['iteration_s']:.2f}"] for r in rows], "lrrlrrrrrrrr")
    lines += ["", f"Sweep kernel: {rows[0]['kernel']} (the backend's). Compilation is not "
              "counted (the fixed passes and the iteration are timed warm)."]
    C.write_text(os.path.join(a.out, "setup.md"), "\n".join(lines) + "\n")


if __name__ == "__main__":
    main()
