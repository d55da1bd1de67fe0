"""The ``difffog`` command line: ``info`` and ``render``.

Errors a user can fix print one line (``difffog: error: …``) and exit with status 2; nothing is
left half-written: outputs go to a temporary folder that is renamed into place at the end.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import sys
import tempfile
import time
from pathlib import Path

from ._errors import DifffogError

DEFAULT_SCENE = "fog-balls"


def _add_scene_args(p: argparse.ArgumentParser, default_resolution: int) -> None:
    p.add_argument("scene", nargs="?", default=DEFAULT_SCENE,
                   help=f"a scene file (.toml) or a built-in scene name (default: {DEFAULT_SCENE})")
    p.add_argument("--set", dest="overrides", action="append", default=[], metavar="PATH=VALUE",
                   help="override a scalar of the scene, e.g. fog.scattering=2.5 (repeatable)")
    p.add_argument("--resolution", "-N", type=int, default=default_resolution,
                   help=f"lattice nodes along the longest domain axis (default {default_resolution})")
    p.add_argument("--directions", "-M", type=int, default=3,
                   help="direction half-width M: (2M+1)^2 directions per cube face (default 3)")


def _positive_int(name: str, value: int) -> int:
    if value < 1:
        raise DifffogError(f"{name} must be a positive integer, got {value}")
    return value


def cmd_info(args) -> int:
    from ._info import scene_info

    from ._scene_io import load_scene

    scene = load_scene(args.scene, args.overrides)
    print(scene_info(scene, resolution=args.resolution, M=args.directions))
    return 0


def _tonemap(img):
    import numpy as np

    scale = float(np.percentile(img, 99.5)) or 1.0
    x = np.clip(img / scale, 0.0, 1.0) ** (1 / 2.2)
    return (x * 255 + 0.5).astype(np.uint8)


def cmd_render(args) -> int:
    import numpy as np
    from skimage import io as skio

    from ._render import Renderer
    from ._scene_io import load_scene
    from ._solver import SweepSolver

    if args.solver != "sweep":
        raise DifffogError(f"--solver {args.solver}: only 'sweep' is available in this version")
    _positive_int("--resolution", args.resolution)
    _positive_int("--directions", args.directions)
    if args.iterations is not None:
        _positive_int("--iterations", args.iterations)
    if args.tol is not None and not args.tol > 0:
        raise DifffogError(f"--tol must be a positive number, got {args.tol}")
    scene = load_scene(args.scene, args.overrides)
    cameras = args.camera or None
    if cameras:
        for c in cameras:
            scene.camera(c)  # raises a clear error for an unknown name
    if not scene.cameras:
        raise DifffogError(f"scene '{scene.title}' has no [[camera]]: add one to render images")
    progress = sys.stderr.isatty() and not args.quiet
    solver = SweepSolver(
        M=args.directions,
        max_iterations=args.iterations or 500,
        tol=0.0 if args.iterations else (args.tol if args.tol is not None else 1e-4),
        progress=progress,
        method=args.method,
    )
    out = Path(args.out)
    if out.exists() and not out.is_dir():
        raise DifffogError(f"--out {out}: exists and is not a folder; choose a folder path")

    def say(msg):
        if progress:
            print(f"  {msg}", file=sys.stderr, flush=True)

    t0 = time.perf_counter()
    say(f"voxelizing '{scene.title}' at resolution {args.resolution} (M = {args.directions})…")
    renderer = Renderer(scene, resolution=args.resolution, solver=solver, cameras=cameras,
                        supersample=args.supersample)
    say("solving the light (compiling first)…")
    result = renderer.render()
    if progress:
        print(file=sys.stderr)
    say(f"done: {int(result.light.iterations)} iterations, writing {out}/")
    # write everything into a temporary folder beside the target, then move into place
    out.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=".difffog-", dir=out.parent))
    try:
        for name, img in result.images.items():
            np.save(tmp / f"{name}.npy", img.astype(np.float32))
            skio.imsave(tmp / f"{name}.png", _tonemap(img), check_contrast=False)
        light = result.light
        k = int(light.iterations)
        report = {
            "scene": scene.title,
            "source": str(scene.source) if scene.source else None,
            "overrides": args.overrides,
            "settings": result.settings,
            "timings_s": {k2: round(v, 4) for k2, v in result.timings.items()},
            "total_s": round(time.perf_counter() - t0, 4),
            "iterations": k,
            "residuals": [float(x) for x in np.asarray(light.residuals)[:k]],
            "error_estimate": float(light.error_estimate),
            "peak_memory_mb": _peak_memory_mb(),
            "images": {
                n: {"shape": list(v.shape), "mean": float(v.mean()), "max": float(v.max())}
                for n, v in result.images.items()
            },
        }
        (tmp / "report.json").write_text(json.dumps(report, indent=1))
        out.mkdir(parents=True, exist_ok=True)
        for f in tmp.iterdir():
            os.replace(f, out / f.name)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    if not args.quiet:
        for n, v in result.images.items():
            print(f"{out / (n + '.npy')}: {v.shape[1]}x{v.shape[0]}, mean radiance {v.mean():.4g}")
        print(f"{out / 'report.json'}: {k} iterations, {report['total_s']:.1f} s")
    return 0


def _peak_memory_mb() -> float:
    import resource

    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="difffog",
        description="Differentiable fog rendering and inverse fog estimation.",
    )
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    p = sub.add_parser("info", help="summarize a scene: domain, lattice, node counts, physics")
    _add_scene_args(p, 64)
    p.set_defaults(func=cmd_info)
    p = sub.add_parser("render", help="render a scene's cameras to .npy/.png with a report")
    _add_scene_args(p, 64)
    p.add_argument("--camera", action="append", metavar="NAME",
                   help="render only this camera (repeatable; default: all)")
    p.add_argument("--solver", default="sweep", choices=["sweep"], help="light solver")
    g = p.add_mutually_exclusive_group()
    p.add_argument("--method", default="auto", choices=["auto", "gmres", "jacobi"],
                   help="iteration: GMRES (auto, the default: measured 1.2-94x faster) or Jacobi")
    g.add_argument("--iterations", type=int,
                   help="run exactly this many iterations (applications of the six sweeps)")
    g.add_argument("--tol", type=float,
                   help="stop when the estimated remaining relative error is below (default 1e-4)")
    p.add_argument("--supersample", type=int, default=2,
                   help="s×s rays per pixel, averaged (box filter; default 2)")
    p.add_argument("--out", default="out", help="output folder (default: out)")
    p.add_argument("--quiet", "-q", action="store_true", help="no progress or summary")
    p.set_defaults(func=cmd_render)
    return parser


def main(argv=None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    if not getattr(args, "func", None):
        parser.print_help()
        return 0
    try:
        return args.func(args)
    except DifffogError as e:
        print(f"difffog: error: {e}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("difffog: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
