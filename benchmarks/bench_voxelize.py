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
import glob
import os
import time
import warnings

import numpy as np

from difffog._lattice import SURFACE, voxelize
from difffog._scene import Domain, Mesh, Scene, Sphere, Torus

SCENES = os.environ.get("DIFFFOG_SCENES", "/work/shared/scenes")
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

    m = trimesh.load(os.path.join(SCENES, "meshes", "ring.obj"), force="mesh")
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


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="resolutions 32 and 64 only (smoke test)")
    ap.add_argument("--repeat", type=int, default=2, help="timing repeats (best is reported)")
    args = ap.parse_args()
    resolutions = (32, 64) if args.quick else (32, 64, 128)

    print("## Normal angular error (degrees) at SURFACE nodes: mean / 95th percentile")
    print(
        f"{'shape':10s} {'res':>4s} {'M':>2s} {'com mean':>9s} {'com p95':>8s} "
        f"{'analytic mean':>14s} {'analytic p95':>13s}"
    )
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # thin-shape warnings do not matter here
        for name, make in (
            ("sphere", sphere_scene),
            ("torus", torus_scene),
            ("ring.obj", mesh_scene),
        ):
            scene, exact = make()
            for res in resolutions:
                for M in (3, 5):
                    cm, cp = normal_errors(scene, exact, res, M, "com")
                    am, apct = normal_errors(scene, exact, res, M, "analytic")
                    print(f"{name:10s} {res:4d} {M:2d} {cm:9.2f} {cp:8.2f} {am:14.3f} {apct:13.3f}")

    from difffog._scene_io import load_scene

    print()
    print(f"## voxelize(scene, resolution, M=5) time (best of {args.repeat}) and node counts")
    print(
        f"{'scene':18s} {'res':>4s} {'seconds':>8s} {'free':>9s} {'surface':>9s} "
        f"{'solid':>9s} {'MiB':>6s}"
    )
    for path in sorted(glob.glob(os.path.join(SCENES, "*.toml"))):
        scene = load_scene(path)
        for res in (64,) if args.quick else (64, 128):
            best = np.inf
            for _ in range(args.repeat):
                t0 = time.perf_counter()
                with warnings.catch_warnings():
                    warnings.simplefilter("ignore")
                    lat = voxelize(scene, res, 5)
                best = min(best, time.perf_counter() - t0)
            c = lat.counts()
            print(
                f"{scene.title:18s} {res:4d} {best:8.2f} {c['free']:9d} {c['surface']:9d} "
                f"{c['solid']:9d} {lat.nbytes / 2**20:6.1f}"
            )


if __name__ == "__main__":
    main()
