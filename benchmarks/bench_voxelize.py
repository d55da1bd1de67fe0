"""Voxelization benchmark: normal accuracy and voxelize() time.

1. Angular error (degrees) of the SURFACE normals, for the "com" (paper) and "analytic" rules,
   against the exact normal: the direction from the sphere's centre, or from the nearest point of
   the torus' core circle (torus = the ring of ring-box.toml; "mesh" = the shared ring.obj, a
   polygonal torus R = 0.14, r = 0.05, against the smooth torus), at resolutions 32, 64, 128 and
   M = 3, 5: mean and 95th percentile over all SURFACE nodes.
2. Seconds and node counts of voxelize() (M = 5, default normals) for every shared scene at
   resolutions 64 and 128 (best of ``--repeat``).

Run:  python benchmarks/bench_voxelize.py [--quick] [--repeat N]
"""

from __future__ import annotations

import argparse
import warnings
from importlib import resources

import numpy as np

import _common as C
from difffog import (Domain, Mesh, Scene, Sphere, Torus, builtin_scenes, load_scene,
                     voxelize)
from difffog.geometry._lattice import SURFACE

RING_OBJ = resources.files("difffog").joinpath("data", "scenes", "meshes", "ring.obj")
RING_AXIS = np.array([0.0, -0.5, 0.866])


def sphere_scene() -> tuple[Scene, callable]:
    c = np.array([0.5, 0.5, 0.5])
    s = Scene(
        title="sphere",
        domain=Domain((0, 0, 0), (1, 1, 1)),
        shapes=(Sphere(name="ball", center=tuple(c), radius=0.25),),
    )
    return s, lambda p: p - c


def _torus_normal(c, axis, R):
    a = axis / np.linalg.norm(axis)

    def exact(p):
        v = p - c
        z = v @ a
        radial = v - z[:, None] * a
        core = c + R * radial / np.linalg.norm(radial, axis=1, keepdims=True)
        return p - core

    return exact


def torus_scene() -> tuple[Scene, callable]:
    c = np.array([0.5, 0.5, 0.45])
    t = Torus(
        name="ring", center=tuple(c), major_radius=0.26, minor_radius=0.07, axis=tuple(RING_AXIS)
    )
    return Scene(title="torus", domain=Domain((0, 0, 0), (1, 1, 1)), shapes=(t,)), _torus_normal(
        c, RING_AXIS, 0.26
    )


def mesh_scene() -> tuple[Scene, callable]:
    import trimesh

    with resources.as_file(RING_OBJ) as path:
        m = trimesh.load(path, force="mesh")
    c = np.array([0.5, 0.5, 0.4])
    mesh = Mesh(name="ring", path="ring.obj", vertices=m.vertices + c, faces=m.faces)
    # ring.obj is a torus R = 0.14, r = 0.05 around the axis (0, 0.866, -0.5)
    return Scene(
        title="ring.obj", domain=Domain((0, 0, 0), (1, 1, 1)), shapes=(mesh,)
    ), _torus_normal(c, np.array([0.0, 0.866, -0.5]), 0.14)


def normal_errors(scene, exact, resolution, M, rule) -> tuple[float, float]:
    """(mean, 95th percentile) angle in degrees between the lattice's and the exact normals."""
    lat = voxelize(scene, resolution, M, normals=rule)
    sel = lat.node_type == SURFACE
    n = lat.normal[sel].astype(np.float64)
    e = exact(lat.node_positions()[sel])
    e /= np.linalg.norm(e, axis=1, keepdims=True)
    ang = np.degrees(np.arccos(np.clip(np.einsum("ij,ij->i", n, e), -1.0, 1.0)))
    return float(ang.mean()), float(np.percentile(ang, 95))


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    C.add_sizes(ap, [32, 64, 128], [16], what="resolutions of the normal errors")
    C.add_sizes(ap, [64, 128], [32], flag="--timing-sizes",
                what="resolutions of the voxelize() timings")
    ap.add_argument("--repeat", type=int, default=2, help="timing repeats (best is reported)")
    ap.add_argument("--out", default=None, help="also write the tables (markdown) here")
    args = C.parse(ap, argv)
    info = C.machine()
    lines = ["# Voxelization (benchmarks/bench_voxelize.py)", "", *C.machine_lines(info), "",
             "## Normal angular error (degrees) at SURFACE nodes: mean / 95th percentile", ""]
    print("\n".join(lines), flush=True)
    rows = []
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # thin-shape warnings do not matter here
        for name, make in (
            ("sphere", sphere_scene),
            ("torus", torus_scene),
            ("ring.obj", mesh_scene),
        ):
            scene, exact = make()
            for res in args.sizes:
                for M in (3, 5):
                    cm, cp = normal_errors(scene, exact, res, M, "com")
                    am, apct = normal_errors(scene, exact, res, M, "analytic")
                    rows.append([name, res, M, f"{cm:.2f}", f"{cp:.2f}", f"{am:.3f}",
                                 f"{apct:.3f}"])
                    print("  ".join(map(str, rows[-1])), flush=True)
    lines += C.md_table(["shape", "res", "M", "com mean", "com p95", "analytic mean",
                         "analytic p95"], rows)
    lines += ["", f"## voxelize(scene, resolution, M=5) time (best of {args.repeat}) and node "
              "counts", ""]
    rows = []
    for name in builtin_scenes():
        scene = load_scene(name)
        for res in args.timing_sizes:
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                t = C.time_calls(lambda: voxelize(scene, res, 5), args.repeat, first=False)
                lat = t.value
            c = lat.counts()
            rows.append([name, res, f"{t.best:.2f}", c["free"], c["surface"],
                         c["solid"], f"{lat.nbytes / 2**20:.1f}"])
            print("  ".join(map(str, rows[-1])), flush=True)
    lines += C.md_table(["scene", "res", "seconds", "free", "surface", "solid", "MiB"], rows)
    print("\n".join(lines))
    if args.out:
        C.write_text(args.out, lines)


if __name__ == "__main__":
    main()
