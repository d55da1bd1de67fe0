"""Where fog-balls' image error at coarse lattices comes from: image means by component.

fog-balls at its true parameters, both views at 1/4 size (as the recovery study fits them),
M = 3, for each resolution: the image mean as it is, with the walls black, with every surface
black, and without the walls (the fog kept as a region over their inside) with the balls as
they are and black.  The model converges in N; what changes between resolutions is the
model's own error, and which parts change says where it sits (docs/fitting.md, "Where the
remaining +1.5% comes from").  Mitsuba's means of the full-size references are printed for
scale.

    python benchmarks/wall_coupling.py [--resolutions 24 32 48 64 96]
"""

from __future__ import annotations

import argparse
import dataclasses

import numpy as np

import _common as C

CAMS = ("top", "oblique")


def variants(scene):
    """(label, scene, {param path: value}) for each component."""
    balls = [s.name for s in scene.shapes if s.name != "walls"]
    black = {f"shape.{n}.albedo": 0.0 for n in balls}
    open_scene = dataclasses.replace(
        scene, shapes=tuple(s for s in scene.shapes if s.name != "walls"),
        fog=dataclasses.replace(scene.fog, region=((0.05, 0.05, 0.05), (0.95, 0.95, 1.0))))
    return [("as it is", scene, {}),
            ("walls black", scene, {"shape.walls.albedo": 0.0}),
            ("all surfaces black", scene, {"shape.walls.albedo": 0.0, **black}),
            ("no walls", open_scene, {}),
            ("no walls, balls black", open_scene, black)]


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--resolutions", nargs="+", type=int, default=[24, 32, 48, 64, 96])
    a = ap.parse_args(argv)
    import difffog as df

    scene = df.load_scene("fog-balls")
    refs = [float(np.asarray(C.reference("fog-balls", c, None)[0], np.float64).mean())
            for c in CAMS]
    print(f"Mitsuba means: top {refs[0]:.5f}, oblique {refs[1]:.5f}")
    models = {}
    for N in a.resolutions:
        for label, sc, vals in variants(scene):
            key = (id(sc), N)
            if key not in models:
                models[key] = C.fit_model(sc, list(CAMS), N, 3, 4)
            fwd = models[key]
            p = fwd.params()
            for path, v in vals.items():
                p = df.set_param(p, fwd.scene, path, v)
            im = fwd(p)
            m = [float(np.asarray(im[c], np.float64).mean()) for c in CAMS]
            print(f"N={N:3d} {label:22s} top {m[0]:.5f} oblique {m[1]:.5f}", flush=True)


if __name__ == "__main__":
    main()
