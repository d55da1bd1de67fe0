"""The cameras' programs for several march chunks and lanes, in one process, their runs
interleaved: which chunk of rays a CPU should march at a time.

Per scene (its default preset), the light is solved once; then for each CHUNK:LANES variant
(``_march.MARCH_CHUNK_CPU``, the model's ``march_lanes``) the program ``--program`` is
compiled: ``images`` (``SweepModel.images_from``, a render's), ``jvp`` (the images' tangents
along ζ, γ and the sky at once, in forward mode: a fit's Jacobian columns) or ``vjp`` (the
gradient of the images' sum, the light held: a density fit's), and the programs are run in
turn ``--rounds`` times
(interleaved, so that the host's load changes hit them alike).  Reported: compile seconds and
the median and best run.  One process for all variants: the differences are the programs',
not the host's hour (a 2-core VM whose neighbours' load moves a run by ±50%).

    PYTHONPATH=src python benchmarks/camera_chunks.py --scenes fog-balls translucent-cube \\
        cloud-tomo cloud-plane --variants 16384:2 16384:1 8192:1 4096:1 4096:2
    PYTHONPATH=src python benchmarks/camera_chunks.py --program vjp --variants 16384:2 4096:2
"""

from __future__ import annotations

import argparse
import statistics as st
import subprocess
import sys

import _common as C
from camera_march import PROGRAMS

CHILD = r"""
import json, sys, time
import jax, jax.numpy as jnp
import difffog as df
from difffog.forward.sweep import _march, _model
from difffog.forward.sweep._march import forward_mode
from difffog.forward._model import light_jit
scene, rounds, program = sys.argv[1], int(sys.argv[2]), sys.argv[3]
variants = [tuple(map(int, v.split(":"))) for v in sys.argv[4:]]
m = df.forward_model(df.load_scene(scene))
p = m.params()
light = light_jit(m, p)
paths = ["fog.scattering", "fog.absorption", "sky.radiance"]
z = jnp.asarray([float(df.get_param(p, m.scene, q)) for q in paths])
""" + PROGRAMS + r"""
fn, arg = {"images": (images, p), "jvp": (jvp, z), "vjp": (vjp, p)}[program]
progs = []
for chunk, lanes in variants:
    _march.MARCH_CHUNK_CPU = chunk  # read when the program is traced
    mv = _model._with_static(m, march_lanes=lanes)
    t = time.perf_counter()
    # a new function each time: jax.jit's cache would serve the first variant's program (the
    # chunk is read when tracing, and the model's pytree does not hold it)
    c = jax.jit(lambda m, l, a: fn(m, l, a)).lower(mv, light, arg).compile()
    progs.append((chunk, lanes, mv, c, time.perf_counter() - t, []))
    jax.block_until_ready(c(mv, light, arg))
for _ in range(rounds):
    for chunk, lanes, mv, c, _, ts in progs:
        t = time.perf_counter()
        jax.block_until_ready(c(mv, light, arg))
        ts.append(time.perf_counter() - t)
print(json.dumps([dict(chunk=ch, lanes=la, compile=tc, runs=ts)
                  for ch, la, _, _, tc, ts in progs]))
"""


def main(argv=None):
    import json

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scenes", nargs="+", default=["fog-balls", "cloud-tomo"])
    ap.add_argument("--variants", nargs="+", default=["16384:2", "16384:1", "4096:1", "4096:2"],
                    metavar="CHUNK:LANES")
    ap.add_argument("--rounds", type=int, default=7)
    ap.add_argument("--program", default="images", choices=["images", "jvp", "vjp"])
    ap.add_argument("--out", default=str(C.RESULTS / "camera_chunks.md"))
    a = ap.parse_args(argv)
    info = C.machine()
    rows = []
    for scene in a.scenes:
        r = subprocess.run([sys.executable, "-c", CHILD, scene, str(a.rounds), a.program,
                            *a.variants],
                           capture_output=True, text=True)
        if r.returncode:
            raise SystemExit(f"{scene}: the child failed:\n{r.stderr[-3000:]}")
        for v in json.loads(r.stdout.strip().splitlines()[-1]):
            rows.append([scene, a.program, str(v["chunk"]), str(v["lanes"]),
                         f"{v['compile']:.2f}",
                         f"{st.median(v['runs']):.3f}", f"{min(v['runs']):.3f}"])
            print(rows[-1], flush=True)
    lines = ["# The cameras' programs by march chunk and lanes", "",
             f"`PYTHONPATH=src python benchmarks/camera_chunks.py` (see its docstring); default "
             f"presets, one process per scene, {a.rounds} interleaved runs of each program", "",
             *C.machine_lines(info), "",
             *C.md_table(["scene", "program", "chunk (rays)", "lanes", "compile s",
                          "run s, median",
                          "run s, best"], rows)]
    C.write_text(a.out, lines)


if __name__ == "__main__":
    main()
