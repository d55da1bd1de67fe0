"""Time ``render_camera`` (compile excluded) on random smooth lattices.

Cameras as in the built-in scenes: a 128×128 orthographic top view and a 160×120 perspective
oblique view of the unit cube, on 64³ and 128³ lattices with fog, sun, sky and three spheres;
supersample 1 and 2, default step h/2.  ``--grad`` also times jit(grad) of the image sum with
respect to all fields.  ``--quick``: a 16³ lattice, supersample 1, one repeat.

The camera march is measured alone, on synthetic fields, so this imports the sweep's internal
``difffog.forward.sweep._march`` (``LatticeFields``, ``march_steps``, ``render_camera``) and
``difffog.forward._camera.camera_rays`` on purpose.  The output starts with the machine (JAX
backend and devices, copy bandwidth) measured in the same run.

    python benchmarks/bench_camera.py [--quick] [--sizes 64 128] [--repeat 3] [--grad]
        [--out FILE.md]
"""

from __future__ import annotations

import argparse

import numpy as np

import _common as C


def cameras():
    import difffog as df

    return {
        "ortho 128x128": df.Camera("top", "orthographic", (0.5, 0.5, 1.5), (0.5, 0.5, 0.0),
                                   (0.0, 1.0, 0.0), (128, 128), extent=(1.0, 1.0)),
        "persp 160x120": df.Camera("oblique", "perspective", (0.5, -0.35, 1.75),
                                   (0.5, 0.5, 0.35), (0.0, 0.0, 1.0), (160, 120), fov_deg=45.0),
    }


def random_fields(n: int, seed: int = 0):
    """Smooth random fields on an n³ lattice over the unit cube, float32."""
    import jax.numpy as jnp
    from scipy.ndimage import gaussian_filter

    from difffog.forward.sweep._march import LatticeFields

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


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    C.add_sizes(ap, [64, 128], [16])
    ap.add_argument("--supersample", type=int, nargs="+", default=None,
                    help="default 1 2; with --quick 1")
    ap.add_argument("--repeat", type=int, default=None, help="default 3; with --quick 1")
    ap.add_argument("--grad", action="store_true", help="also time jit(grad) w.r.t. the fields")
    ap.add_argument("--out", default=None, help="also write the table (markdown) here")
    args = C.parse(ap, argv)
    supersample = args.supersample or ([1] if args.quick else [1, 2])
    repeat = args.repeat or (1 if args.quick else 3)

    import jax

    from difffog.forward._camera import camera_rays
    from difffog.forward.sweep._march import march_steps, render_camera

    info = C.machine()
    C.print_machine(info)
    print("float32, step h/2", flush=True)
    header = ["lattice", "camera", "ss", "rays", "steps", "first (s)", "render (s)",
              "Mray-steps/s"] + (["grad (s)"] if args.grad else [])
    rows = []
    for n in args.sizes:
        fields = random_fields(n)
        for cname, cam in cameras().items():
            for ss in supersample:
                o, d = camera_rays(cam, ss)
                steps = march_steps(fields, fields.h / 2, o, d)
                rays = o.shape[0] * o.shape[1] * o.shape[2]
                t = C.time_calls(lambda: render_camera(fields, cam, supersample=ss), repeat)
                row = [f"{n}³", cname, ss, rays, steps, f"{t.first:.2f}", f"{t.median:.3f}",
                       f"{rays * steps / t.median / 1e6:.1f}"]
                if args.grad:
                    g = jax.jit(jax.grad(lambda f: render_camera(f, cam, supersample=ss).sum()))
                    row.append(f"{C.time_calls(lambda: g(fields), repeat).median:.3f}")
                rows.append(row)
                print("  ".join(map(str, row)), flush=True)
    lines = C.md_table(header, rows, "ll" + "r" * (len(header) - 2))
    print("\n".join(lines))
    if args.out:
        C.write_text(args.out, ["# Camera march (benchmarks/bench_camera.py)", "",
                                *C.machine_lines(info), "", *lines])


if __name__ == "__main__":
    main()
