"""``difffog render``: every camera of a scene to ``.npy``/``.png`` with a ``report.json``."""

from __future__ import annotations

import json
import sys
import time

from .._errors import DifffogError
from ..forward._registry import SOLVERS, solver_entry
from ._main import add_scene_args, model_settings, peak_memory_mb, positive_int, solver_help


def add_parser(sub) -> None:
    p = sub.add_parser("render", help="render a scene's cameras to .npy/.png with a report")
    add_scene_args(p)
    p.add_argument("--camera", action="append", metavar="NAME",
                   help="render only this camera (repeatable; default: all)")
    p.add_argument("--solver", default="sweep", choices=list(SOLVERS), help=solver_help())
    p.add_argument("--sheets", type=int, metavar="K",
                   help="splat: sheets per camera pass (default: from --accuracy)")
    p.add_argument("--method", default=None, choices=["auto", "gmres", "jacobi"],
                   help="sweep: GMRES (auto, the default: measured 1.2-94x faster) or Jacobi")
    g = p.add_mutually_exclusive_group()
    g.add_argument("--iterations", type=int,
                   help="sweep: run exactly this many iterations (applications of the six "
                        "sweeps)")
    g.add_argument("--tol", type=float,
                   help="sweep: stop when the estimated remaining relative error is below "
                        "(default: from --accuracy, 1e-4)")
    p.add_argument("--max-iterations", type=int, metavar="K",
                   help="sweep: iteration cap of the light solve with --tol (default 500); "
                        "reaching it before the tolerance is a failed solve (exit status 1)")
    p.add_argument("--supersample", type=int, default=None,
                   help="s×s rays per pixel, averaged (box filter; default 2, splat 1)")
    p.add_argument("--devices", type=int, default=None, metavar="N",
                   help="sweep: run the sweeps on N devices (faces and plane blocks; on a CPU, "
                        "N host devices sharing its cores; default 1)")
    p.add_argument("--force", action="store_true",
                   help="run even where the estimated peak memory exceeds what this machine "
                        "has (refused otherwise, before anything is allocated)")
    p.add_argument("--out", default="out", help="output folder (default: out)")
    p.add_argument("--quiet", "-q", action="store_true", help="no progress or summary")
    p.set_defaults(func=run)


def run(args) -> int:
    from .._cost import machine
    from .._output import atomic_folder, check_out_dir, save_image
    from .._progress import NoProgress, TextProgress
    from ..forward._model import failure_details, render
    from ..forward._registry import forward_model, model_estimate
    from ..scene._toml import load_scene

    for flag, v in (("--resolution", args.resolution), ("--directions", args.directions),
                    ("--sheets", args.sheets), ("--iterations", args.iterations),
                    ("--max-iterations", args.max_iterations),
                    ("--supersample", args.supersample), ("--devices", args.devices)):
        positive_int(flag, v)
    if args.tol is not None and not args.tol > 0:
        raise DifffogError(f"--tol must be a positive number, got {args.tol}")
    if args.iterations is not None and args.max_iterations is not None:
        raise DifffogError("--max-iterations caps a solve to a tolerance (--tol); --iterations "
                           "already runs exactly that many: give one of them")
    settings = model_settings(args, args.solver, accuracy=args.accuracy)
    scene = load_scene(args.scene, args.overrides)
    cameras = args.camera or None
    for c in cameras or []:
        scene.camera(c)  # a clear error for an unknown name
    if not scene.cameras:
        raise DifffogError(f"scene '{scene.title}' has no [[camera]]: add one to render images")
    out = check_out_dir(args.out)
    show = sys.stderr.isatty() and not args.quiet
    if "progress" in solver_entry(args.solver).settings:
        settings["progress"] = TextProgress("iteration") if show else NoProgress()

    def say(msg):
        if show:
            print(f"  {msg}", file=sys.stderr, flush=True)

    t0 = time.perf_counter()
    say(f"setting up '{scene.title}' for the {args.solver} at resolution "
        f"{settings.get('resolution')}…")
    est = model_estimate(scene, args.solver, cameras=cameras, **settings)
    model = forward_model(scene, args.solver, accuracy=None, cameras=cameras, force=args.force,
                          **settings)
    say("computing the light (compiling first)…")
    result = render(model, throw=False)
    light = result.light
    report = {
        "scene": scene.title,
        "source": str(scene.source) if scene.source else None,
        "overrides": args.overrides,
        "accuracy": args.accuracy,
        "settings": result.settings,
        "result": result.result.name,
        "timings_s": {k: round(v, 4) for k, v in result.timings.items()},
        "total_s": round(time.perf_counter() - t0, 4),
        **light.report(),
        "error_estimate": float(light.error_estimate),
        "machine": machine(),  # the JAX backend and devices that ran it
        "peak_memory_mb": peak_memory_mb(),
        # the estimate made before anything was built (difffog.estimate), beside the measured
        "estimate": {**est.as_dict(), "peak_mb": round(est.peak_bytes / 2**20, 1)},
        "images": {n: {"shape": list(v.shape), "mean": float(v.mean()), "max": float(v.max())}
                   for n, v in result.images.items()},
    }
    with atomic_folder(out) as tmp:
        for name, img in result.images.items():
            save_image(tmp, name, img)
        (tmp / "report.json").write_text(json.dumps(report, indent=1))
    if not result.converged:
        print(f"difffog: error: render: {result.result.name} "
              f"({failure_details(light, model.params())}): "
              f"{result.result.message} (images and report.json written to {out}/)",
              file=sys.stderr)
        return 1
    if not args.quiet:
        for n, v in result.images.items():
            print(f"{out / (n + '.npy')}: {v.shape[1]}x{v.shape[0]}, mean radiance {v.mean():.4g}")
        print(f"{out / 'report.json'}: {int(light.iterations)} iteration(s), "
              f"{report['total_s']:.1f} s")
    return 0
