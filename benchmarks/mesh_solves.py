"""The device mesh's two open problems (issue 20, item 5), measured: the adjoint GMRES on a
mesh against one device, and batched (vmapped) light solves on a mesh against one device.

Part A (adjoint): fog-balls, N = 11 (its margin 3), M = 2, float64, 8 Jacobi iterations
forward, the gradient of Σ Λ² by the linearised adjoint at rtol 1e-10, on one device and on the
meshes (2,1,1), (1,2,1), (1,2,2) of 4 host devices.  Reported per mesh: the adjoint GMRES's
products and error estimate (read from the solve through a host callback), the gradient's
largest difference from one device's, seconds (compile included).

Part B (batched solves): ``render_batch`` of 4 parameter sets (ζ = 1.5 … 4.5) of fog-balls at
N = 24, M = 2, float32, GMRES to the default tolerance, with the light on one device and on a
2-device mesh (2,1,1): seconds of the second call (compiled), and the largest image difference.
Part A runs each mesh in its own process (4 host devices; one stuck in XLA's rendezvous is
reported, not waited for: once in two runs at stop 62 the (1,2,2) gradient stopped there,
device 0 waiting on one collective while the others waited on another, and XLA ended the
process after 40 s), part B in this one.

    python benchmarks/mesh_solves.py [--out benchmarks/results/mesh_solves.md]
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import time
import warnings

import _common as C


def adjoint_worker(mesh):
    """One mesh's adjoint (part A), in this process: its table row."""
    import jax
    import jax.numpy as jnp
    import numpy as np

    import difffog as df
    import difffog.forward.sweep._implicit as implicit

    jax.config.update("jax_enable_x64", True)
    seen = []
    inner = implicit.gmres

    def counted(*args, **kw):  # the adjoint's GMRES: record its products and error estimate
        out = inner(*args, **kw)
        jax.debug.callback(lambda k, e: seen.append((int(k), float(e))), out[2], out[3])
        return out

    implicit.gmres = counted
    scene = df.load_scene("fog-balls", ["shape.walls.thickness=0.1"])
    lat = df.voxelize(scene, 11, 2, margin=3)
    out = {}
    for m in [(1, 1, 1), tuple(mesh)]:
        solver = df.SweepSolver(M=2, tol=0.0, max_iterations=8, adjoint_rtol=1e-10,
                                devices=int(np.prod(m)), method="jacobi", mesh=m, throw=False,
                                adjoint="linearised")
        geom = solver.prepare(scene, lat)
        p = df.Params.from_scene(scene, jnp.float64)

        def loss(p):
            return jnp.sum(solver.solve(geom, p).fluence ** 2)

        seen.clear()
        t = time.perf_counter()
        with warnings.catch_warnings(record=True) as w:
            warnings.simplefilter("always", df.AdjointWarning)
            g = jax.block_until_ready(jax.jit(jax.grad(loss))(p))
        out[m] = dict(g=np.concatenate([np.ravel(np.asarray(x)) for x in (
            g.scattering, g.absorption, g.albedo, g.sun_irradiance)]),
            k=seen[-1][0], err=seen[-1][1], warnings=len(w), s=time.perf_counter() - t)
    ref, got = out[(1, 1, 1)], out[tuple(mesh)]
    diff = float(np.max(np.abs(got["g"] - ref["g"])) / np.max(np.abs(ref["g"])))
    return [str(tuple(mesh)), int(np.prod(mesh)), got["k"], f"{got['err']:.2e}",
            got["warnings"], f"{diff:.1e}", f"{got['s']:.1f}"]


def adjoint_part(rows):
    for mesh in [(1, 1, 1), (2, 1, 1), (1, 2, 1), (1, 2, 2)]:
        cmd = [sys.executable, __file__, "--worker", json.dumps(list(mesh))]
        try:
            r = subprocess.run(cmd, env=C.host_devices_env(4), capture_output=True, text=True,
                               timeout=300)
            line = [s for s in r.stdout.splitlines() if s.startswith("RESULT ")]
            row = json.loads(line[-1][len("RESULT "):]) if line else None
            why = "" if row else (r.stderr.strip().splitlines() or ["no output"])[-1][:160]
        except subprocess.TimeoutExpired:
            row, why = None, "timed out after 300 s"
        rows.append(row or [str(mesh), int(mesh[0] * mesh[1] * mesh[2]), "–", "–", "–", "–",
                            f"stopped: {why}"])
        print(rows[-1], flush=True)


def batch_part(rows):
    import jax.numpy as jnp
    import numpy as np

    import difffog as df
    from difffog.fit._driver import make_model

    scene = df.load_scene("fog-balls", ["shape.walls.thickness=0.1"])
    images = {}
    for devices in (1, 2):
        m = make_model(scene, "sweep", cameras=["top"], resolution=24, downsample=8,
                       model_settings={"M": 2, "devices": devices})
        p = m.params(jnp.float32)
        sets = [df.set_param(p, scene, "fog.scattering", z) for z in (1.5, 2.5, 3.5, 4.5)]
        times = []
        for _ in range(2):
            t = time.perf_counter()
            out = df.render_batch(m, sets)
            img = np.asarray(out["top"])
            times.append(time.perf_counter() - t)
        images[devices] = img
        diff = float(np.max(np.abs(img - images[1])) / np.max(np.abs(images[1])))
        rows.append([str(m.solver.layout()), devices, f"{times[0]:.2f}", f"{times[1]:.2f}",
                     f"{diff:.1e}"])
        print(rows[-1], flush=True)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", default="benchmarks/results/mesh_solves.md")
    ap.add_argument("--worker", default=None, help=argparse.SUPPRESS)
    a = ap.parse_args(argv)
    if a.worker:
        C.emit_result(adjoint_worker(json.loads(a.worker)))
        return 0
    C.force_host_devices(4)
    info = C.machine()
    C.print_machine(info)
    adj, batch = [], []
    adjoint_part(adj)
    batch_part(batch)
    lines = ["# The device mesh's adjoint and batched solves (`benchmarks/mesh_solves.py`)", ""]
    lines += C.machine_lines(info) + [""]
    lines += ["## Adjoint GMRES (fog-balls N = 11, M = 2, float64, rtol 1e-10, linearised)", ""]
    lines += C.md_table(["mesh", "devices", "adjoint products", "error estimate",
                         "AdjointWarnings", "gradient vs one device", "s (compile incl.)"], adj)
    lines += ["", "(each mesh in its own process beside a one-device run of the same gradient)"]
    lines += ["", "## render_batch of 4 sets (fog-balls N = 24, M = 2, float32, GMRES)", ""]
    lines += C.md_table(["mesh", "devices", "first call s", "second call s",
                         "images vs one device"], batch)
    print(C.write_text(a.out, lines))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
