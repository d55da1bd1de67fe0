"""How weakly cloud-plane's images pin ζ, against how much they change between two lattices.

For cloud-plane and a variant whose density grid is smooth (the same four ellipsoids as
``../shared/scenes/data/make_cloud.py`` without its noise), renders at the scene's own
parameters at ``--target-N`` (64) and ``--N`` (48), and at ``--N`` with ζ raised by
``--step`` (2%); prints each view's image mean, the mean difference between the two lattices
in %, and the relative change of ζ that would move the ``--N`` images onto the
``--target-N`` ones (least squares over both views' pixels on the finite-difference dI/dζ):
the part of a fit's ζ error that the lattice's own error accounts for when ζ is fitted alone.
If the smooth cloud gives what the noisy one gives, the density grid's sampling on the lattice
is not what separates the two lattices.

    python benchmarks/cloud_plane_zeta_sensitivity.py [--N 48] [--target-N 64]
        [--scheme substep] [--step 0.02] [--out FILE]
"""

from __future__ import annotations

import argparse
import shutil
import tempfile
import time
import warnings
from pathlib import Path

import numpy as np

import _common as C


def smooth_variant(folder: Path) -> Path:
    """cloud-plane with a smooth density grid (make_cloud.py's blobs, no noise), written to
    ``folder`` beside a link to the scene's meshes; returns the scene file."""
    import difffog

    data = Path(difffog.__file__).parent / "data" / "scenes"
    n = 64
    c = (np.arange(n) + 0.5) / n
    X, Y, Z = np.meshgrid(c, c, c, indexing="ij")
    blobs = [((0.50, 0.50, 0.42), (0.30, 0.22, 0.12)),
             ((0.35, 0.45, 0.48), (0.16, 0.14, 0.12)),
             ((0.62, 0.56, 0.50), (0.18, 0.15, 0.13)),
             ((0.50, 0.40, 0.55), (0.12, 0.12, 0.10))]
    f = np.full_like(X, -10.0)
    for (cx, cy, cz), (rx, ry, rz) in blobs:
        f = np.maximum(f, 1.0 - (((X - cx) / rx) ** 2 + ((Y - cy) / ry) ** 2
                                 + ((Z - cz) / rz) ** 2))
    density = np.clip(f, 0.0, None)
    (folder / "data").mkdir()
    np.savez(folder / "data" / "smooth64.npz", density=(density / density.max()).astype(np.float32))
    (folder / "meshes").symlink_to(data / "meshes")
    text = (data / "cloud-plane.toml").read_text()
    text = text.replace('density = "data/cloud64.npz"', 'density = "data/smooth64.npz"')
    text = text.replace('title = "cloud-plane"', 'title = "cloud-plane-smooth"')
    path = folder / "cloud-plane-smooth.toml"
    path.write_text(text)
    return path


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--N", type=int, default=48)
    ap.add_argument("--target-N", type=int, default=64)
    ap.add_argument("-M", type=int, default=3)
    ap.add_argument("--scheme", default="substep")
    ap.add_argument("--step", type=float, default=0.02, help="relative step of ζ for dI/dζ")
    ap.add_argument("--out", default=None)
    a = ap.parse_args(argv)
    import difffog as df

    folder = Path(tempfile.mkdtemp(prefix="difffog-zeta-"))
    lines = [f"# cloud-plane's ζ sensitivity against its lattice error (N = {a.N} vs "
             f"{a.target_N}, M = {a.M}, scheme {a.scheme})", "",
             "`python benchmarks/cloud_plane_zeta_sensitivity.py` (module docstring)", "",
             *C.machine_lines(C.machine(bandwidth=False)), "",
             "| scene | image mean N = {0} (oblique / top) | N = {1} | {1}, ζ × {2:g} | "
             "mean {0} vs {1} % | ζ shift to match % |".format(a.target_N, a.N, 1 + a.step),
             "|---|---:|---:|---:|---:|---:|"]
    try:
        for label, path in (("cloud-plane", "cloud-plane"),
                            ("smooth variant", str(smooth_variant(folder)))):
            zeta = df.load_scene(path).fog.scattering
            imgs = {}
            for N, factor in ((a.target_N, 1.0), (a.N, 1.0), (a.N, 1.0 + a.step)):
                t = time.perf_counter()
                scene = df.load_scene(path, [f"fog.scattering={zeta * factor}"])
                with warnings.catch_warnings():  # its steps are thick (it says so)
                    warnings.simplefilter("ignore", df.ThickStepWarning)
                    out = df.render(scene, accuracy=None, resolution=N, M=a.M, phase_order=3,
                                    scheme=a.scheme)
                imgs[N, factor] = {k: np.asarray(v, np.float64) for k, v in out.images.items()}
                print(label, N, factor, f"{time.perf_counter() - t:.0f} s", flush=True)
            tgt, base, up = imgs[a.target_N, 1.0], imgs[a.N, 1.0], imgs[a.N, 1.0 + a.step]
            cams = sorted(tgt)
            r = np.concatenate([(tgt[k] - base[k]).ravel() for k in cams])
            j = np.concatenate([((up[k] - base[k]) / (a.step * zeta)).ravel() for k in cams])
            shift = float(r @ j / (j @ j)) / zeta
            means = lambda im: " / ".join(f"{im[k].mean():.5f}" for k in cams)  # noqa: E731
            diff = " / ".join(f"{100 * (tgt[k].mean() / base[k].mean() - 1):+.3f}" for k in cams)
            lines.append(f"| {label} | {means(tgt)} | {means(base)} | {means(up)} | {diff} | "
                         f"{100 * shift:+.2f} |")
            print(lines[-1], flush=True)
    finally:
        shutil.rmtree(folder, ignore_errors=True)
    lines += ["", f"(views in the order {', '.join(cams)})"]
    print("\n".join(lines))
    if a.out:
        C.write_text(a.out, lines)


if __name__ == "__main__":
    main()
