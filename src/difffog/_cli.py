"""The ``difffog`` command line: ``info``, ``render`` and ``fit``.

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
from ._presets import LEVELS, PRESETS, preset

DEFAULT_SCENE = "fog-balls"


def _add_scene_args(p: argparse.ArgumentParser, default_resolution: int) -> None:
    p.add_argument("scene", nargs="?", default=DEFAULT_SCENE,
                   help=f"a scene file (.toml) or a built-in scene name (default: {DEFAULT_SCENE})")
    p.add_argument("--set", dest="overrides", action="append", default=[], metavar="PATH=VALUE",
                   help="override a scalar of the scene, e.g. fog.scattering=2.5 (repeatable)")
    p.add_argument("--accuracy", choices=LEVELS, default="default",
                   help="preset of resolution, directions, tolerance and sheets, chosen from "
                        "the measured speed-accuracy study (default: default); the options "
                        "below override single settings")
    p.add_argument("--resolution", "-N", type=int, default=None,
                   help="lattice nodes along the longest domain axis (default: from --accuracy, "
                        f"{PRESETS['sweep']['default']['resolution']} at default)")
    p.add_argument("--directions", "-M", type=int, default=None,
                   help="direction half-width M: (2M+1)^2 directions per cube face (default: "
                        f"from --accuracy, {PRESETS['sweep']['default']['M']} at default)")


def _apply_accuracy(args, solver: str = "sweep") -> None:
    """Fill the settings the user did not give from the --accuracy preset of ``solver``."""
    s = preset(solver, getattr(args, "accuracy", "default"))
    if getattr(args, "resolution", None) is None:
        args.resolution = s["resolution"]
    if getattr(args, "directions", None) is None:
        args.directions = PRESETS["sweep"][args.accuracy]["M"]
    if solver == "sweep" and getattr(args, "tol", None) is None and hasattr(args, "tol"):
        if getattr(args, "iterations", None) is None:
            args.tol = s["tol"]
    if solver == "splat" and getattr(args, "sheets", None) is None and hasattr(args, "sheets"):
        args.sheets = s["sheets"]


def _positive_int(name: str, value: int) -> int:
    if value < 1:
        raise DifffogError(f"{name} must be a positive integer, got {value}")
    return value


def cmd_info(args) -> int:
    from ._info import scene_info

    from ._scene_io import load_scene

    _apply_accuracy(args)
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

    splat = args.solver == "splat"
    _apply_accuracy(args, args.solver)
    if args.sheets is not None:
        _positive_int("--sheets", args.sheets)
        if not splat:
            raise DifffogError("--sheets applies to --solver splat only; the sweep's knobs are "
                               "--directions and --tol")
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
    _positive_int("--devices", args.devices)
    if splat and args.devices > 1:
        raise DifffogError("--devices applies to --solver sweep (the splat renders on one device)")
    solver = SweepSolver(
        devices=args.devices,
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
    if splat:
        from ._splat import SplatRenderer

        say(f"splatting '{scene.title}' at resolution {args.resolution}…")
        renderer = SplatRenderer(scene, resolution=args.resolution, sheets=args.sheets,
                                 cameras=cameras, supersample=args.supersample or 1)
        say("rendering the sheets (compiling first)…")
        result = renderer.render()
        say(f"done, writing {out}/")
    else:
        say(f"voxelizing '{scene.title}' at resolution {args.resolution} (M = {args.directions})…")
        renderer = Renderer(scene, resolution=args.resolution, solver=solver, cameras=cameras,
                            supersample=args.supersample or 2)
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
        k = 0 if splat else int(light.iterations)
        report = {
            "scene": scene.title,
            "source": str(scene.source) if scene.source else None,
            "overrides": args.overrides,
            "accuracy": args.accuracy,
            "settings": result.settings,
            "timings_s": {k2: round(v, 4) for k2, v in result.timings.items()},
            "total_s": round(time.perf_counter() - t0, 4),
            **({"passes": light} if splat else {
                "iterations": k,
                "residuals": [float(x) for x in np.asarray(light.residuals)[:k]],
                "error_estimate": float(light.error_estimate)}),
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
        what = "splat" if splat else f"{k} iterations"
        print(f"{out / 'report.json'}: {what}, {report['total_s']:.1f} s")
    return 0


def _parse_kv(items, flag: str) -> list[tuple[str, str]]:
    out = []
    for it in items or []:
        if "=" not in it:
            raise DifffogError(f"{flag} {it!r}: expected NAME=VALUE")
        k, v = it.split("=", 1)
        out.append((k.strip(), v.strip()))
    return out


def _float(flag: str, key: str, text: str) -> float:
    try:
        return float(text)
    except ValueError:
        raise DifffogError(f"{flag} {key}={text}: {text!r} is not a number") from None


def _load_image(flag: str, cam: str, path: str):
    import numpy as np

    p = Path(path)
    if p.suffix != ".npy":
        raise DifffogError(f"{flag} {cam}={path}: give a .npy file of the (H, W) image")
    if not p.is_file():
        raise DifffogError(f"{flag} {cam}={path}: no such file")
    try:
        a = np.load(p, allow_pickle=False)
    except Exception as e:  # noqa: BLE001 - any unreadable file gets the same one-line answer
        raise DifffogError(f"{flag} {cam}={path}: cannot read it as .npy ({e})") from None
    if a.ndim != 2:
        raise DifffogError(f"{flag} {cam}={path}: expected an (H, W) image, got shape {a.shape}")
    return a


def _fit_plots(result, tmp: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import numpy as np

    hist = result.history
    steps = [h["step"] for h in hist]
    fig, (a1, a2) = plt.subplots(1, 2, figsize=(10, 4))
    a1.semilogy(steps, [max(h["loss"], 1e-30) for h in hist], "o-")
    a1.set_xlabel("step")
    a1.set_ylabel("loss ½Σr² (residual / target RMS)")
    a1.set_title("convergence")
    for p in result.paths:
        a2.plot(steps, [h["values"][p] / result.estimates[p] for h in hist], "o-", label=p)
    a2.set_xlabel("step")
    a2.set_ylabel("value / final estimate")
    a2.set_title("unknowns")
    a2.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(tmp / "convergence.png", dpi=100)
    plt.close(fig)
    for name, fitted in result.images.items():
        target = result.targets[name]
        res = fitted - target
        fig, ax = plt.subplots(1, 3, figsize=(12, 3.6))
        vmax = float(np.percentile(target, 99.5)) or 1.0
        for a, img, title in ((ax[0], target, "target"), (ax[1], fitted, "fitted")):
            im = a.imshow(img, vmin=0, vmax=vmax, cmap="gray")
            a.set_title(f"{name}: {title}")
            fig.colorbar(im, ax=a, label="radiance")
        r = float(np.percentile(np.abs(res), 99.5)) or 1.0
        im = ax[2].imshow(res, vmin=-r, vmax=r, cmap="RdBu_r")
        ax[2].set_title(f"{name}: fitted − target")
        fig.colorbar(im, ax=ax[2], label="radiance")
        for a in ax:
            a.set_xlabel("pixel column")
            a.set_ylabel("pixel row")
        fig.tight_layout()
        fig.savefig(tmp / f"{name}_fit.png", dpi=100)
        plt.close(fig)


def cmd_fit(args) -> int:
    import warnings

    import numpy as np

    from ._fit import IdentifiabilityWarning, Unknown, fit
    from ._scene_io import load_scene

    if args.accuracy is None:  # the fit API's defaults: N = 32, M = 3 (a step is 1 + n solves)
        args.resolution = 32 if args.resolution is None else args.resolution
        args.directions = 3 if args.directions is None else args.directions
    else:
        _apply_accuracy(args, args.forward)
    _positive_int("--resolution", args.resolution)
    _positive_int("--directions", args.directions)
    _positive_int("--max-steps", args.max_steps)
    _positive_int("--devices", args.devices)
    scene = load_scene(args.scene, args.overrides)
    targets = {}
    for cam, path in _parse_kv(args.target, "--target"):
        scene.camera(cam)
        targets[cam] = _load_image("--target", cam, path)
    if not targets:
        raise DifffogError("give at least one --target CAMERA=PATH.npy")
    weights = {}
    for cam, path in _parse_kv(args.mask, "--mask"):
        if cam not in targets:
            raise DifffogError(f"--mask {cam}=…: camera '{cam}' has no --target")
        weights[cam] = _load_image("--mask", cam, path).astype(float)
    bounds = {}
    for key, val in _parse_kv(args.bounds, "--bounds"):
        parts = val.split(",")
        if len(parts) != 2:
            raise DifffogError(f"--bounds {key}={val}: expected LOWER,UPPER")
        bounds[key] = tuple(_float("--bounds", key, x) for x in parts)
    unknowns = []
    for item in args.unknown or []:
        path, _, init = item.partition("=")
        lo, hi = bounds.pop(path.strip(), (None, None))
        unknowns.append(Unknown(path.strip(), _float("--unknown", path, init) if init else None,
                                lo, hi))
    if not unknowns:
        raise DifffogError("give at least one --unknown PATH[=INIT], e.g. "
                           "--unknown fog.scattering=1.0")
    if bounds:
        raise DifffogError(f"--bounds {next(iter(bounds))}: not among the --unknown paths")
    if args.downsample is None:  # the largest of 4, 2, 1 dividing every target camera
        cams = [scene.camera(c) for c in targets]
        down = next(k for k in (4, 2, 1) if all(c.width % k == 0 and c.height % k == 0
                                                for c in cams))
    else:
        down = _positive_int("--downsample", args.downsample)
    out = Path(args.out)
    if out.exists() and not out.is_dir():
        raise DifffogError(f"--out {out}: exists and is not a folder; choose a folder path")
    ckpt = out.parent / f".{out.name}.fit-checkpoint.npz"
    if args.resume and not ckpt.exists():
        raise DifffogError(f"--resume: no checkpoint {ckpt} (a killed `difffog fit --out {out}` "
                           f"leaves one); run without --resume")
    progress = sys.stderr.isatty() and not args.quiet
    t0 = time.perf_counter()
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always", IdentifiabilityWarning)
        result = fit(scene, targets, unknowns, solver=args.solver, forward=args.forward,
                     resolution=args.resolution, directions=args.directions, downsample=down,
                     weights=weights or None, loss=args.loss, max_steps=args.max_steps,
                     devices=args.devices, checkpoint=ckpt, resume=args.resume,
                     progress=progress)
    del caught  # the warnings are in result.warnings (and fit.json)
    out.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=".difffog-", dir=out.parent))
    try:
        report = result.to_json()
        report.update({
            "scene": scene.title,
            "source": str(scene.source) if scene.source else None,
            "overrides": args.overrides,
            "targets": {c: str(p) for c, p in _parse_kv(args.target, "--target")},
            "total_s": round(time.perf_counter() - t0, 3),
            "peak_memory_mb": _peak_memory_mb(),
            "resumed": bool(args.resume),
        })
        (tmp / "fit.json").write_text(json.dumps(report, indent=1))
        for name, img in result.images.items():
            np.save(tmp / f"{name}_fit.npy", img)
            np.save(tmp / f"{name}_target.npy", result.targets[name])
            np.save(tmp / f"{name}_residual.npy", img - result.targets[name])
        _fit_plots(result, tmp)
        out.mkdir(parents=True, exist_ok=True)
        for f in tmp.iterdir():
            os.replace(f, out / f.name)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    if result.converged and ckpt.exists():
        ckpt.unlink()
    if not args.quiet:
        print(result.summary())
        print(f"{out / 'fit.json'}: {result.iterations} steps, {report['total_s']:.1f} s")
        if not result.converged:
            print(f"the checkpoint {ckpt} is kept: add --resume (and a larger --max-steps) to "
                  f"continue")
    return 0 if result.converged else 1


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
    p.add_argument("--solver", default="sweep", choices=["sweep", "splat"],
                   help="light solver: sweep (discrete ordinates, accurate) or splat (sheet-based "
                        "splatting, fast and approximate; needs a [sun])")
    p.add_argument("--sheets", type=int, metavar="K",
                   help="splat: sheets per camera pass (default: one per voxel)")
    g = p.add_mutually_exclusive_group()
    p.add_argument("--method", default="auto", choices=["auto", "gmres", "jacobi"],
                   help="iteration: GMRES (auto, the default: measured 1.2-94x faster) or Jacobi")
    g.add_argument("--iterations", type=int,
                   help="run exactly this many iterations (applications of the six sweeps)")
    g.add_argument("--tol", type=float,
                   help="stop when the estimated remaining relative error is below (default 1e-4)")
    p.add_argument("--supersample", type=int, default=None,
                   help="s×s rays per pixel, averaged (box filter; default 2, splat 1)")
    p.add_argument("--devices", type=int, default=1, metavar="N",
                   help="run the sweeps on N devices (faces and plane blocks; on a CPU, N host "
                        "devices sharing its cores; default 1)")
    p.add_argument("--out", default="out", help="output folder (default: out)")
    p.add_argument("--quiet", "-q", action="store_true", help="no progress or summary")
    p.set_defaults(func=cmd_render)
    p = sub.add_parser("bench", help="the speed-accuracy study: both solvers over their knobs "
                                      "against the Monte Carlo references; CSV + Pareto plot")
    p.add_argument("--scenes", nargs="+", default=["fog-balls", "ring-box", "translucent-cube",
                                                   "cloud-plane"],
                   help="scenes with reference images (default: the four benchmark scenes)")
    p.add_argument("--solvers", nargs="+", default=["sweep", "splat"], choices=["sweep", "splat"])
    p.add_argument("--references", default=None, metavar="DIR",
                   help="reference images (<scene>/<camera>.npy, convergence.csv); default: "
                        "../shared/references beside the repository")
    p.add_argument("--quick", action="store_true", help="one small setting per solver (a smoke test)")
    p.add_argument("--out", default="bench", help="output folder (default: bench)")
    p.add_argument("--quiet", "-q", action="store_true", help="no progress or summary")
    p.set_defaults(func=cmd_bench)
    p = sub.add_parser("fit", help="fit fog and surface parameters to target images")
    _add_scene_args(p, 32)
    p.add_argument("--target", action="append", metavar="CAMERA=PATH.npy",
                   help="a target image (H, W) of a scene camera (repeatable: several views)")
    p.add_argument("--unknown", action="append", metavar="PATH[=INIT]",
                   help="a parameter to fit, e.g. fog.scattering=1.0 (repeatable; default "
                        "initial value: the scene's)")
    p.add_argument("--bounds", action="append", metavar="PATH=LOWER,UPPER",
                   help="bounds of an unknown (default: (0, inf) for coefficients, (0, 1) "
                        "for albedo)")
    p.add_argument("--mask", action="append", metavar="CAMERA=PATH.npy",
                   help="per-pixel weights >= 0 (or a 0/1 mask) for a target")
    p.add_argument("--forward", default="sweep", choices=["sweep", "splat"],
                   help="forward model (default sweep)")
    p.add_argument("--solver", default="lm", choices=["lm", "gauss-newton", "bfgs"],
                   help="optimiser: Levenberg-Marquardt (default), Gauss-Newton or BFGS")
    p.add_argument("--loss", default="linear", choices=["linear", "huber", "soft_l1", "cauchy"],
                   help="residual loss (default linear = least squares)")
    p.add_argument("--downsample", type=int, default=None,
                   help="render the cameras at 1/K width and height, box-averaging the "
                        "targets to match (default: the largest of 4, 2, 1 that divides)")
    p.add_argument("--max-steps", type=int, default=50, help="optimiser steps (default 50)")
    p.add_argument("--devices", type=int, default=1, metavar="N",
                   help="share each light solve over N devices (the sweep; on a CPU, N host "
                        "devices sharing its cores; the same estimates; default 1)")
    # a fit solves 1 + (number of unknowns) light problems per step: without --accuracy it
    # uses the API's N = 32, M = 3 rather than the render presets
    p.set_defaults(accuracy=None)
    p.add_argument("--resume", action="store_true",
                   help="continue a killed fit from its checkpoint (.OUT.fit-checkpoint.npz)")
    p.add_argument("--out", default="fit", help="output folder (default: fit)")
    p.add_argument("--quiet", "-q", action="store_true", help="no progress or summary")
    p.set_defaults(func=cmd_fit)
    return parser


def cmd_bench(args) -> int:
    from ._bench import run_bench

    progress = sys.stderr.isatty() and not args.quiet
    res = run_bench(scenes=args.scenes, solvers=args.solvers, out=Path(args.out),
                    references=Path(args.references) if args.references else None,
                    quick=args.quick, progress=progress)
    if not args.quiet:
        print(res.summary_path.read_text())
        print(f"{res.csv_path}, {res.plot_path}: {len(res.rows)} rows")
    return 0


def _host_devices(n: int) -> None:
    """Ask XLA for n host (CPU) devices if JAX has not started yet and nobody chose a count;
    on a GPU machine the flag only concerns the host platform, so it is harmless."""
    try:  # XLA reads the flag when the first backend starts, not at ``import jax``
        from jax._src import xla_bridge

        started = xla_bridge.backends_are_initialized()
    except (ImportError, AttributeError):
        started = "jax" in sys.modules
    if n > 1 and not started:
        flags = os.environ.get("XLA_FLAGS", "")
        if "xla_force_host_platform_device_count" not in flags:
            os.environ["XLA_FLAGS"] = f"{flags} --xla_force_host_platform_device_count={n}".strip()


def main(argv=None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    _host_devices(getattr(args, "devices", 1) or 1)
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
