"""The lattice's vacuum margin against the images: each scene rendered with the margin of
``--margins`` (``_model.VACUUM_MARGIN`` set before the model is built; the renderer's is 2, it
was M + 1 until stop 82), each image held against the first margin's (max |Δ| over the image
mean) and every camera against the Monte Carlo references (relative RMSE, their noise
removed), with the light's run time (a warm render).

    python benchmarks/vacuum_margin.py --scenes fog-balls ring-box --N 64 --M 3 --margins 4 2 1
"""

from __future__ import annotations

import argparse

import numpy as np

import difffog as df
from difffog.forward.sweep import _model
from difffog.study._bench import scene_errors
from difffog.study.references import references_dir


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scenes", nargs="+", default=["fog-balls", "ring-box", "translucent-cube",
                                                    "cloud-tomo", "cloud-plane"])
    ap.add_argument("--N", type=int, default=64)
    ap.add_argument("--M", type=int, default=3)
    ap.add_argument("--margins", nargs="+", type=int, default=[4, 2, 1])
    a = ap.parse_args(argv)
    for name in a.scenes:
        scene, first = df.load_scene(name), None
        for k in a.margins:
            _model.VACUUM_MARGIN = k
            m = df.forward_model(scene, "sweep", accuracy=None, resolution=a.N, M=a.M)
            df.render(m)
            out = df.render(m)  # warm
            imgs = {c: np.asarray(v) for c, v in out.images.items()}
            err, bias, _ = scene_errors(imgs, references_dir(), name)
            first = imgs if first is None else first
            diff = max(float(np.abs(imgs[c] - first[c]).max() / first[c].mean()) for c in imgs)
            print(f"{name} margin {k}: lattice {'x'.join(map(str, m.lattice.shape))}, light "
                  f"{out.timings['light_s']:.2f} s, error {100 * err:.2f}%, bias "
                  f"{100 * bias:+.2f}%, max |diff| / mean vs margin {a.margins[0]}: {diff:.1e}",
                  flush=True)


if __name__ == "__main__":
    main()
