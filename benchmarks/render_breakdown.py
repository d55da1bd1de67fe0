"""Where a render's time goes: set-up, compile (first and from XLA's persistent cache), the
light solve's fixed passes and its iterations, and the cameras, through the command line.

For each case (a scene and ``difffog render`` options), in new processes on an empty
``DIFFFOG_CACHE_DIR`` of this run's own (the native library already built):

* the render as asked, twice (``first``: compiling; ``cached``: its programs from the cache),
  ``report.json``'s timings and the light solve's iterations;
* the same settings with ``--method jacobi --iterations 1`` and ``--iterations K`` (cached):
  one iteration's seconds, (light(K) − light(1)) / (K − 1), and the fixed passes (the sun's
  and the sky's first collision, the sources), light(1) − one iteration.

The render's light solve is then split into its fixed passes and the rest (its iterations,
GMRES's own arithmetic included).  The report starts with the machine and its copy bandwidth
(1 and 2 threads), measured in the same run; G ray updates/s = 6·nodes·(2M+1)² per iteration
over its seconds, and its ratio to the 2-thread copy's roofline (8 bytes an update).

    PYTHONPATH=src python benchmarks/render_breakdown.py              # fog-balls default
    PYTHONPATH=src python benchmarks/render_breakdown.py --cases "fog-balls" \\
        "fog-balls -N 128 -M 5" "fog-balls -N 128 -M 5 --devices 2"
"""

from __future__ import annotations

import argparse
import shlex
import tempfile
from pathlib import Path

import _common as C


def _render(args, cache, out):
    return C.cli_render(args, out, cache)[0]


def _case(spec, K, tmp):
    args = shlex.split(spec)
    cache = Path(tmp) / ("cache_" + "_".join(args).replace("-", ""))
    first = _render(args, cache, Path(tmp) / "first")
    cached = _render(args, cache, Path(tmp) / "cached")
    j1 = _render(args + ["--method", "jacobi", "--iterations", "1"], cache, Path(tmp) / "j1")
    jk = _render(args + ["--method", "jacobi", "--iterations", str(K)], cache, Path(tmp) / "jk")
    per_it = (jk["timings_s"]["light_s"] - j1["timings_s"]["light_s"]) / (K - 1)
    fixed = j1["timings_s"]["light_s"] - per_it
    t = cached["timings_s"]
    setup = t["voxelize_s"] + t["prepare_s"] + t["camera_hits_s"]
    opts = cached["settings"]["solver_options"]
    shape = cached["settings"]["lattice_shape"]
    nodes = shape[0] * shape[1] * shape[2]
    updates = 6 * nodes * (2 * opts["M"] + 1) ** 2
    return dict(spec=spec, shape=shape, M=opts["M"], method=opts["method"],
                devices=opts["devices"], iterations=cached["iterations"],
                setup=setup, compile_first=(first["timings_s"]["light_compile_s"],
                                            first["timings_s"]["images_compile_s"]),
                compile_cached=(t["light_compile_s"], t["images_compile_s"]),
                light=t["light_s"], fixed=fixed, per_it=per_it, cameras=t["images_s"],
                total=cached["total_s"], gups=updates / per_it / 1e9)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cases", nargs="+", default=["fog-balls"])
    ap.add_argument("--K", type=int, default=6, help="Jacobi iterations of the long run")
    ap.add_argument("--out", default=str(C.RESULTS / "render_breakdown.md"))
    a = ap.parse_args(argv)
    info = C.machine()
    copy2 = C.copy_bandwidth(1024 * C.MIB, threads=2)
    roof = copy2 / 8
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for spec in a.cases:
            r = _case(spec, a.K, tmp)
            rest = r["light"] - r["fixed"]
            rows.append([f"`difffog render {r['spec']}`", "×".join(map(str, r["shape"])),
                         str(r["M"]), str(r["devices"]), f"{r['setup']:.2f}",
                         f"{r['compile_first'][0]:.2f} + {r['compile_first'][1]:.2f}",
                         f"{r['compile_cached'][0]:.2f} + {r['compile_cached'][1]:.2f}",
                         f"{r['fixed']:.2f}", f"{rest:.2f} ({r['iterations']})",
                         f"{r['per_it']:.3f}", f"{r['gups']:.2f}",
                         f"{100 * r['gups'] / roof:.0f}%", f"{r['cameras']:.2f}",
                         f"{r['total']:.1f}"])
            print(rows[-1], flush=True)
    lines = ["# A render's time, part by part", "",
             "`PYTHONPATH=src python benchmarks/render_breakdown.py` (see its docstring)", "",
             *C.machine_lines(info),
             f"- copy bandwidth, 2 threads (NumPy copyto of 1024 MiB, this run): {copy2:.1f} "
             f"GB/s: a roofline of {roof:.2f} G updates/s at 8 bytes each", "",
             *C.md_table(["command", "lattice", "M", "devices", "set-up s",
                          "compile s, first (light + cameras)", "compile s, from the cache",
                          "fixed passes s", "iterations s (count)", "s / Jacobi iteration",
                          "G updates/s", "% of 2-thread copy roofline", "cameras s",
                          "total s (cached)"], rows)]
    C.write_text(a.out, lines)


if __name__ == "__main__":
    main()
