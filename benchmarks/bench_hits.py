"""The host cost of exact camera hits: set-up seconds per camera (``camera_hits``).

For each scene's cameras at 128² and 256² pixels (the camera's aspect kept), supersample 2, on
the lattice of the default preset (N = 64, M = 3): the seconds to cast every sub-pixel ray
against the exact shapes, find the edge pixels, cast their 16 Hammersley rays, and cast the
shadow rays and integrate the sun's depth at every hit; the share of edge pixels and the rays
per pixel.  The output starts with the machine (copy bandwidth measured in the same run).

    python benchmarks/bench_hits.py [--scenes fog-balls ring-box translucent-cube cloud-plane]
        [--sizes 128 256] [--out FILE.md]
"""

from __future__ import annotations

import argparse
import dataclasses
import time

import numpy as np

import _common as C


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scenes", nargs="+",
                    default=["fog-balls", "ring-box", "translucent-cube", "cloud-plane"])
    ap.add_argument("--sizes", nargs="+", type=int, default=[128, 256])
    ap.add_argument("--resolution", type=int, default=64)
    ap.add_argument("--out", default=None)
    args = ap.parse_args(argv)

    import difffog as df
    from difffog.forward.sweep._march import camera_hits
    from difffog.geometry._lattice import voxelize

    info = C.machine()
    C.print_machine(info)
    rows = []
    for name in args.scenes:
        scene = df.load_scene(name)
        lat = voxelize(scene, args.resolution, 3, margin=4)
        for cam in scene.cameras:
            w, h = cam.resolution
            for size in args.sizes:
                res = (size, max(1, round(size * h / w)))
                c = dataclasses.replace(cam, resolution=res)
                t = time.perf_counter()
                hits = camera_hits(scene, c, 2, lat.fog_density, lat.origin, lat.h, lat.shape)
                s = time.perf_counter() - t
                px = res[0] * res[1]
                counts = np.bincount(np.asarray(hits.pixel), minlength=px)
                row = [name, cam.name, f"{res[0]}×{res[1]}", f"{s:.2f}",
                       f"{100 * np.mean(counts > 4):.1f}", f"{counts.sum() / px:.2f}"]
                rows.append(row)
                print(*row, flush=True)
    lines = ["# Exact camera hits: host set-up per camera", "", *C.machine_lines(info), "",
             f"Lattice N = {args.resolution}, M = 3; supersample 2; edge pixels get 16 rays.", ""]
    lines += C.md_table(["scene", "camera", "pixels", "set-up s", "edge pixels %",
                         "rays / pixel"], rows, "lllrrr")
    text = "\n".join(lines) + "\n"
    print(text)
    if args.out:
        C.write_text(args.out, text)


if __name__ == "__main__":
    main()
