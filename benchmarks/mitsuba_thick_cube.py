"""Issue 14's thick cube (and a wide slab that checks it) in Mitsuba 3, the independent peer.

Needs Mitsuba 3 (``pip install mitsuba``; not a difffog dependency), variant ``scalar_rgb``
(the LLVM variants failed to compile on this machine's LLVM; the image is grey, so channel 0
is the mono image).  The scene is ``difffog.study._semi_infinite.thick_cube``: a cube with a
null surface around a homogeneous isotropic medium (σ_t = ζ + 0.001, albedo ζ/σ_t), the ball
(diffuse 0.6, its exterior that medium), a directional sun (irradiance 2, zenith 30°), the sky
as an environment map of 0.2 above the horizon and 0 below it, an orthographic camera of
16 × 16 pixels over the middle 0.8 × 0.8 of the top face, volpath without a depth limit.
The same conversion, with translucent-cube's shapes, reproduces the shipped reference of that
scene within 0.04% (mean) and its noise (RMS).

``--slab W``: instead a slab [−W, W]² × [0, 1] of the same fog and no ball, which can return
no more than the semi-infinite medium's 0.773; ``--origin X`` moves the whole scene to
(X, X, ·), which scales float32's ray epsilon (Mitsuba's is ~9·10⁻⁵·(1 + |origin|)).

Measured (2026-11-29, 2 cores): the cube at ζ = 10: 0.4880 ± 0.0005; ζ = 100: 0.7286 ±
0.0003; ζ = 1000: 0.7851 ± 0.0005; ζ = 10000: 0.822 ± 0.001.  The slab (W = 5, ζ = 100) 0.7610,
0.7704 and 0.7755 at origins 0, 10 and 20; (W = 3, ζ = 1000) 0.785 ± 0.004, above the
half-space's bound: Mitsuba's float32 images of fog ≳ 1000 mean free paths per unit are
biased bright.  The float64 random walk of ``benchmarks/thick_cube_mc.py`` is the reference
there (docs/validation.md, "The thick cube against independent truth").

    python benchmarks/mitsuba_thick_cube.py --zetas 10 100 --spp 1024 --reps 4
    python benchmarks/mitsuba_thick_cube.py --zetas 100 --slab 5 --origin 10
"""

from __future__ import annotations

import argparse
import json
import math
import time

import numpy as np


def scene(mi, zeta: float, spp: int, seed: int, slab: float | None, origin: float):
    T = mi.ScalarTransform4f
    o = origin
    sigma_t = zeta + 0.001
    half = [0.5, 0.5, 0.5] if slab is None else [slab, slab, 0.5]
    d = {"type": "scene",
         "integrator": {"type": "volpath", "max_depth": -1, "rr_depth": 100000},
         "sensor": {"type": "orthographic",
                    "to_world": T().look_at(origin=[o + 0.5, o + 0.5, 1.5],
                                            target=[o + 0.5, o + 0.5, 0.5], up=[0, 1, 0])
                    @ T().scale([0.4, 0.4, 1]),
                    "film": {"type": "hdrfilm", "width": 16, "height": 16,
                             "rfilter": {"type": "box"}, "pixel_format": "rgb"},
                    "sampler": {"type": "independent", "sample_count": spp, "seed": seed}},
         "fog": {"type": "homogeneous", "sigma_t": sigma_t, "albedo": zeta / sigma_t,
                 "phase": {"type": "isotropic"}},
         "box": {"type": "cube", "to_world": T().translate([o + 0.5, o + 0.5, 0.5]) @ T().scale(half),
                 "bsdf": {"type": "null"}, "interior": {"type": "ref", "id": "fog"}}}
    if slab is None:
        d["ball"] = {"type": "sphere", "center": [o + 0.5, o + 0.5, 0.5], "radius": 0.2,
                     "bsdf": {"type": "diffuse", "reflectance": 0.6},
                     "exterior": {"type": "ref", "id": "fog"}}
    z = math.radians(30.0)
    d["sun"] = {"type": "directional", "direction": [-math.sin(z), 0.0, -math.cos(z)],
                "irradiance": 2.0}
    sky = np.zeros((512, 1024, 3), np.float32)
    sky[:256] = 0.2  # the upper hemisphere (the map's +y, turned to +z)
    d["sky"] = {"type": "envmap", "bitmap": mi.Bitmap(sky), "to_world": T().rotate([1, 0, 0], 90)}
    return mi.load_dict(d)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--zetas", nargs="+", type=float, default=[10.0, 100.0])
    ap.add_argument("--spp", type=int, default=1024)
    ap.add_argument("--reps", type=int, default=4)
    ap.add_argument("--slab", type=float, default=None, help="half-width W of a slab instead")
    ap.add_argument("--origin", type=float, default=0.0)
    a = ap.parse_args(argv)
    import mitsuba as mi

    mi.set_variant("scalar_rgb")
    for zeta in a.zetas:
        t0 = time.perf_counter()
        means = [float(np.array(mi.render(scene(mi, zeta, a.spp, r, a.slab, a.origin),
                                          seed=r))[..., 0].mean()) for r in range(a.reps)]
        print(json.dumps({"zeta": zeta, "slab": a.slab, "origin": a.origin, "spp": a.spp,
                          "reps": a.reps, "mean": round(float(np.mean(means)), 5),
                          "stderr": round(float(np.std(means, ddof=1) / math.sqrt(a.reps)), 5)
                          if a.reps > 1 else None,
                          "time_s": round(time.perf_counter() - t0, 1)}), flush=True)


if __name__ == "__main__":
    main()
