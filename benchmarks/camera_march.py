"""The cameras' march: compile and run time of a model's camera programs, for one or more
source trees alternated in one run (each measurement in a new process, JAX's persistent cache
off).

Per scene (its default preset unless ``--N``/``--M``), the programs a render and a fit compile
for the cameras, given a solved light:

* ``images``: the images from the light (``SweepModel.images_from``), as a render runs it;
* ``jvp``: the images' tangents along ``--unknowns`` unknowns at once (``jax.vmap`` of
  ``jax.jvp`` inside ``forward_mode()``), as a fit's Jacobian takes the cameras' columns;
* ``vjp``: the gradient of Σ images with respect to the parameters, the light held (the
  march's hand-written reverse pass), as a loss gradient takes it.

Each: XLA compile seconds (cold) and the best of ``--repeat`` warm runs.  The first tree is the
reference; each other tree's images, tangents and gradient are compared with its (max |Δ| over
max |ref|).  To compare with an earlier commit: ``git worktree add /tmp/old <commit>`` and
``--trees /tmp/old .``.  ``--variants CHUNK:LANES ...`` runs each tree also with other march
chunks and lanes on a CPU (``_march.MARCH_CHUNK_CPU``, the model's ``march_lanes``, or
``MARCH_LANES`` in a tree of stops 80-81; the rays a march takes at a time, and how many
marches run side by side).

    PYTHONPATH=src python benchmarks/camera_march.py --trees /tmp/old .  # results/camera_march.md
"""

from __future__ import annotations

import argparse
import json
import os
import statistics as st
import subprocess
import sys
import tempfile
from pathlib import Path

import _common as C

ROOT = Path(__file__).resolve().parents[1]

# the cameras' programs, each called (model, light, arg): ``images`` and ``vjp`` take the
# parameters ``p``, ``jvp`` the unknowns' values ``z`` (global: the model ``m``, ``paths``)
PROGRAMS = r"""
def at(x):
    q = p
    for i, path in enumerate(paths):
        q = df.set_param(q, m.scene, path, x[i])
    return q

def images(m, l, q):
    return m.images_from(l, q)

def jvp(m, l, x):
    with forward_mode():
        return jax.vmap(lambda e: jax.jvp(lambda y: m.images_from(l, at(y)), (x,), (e,))[1])(
            jnp.eye(len(paths), dtype=x.dtype))

def vjp(m, l, q):
    return jax.grad(lambda r: sum(jnp.sum(v) for v in m.images_from(l, r).values()))(q)
"""

CHILD = r"""
import json, sys, time
import numpy as np
import equinox as eqx, jax, jax.numpy as jnp
import difffog as df
from difffog.forward.sweep import _march
from difffog.forward.sweep._march import forward_mode
scene, N, M, n_unk, repeat, out = sys.argv[1], int(sys.argv[2]), int(sys.argv[3]), \
    int(sys.argv[4]), int(sys.argv[5]), sys.argv[6]
if sys.argv[7] != "-":  # a variant: the CPU's march chunk and lanes
    _march.MARCH_CHUNK_CPU = int(sys.argv[7])
if sys.argv[8] != "-" and hasattr(_march, "MARCH_LANES"):  # a tree of stops 80-81
    _march.MARCH_LANES = int(sys.argv[8])
kw = {} if N == 0 else {"resolution": N, "M": M}
m = df.forward_model(df.load_scene(scene), "sweep", **kw)
if sys.argv[8] != "-" and hasattr(m, "march_lanes"):  # the model's lanes (stop 81 on)
    from difffog.forward.sweep._model import _with_static
    m = _with_static(m, march_lanes=int(sys.argv[8]))
p = m.params()
light = m.light(p)
paths = ["fog.scattering", "fog.absorption", "sky.radiance"][:n_unk]
z = jnp.asarray([float(df.get_param(p, m.scene, q)) for q in paths])
""" + PROGRAMS + r"""
res, arrays = {}, {}
for name, fn, arg in (("images", images, p), ("jvp", jvp, z), ("vjp", vjp, p)):
    t = time.perf_counter()
    comp = eqx.filter_jit(fn).lower(m, light, arg).compile()
    c = time.perf_counter() - t
    val = jax.block_until_ready(comp(m, light, arg))
    ts = []
    for _ in range(repeat):
        t = time.perf_counter()
        jax.block_until_ready(comp(m, light, arg))
        ts.append(time.perf_counter() - t)
    res[name] = [c, min(ts)]
    for i, leaf in enumerate(jax.tree.leaves(val)):
        arrays[f"{name}{i}"] = np.asarray(leaf)
rays = sum(int(h.pixel.shape[0]) for h in m.hits) if m.hits is not None else None
res["rays"] = rays
res["cameras"] = len(m.cameras)
np.savez(out, **arrays)
print(json.dumps(res))
"""


def _run(tree, scene, N, M, unknowns, repeat, out, variant=("-", "-")):
    env = dict(os.environ, PYTHONPATH=str(Path(tree).resolve() / "src"),
               DIFFFOG_CACHE_DIR="off")
    r = subprocess.run([sys.executable, "-c", CHILD, scene, str(N), str(M), str(unknowns),
                        str(repeat), out, *variant], env=env, capture_output=True, text=True)
    if r.returncode:
        raise SystemExit(f"{tree} {scene}: the child failed:\n{r.stderr[-3000:]}")
    return json.loads(r.stdout.strip().splitlines()[-1])


def _diff(ref, new):
    import numpy as np

    a, b = np.load(ref), np.load(new)
    return max(float(np.max(np.abs(a[k] - b[k])) / max(float(np.max(np.abs(a[k]))), 1e-30))
               for k in a.files)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--trees", nargs="+", default=[str(ROOT)])
    ap.add_argument("--scenes", nargs="+", default=["fog-balls", "cloud-tomo"])
    ap.add_argument("--N", type=int, default=0, help="resolution (0: the scene's default)")
    ap.add_argument("--M", type=int, default=3)
    ap.add_argument("--unknowns", type=int, default=3)
    ap.add_argument("--rounds", type=int, default=2)
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--variants", nargs="+", default=["-:-"], metavar="CHUNK:LANES",
                    help="on a CPU, each tree also with these march chunks and lanes "
                         "(_march.MARCH_CHUNK_CPU, the model's march_lanes; '-': the tree's own), "
                         "e.g. "
                         "16384:2 4096:1")
    ap.add_argument("--out", default=str(C.RESULTS / "camera_march.md"))
    a = ap.parse_args(argv)
    runs = [(tree, tuple(v.split(":"))) for tree in a.trees for v in a.variants]
    info = C.machine()
    got = {}
    with tempfile.TemporaryDirectory() as tmp:
        for r in range(a.rounds):
            for scene in a.scenes:
                order = list(enumerate(runs))
                for i, (tree, variant) in (order if r % 2 == 0 else order[::-1]):
                    out = str(Path(tmp) / f"{scene}_{i}_{r}.npz")
                    res = _run(tree, scene, a.N, a.M, a.unknowns, a.repeat, out, variant)
                    got.setdefault((scene, tree, ":".join(variant)), []).append((res, out))
                    print(scene, tree, variant, res, flush=True)
                for i in range(len(runs)):  # against the first run of the round
                    key = (scene, runs[i][0], ":".join(runs[i][1]))
                    got[key][-1][0]["diff"] = _diff(str(Path(tmp) / f"{scene}_0_{r}.npz"),
                                                    got[key][-1][1])
    rows = []
    for (scene, tree, variant), rs in got.items():
        rs = [x for x, _ in rs]

        def med(name, k):
            return st.median(x[name][k] for x in rs)
        rows.append([scene, str(rs[0]["cameras"]), str(rs[0]["rays"]),
                     tree if variant == "-:-" else f"{tree} (chunk:lanes {variant})",
                     *(f"{med(n, 0):.2f} / {med(n, 1):.3f}" for n in ("images", "jvp", "vjp")),
                     f"{max(x['diff'] for x in rs):.1e}"])
    lines = ["# The cameras' march: compile and run seconds", "",
             "`PYTHONPATH=src python benchmarks/camera_march.py` (see its docstring); "
             f"{'default presets' if a.N == 0 else f'N = {a.N}, M = {a.M}'}, "
             f"{a.unknowns} unknowns, medians of {a.rounds} rounds (new processes, alternated), "
             f"runs the best of {a.repeat}", "",
             *C.machine_lines(info), "",
             *C.md_table(["scene", "cameras", "rays", "tree", "images: compile s / run s",
                          f"jvp ({a.unknowns} columns): compile / run", "vjp: compile / run",
                          "max rel. difference from the first tree"], rows)]
    C.write_text(a.out, lines)


if __name__ == "__main__":
    main()
