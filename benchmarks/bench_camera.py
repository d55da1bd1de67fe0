"""Time ``render_camera`` (compile excluded) on random smooth lattices.

Cameras as in the shared scenes: a 128×128 orthographic top view and a 160×120 perspective
oblique view of the unit cube, on 64³ and 128³ lattices with fog, sun, sky and three spheres;
supersample 1 and 2, default step h/2.  ``--grad`` also times jit(grad) of the image sum with
respect to all fields.

    python benchmarks/bench_camera.py [--sizes 64 128] [--repeat 3] [--grad]
"""

from __future__ import annotations

import argparse
import statistics
import time

import jax
import jax.numpy as jnp
import numpy as np
from scipy.ndimage import gaussian_filter

from difffog._camera import LatticeFields, march_steps, render_camera
from difffog._scene import Camera

CAMERAS = {
    "ortho 128x128": Camera("top", "orthographic", (0.5, 0.5, 1.5), (0.5, 0.5, 0.0),
                            (0.0, 1.0, 0.0), (128, 128), extent=(1.0, 1.0)),
    "persp 160x120": Camera("oblique", "perspective", (0.5, -0.35, 1.75), (0.5, 0.5, 0.35),
                            (0.0, 0.0, 1.0), (160, 120), fov_deg=45.0),
}


def random_fields(n: int, seed: int = 0) -> LatticeFields:
    """Smooth random fields on an n³ lattice over the unit cube, float32."""
    rng = np.random.default_rng(seed)
    smooth = lambda: gaussian_filter(rng.standard_normal((n, n, n)), n / 16, mode="wrap")  # noqa
    norm = lambda a: (a - a.min()) / (a.max() - a.min())  # noqa: E731
    h = 1.0 / n
    x = (np.arange(n) + 0.5) * h
    P = np.stack(np.meshgrid(x, x, x, indexing="ij"), -1)
    balls = [((0.3, 0.35, 0.25), 0.18), ((0.7, 0.6, 0.3), 0.22), ((0.45, 0.7, 0.6), 0.12)]
    sdf = np.min([np.linalg.norm(P - c, axis=-1) - r for c, r in balls], axis=0)
    f32 = lambda a: jnp.asarray(a, jnp.float32)  # noqa: E731
    return LatticeFields(
        sigma_t=f32(4.0 * norm(smooth())), j_iso=f32(0.5 * norm(smooth())),
        j_sun=f32(2.0 * norm(smooth())), radiosity_ext=f32(0.2 + 0.6 * norm(smooth())),
        sdf=f32(sdf), origin=(0.0, 0.0, 0.0), h=h, g=0.6, sun_dir=(0.3, 0.2, 0.93), sky=1.0)


def timeit(fn, repeat: int) -> tuple[float, float]:
    """(first-call seconds incl. compile, median seconds of `repeat` warm calls)."""
    t = time.perf_counter()
    jax.block_until_ready(fn())
    first = time.perf_counter() - t
    times = []
    for _ in range(repeat):
        t = time.perf_counter()
        jax.block_until_ready(fn())
        times.append(time.perf_counter() - t)
    return first, statistics.median(times)


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sizes", type=int, nargs="+", default=[64, 128])
    ap.add_argument("--supersample", type=int, nargs="+", default=[1, 2])
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--grad", action="store_true", help="also time jit(grad) w.r.t. the fields")
    args = ap.parse_args(argv)

    print(f"jax {jax.__version__} on {jax.devices()[0].device_kind} "
          f"({jax.devices()[0].platform}), float32, step h/2")
    cols = "lattice  camera          ss   rays    steps  first(s)  render(s)  Mray-steps/s"
    if args.grad:
        cols += "  grad(s)"
    print(cols)
    print("-" * len(cols))
    for n in args.sizes:
        fields = random_fields(n)
        for cname, cam in CAMERAS.items():
            for ss in args.supersample:
                from difffog._camera import camera_rays

                o, d = camera_rays(cam, ss)
                steps = march_steps(fields, fields.h / 2, o, d)
                rays = o.shape[0] * o.shape[1] * o.shape[2]
                first, t = timeit(lambda: render_camera(fields, cam, supersample=ss), args.repeat)
                line = (f"{n:>4}^3   {cname:<15} {ss:>2} {rays:>7} {steps:>7} {first:>9.2f} "
                        f"{t:>10.3f} {rays * steps / t / 1e6:>13.1f}")
                if args.grad:
                    g = jax.jit(jax.grad(lambda f: render_camera(f, cam, supersample=ss).sum()))
                    _, tg = timeit(lambda: g(fields), args.repeat)
                    line += f" {tg:>8.3f}"
                print(line, flush=True)


if __name__ == "__main__":
    main()
