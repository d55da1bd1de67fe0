"""``difffog fit``: fit fog and surface parameters to target images, with a checkpoint after
every step, ``fit.json``, the fitted/target/residual images and convergence plots."""

from __future__ import annotations

import json
import sys
import time
from pathlib import Path

from .._errors import DifffogError, MemoryWarning
from ..fit._stepper import OPTIMIZERS
from ..forward._registry import SOLVERS, solver_entry
from ._main import add_scene_args, model_settings, peak_memory_mb, positive_int, solver_help


def _ladder(text: str):
    """--ladder: "auto", "none" or "NC,N"."""
    if text in ("auto", "none"):
        return None if text == "none" else "auto"
    try:
        levels = tuple(int(x) for x in text.split(","))
    except ValueError:
        levels = ()
    if len(levels) != 2:
        raise DifffogError(f"--ladder {text}: use auto, none or two resolutions NC,N (e.g. 24,32)")
    return levels


def _model_floor(text: str):
    """--model-floor: "auto" or a relative brightness (0.005, 0.5%)."""
    if text == "auto":
        return "auto"
    try:
        value = float(text[:-1]) / 100 if text.endswith("%") else float(text)
    except ValueError:
        value = None
    if value is None or not 0.0 <= value < 1.0:
        raise DifffogError(f"--model-floor {text}: use auto or a relative brightness in [0, 1) "
                           f"such as 0.005 or 0.5% (0 leaves it out)")
    return value


def _model_error(text: str):
    """--model-error: "refine", "none" or a resolution N."""
    if text in ("refine", "none"):
        return None if text == "none" else "refine"
    try:
        return int(text)
    except ValueError:
        raise DifffogError(f"--model-error {text}: use refine, none or a finer resolution N "
                           f"(e.g. 64)") from None


def _refine_steps(k: int) -> int:
    """--refine-steps: an integer ≥ 1."""
    if k < 1:
        raise DifffogError(f"--refine-steps {k}: give the most renders of the finer model the "
                           f"correction takes, 1 or more (default 4; 1: one Gauss-Newton step)")
    return k


def add_parser(sub) -> None:
    p = sub.add_parser("fit", help="fit fog and surface parameters to target images")
    add_scene_args(p)
    p.add_argument("--target", action="append", metavar="CAMERA=FILE",
                   help="a target image of a scene camera (repeatable: several views): .npy "
                        "(linear radiance), .png (8/16-bit), .tif (8/16-bit, float), .exr "
                        "(half, float) or .jpg")
    p.add_argument("--channel", default="luminance", choices=["luminance", "r", "g", "b"],
                   help="colour targets to one channel: luminance (default: Y = 0.2126 R + "
                        "0.7152 G + 0.0722 B of the linear values) or one channel")
    p.add_argument("--transfer", default="auto", choices=["auto", "srgb", "linear"],
                   help="encoding of target files: auto (default: sRGB for 8-bit, linear for "
                        "16-bit and float), srgb or linear")
    p.add_argument("--unknown", action="append", metavar="PATH[=INIT]",
                   help="a parameter to fit, e.g. fog.scattering=1.0, or a gain on the images "
                        "(exposure, camera.NAME.exposure; for photographs), or the sun's "
                        "direction (sun.zenith_deg, sun.azimuth_deg; sweep solver) (repeatable; "
                        "default initial value: the scene's; an exposure's: the best gain for "
                        "the first render)")
    p.add_argument("--bounds", action="append", metavar="PATH=LOWER,UPPER",
                   help="bounds of an unknown (default: (0, inf) for coefficients, (0, 1) "
                        "for albedo, (0, 90) for the sun's zenith, (-360, 360) for its azimuth)")
    p.add_argument("--mask", action="append", metavar="CAMERA=FILE",
                   help="a target's mask: .npy weights >= 0, or an image file used where its "
                        "alpha (else any channel) is nonzero, e.g. the photo itself")
    p.add_argument("--edge-weight", type=float, default=1.0, metavar="W",
                   help="weight (0 to 1) of the pixels that straddle a geometric or a shadow "
                        "edge, known from the exact geometry (default 1: as any pixel; 0: left "
                        "out); fit.json records the share of each view it applies to")
    p.add_argument("--solver", default="sweep", choices=list(SOLVERS),
                   help="forward model (default sweep); " + solver_help())
    p.add_argument("--optimizer", default="lm", choices=list(OPTIMIZERS),
                   help="Levenberg-Marquardt (lm, default), Gauss-Newton or BFGS")
    p.add_argument("--loss", default="linear", choices=["linear", "huber", "soft_l1", "cauchy"],
                   help="residual loss (default linear = least squares)")
    p.add_argument("--downsample", type=int, default=None,
                   help="render the cameras at 1/K width and height, box-averaging the "
                        "targets to match (default: the largest of 4, 2, 1 that divides; "
                        "--unknown fog.density: every level at 1/K, default per level about "
                        "one pixel per lattice node, two on the final grid)")
    p.add_argument("--max-steps", type=int, default=None,
                   help="optimizer steps (default 50; --unknown fog.density: evaluations per "
                        "grid level, default 20, and 40 for the final grid)")
    p.add_argument("--ladder", default="none", metavar="auto|none|NC,N",
                   help="experimental estimate of the model's own error: fit at a coarser "
                        "resolution first (auto: 3/4 of -N), then at -N from there; the "
                        "change, extrapolated to first order, is each estimate's model error, "
                        "added to its uncertainty in fit.json (default none: noise only)")
    p.add_argument("--model-error", default="refine", metavar="refine|none|N",
                   help="correct the estimates for the lattice and state its error: render "
                        "the fitted model once more on a lattice twice as fine (or N) with one "
                        "more direction and take the Gauss-Newton step that image change "
                        "causes, then more such steps from where it lands (--refine-steps); "
                        "the estimates are the fit moved by them (fit.json's fitted: the "
                        "fit itself); their model error, from that step and two checks (a "
                        "lattice between, M + 1), is added to the uncertainty (default refine; "
                        "none: the fit itself, noise only)")
    p.add_argument("--refine-steps", type=int, default=4, metavar="K",
                   help="with --model-error: the most renders of the finer model its correction "
                        "takes, stopping when a step moves every estimate by less than a tenth "
                        "of its stated uncertainty (default 4; 1: one Gauss-Newton step)")
    p.add_argument("--model-floor", default="auto", metavar="auto|F",
                   help="with --model-error: also count, in each estimate's model error, a "
                        "relative brightness bias F of one camera's images at a time, the "
                        "forward model's brightness against independent truth that no finer "
                        "lattice reveals (default auto: the solver's validated figure, 0.5%% "
                        "for the sweep; 0 leaves it out)")
    p.add_argument("--prior", default=None, metavar="KIND=WEIGHT",
                   help="--unknown fog.density: the prior and its weight relative to the "
                        "images' mean squared misfit: shape=W (the squared gradient at a "
                        "fixed mass: it does not pull the mass down), smooth=W (squared "
                        "gradient) or tv=W (total variation), a fixed weight; "
                        "smooth=balance or shape=balance: start at the default weight and "
                        "choose it per fit by the balancing principle (default "
                        + _default_prior() + ", balanced)")
    p.add_argument("--grid", type=int, default=None, metavar="N",
                   help="--unknown fog.density: the estimate's grid, N cells along each axis "
                        "(default: the scene's density grid, or 32)")
    p.add_argument("--devices", type=int, default=None, metavar="N",
                   help="sweep: share each light solve over N devices (on a CPU, N host "
                        "devices sharing its cores; the same estimates; default 1)")
    # without --accuracy a fit uses the solver's fit defaults (the sweep: N = 32, M = 3)
    p.set_defaults(accuracy=None)
    p.add_argument("--resume", action="store_true",
                   help="continue a killed fit from its checkpoint (.OUT.fit-checkpoint.npz)")
    p.add_argument("--force", action="store_true",
                   help="run even where the estimated peak memory exceeds what this machine "
                        "has (refused otherwise, before anything is allocated)")
    p.add_argument("--out", default="fit", help="output folder (default: fit)")
    p.add_argument("--quiet", "-q", action="store_true", help="no progress or summary")
    p.set_defaults(func=run)


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


def run(args) -> int:
    import warnings

    import numpy as np

    from .._output import atomic_folder, check_out_dir
    from .._progress import NoProgress, TqdmProgress
    from ..fit._driver import fit
    from ..fit._result import IdentifiabilityWarning
    from ..fit._unknowns import Unknown
    from ..scene._toml import load_scene

    for flag, v in (("--resolution", args.resolution), ("--directions", args.directions),
                    ("--max-steps", args.max_steps), ("--devices", args.devices)):
        positive_int(flag, v)
    density_fit = any(u.partition("=")[0].strip() == "fog.density" for u in args.unknown or [])
    if args.max_steps is None and not density_fit:
        args.max_steps = 50
    # without --accuracy a fit uses the solver's fit defaults (the sweep: N = 32, M = 3; a
    # step is 1 + n light solves), else that preset; single flags override either
    settings = model_settings(args, args.solver, accuracy=args.accuracy)
    resolution = settings.pop("resolution", None)
    if args.force:
        settings["force"] = True
    scene = load_scene(args.scene, args.overrides)
    # files are read by the fit (fit/_images.py), which records how in fit.json
    targets = {}
    for cam, path in _parse_kv(args.target, "--target"):
        scene.camera(cam)
        targets[cam] = path
    if not targets:
        raise DifffogError("give at least one --target CAMERA=FILE, e.g. --target top=photo.png")
    weights = {}
    for cam, path in _parse_kv(args.mask, "--mask"):
        if cam not in targets:
            raise DifffogError(f"--mask {cam}=…: camera '{cam}' has no --target")
        weights[cam] = path
    bounds = {}
    for key, val in _parse_kv(args.bounds, "--bounds"):
        parts = val.split(",")
        if len(parts) != 2:
            raise DifffogError(f"--bounds {key}={val}: expected LOWER,UPPER")
        bounds[key] = tuple(_float("--bounds", key, x) for x in parts)
    if density_fit:
        return _run_density(args, scene, targets)
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
        down = positive_int("--downsample", args.downsample)
    out = check_out_dir(args.out)
    ckpt = out.parent / f".{out.name}.fit-checkpoint.npz"
    if args.resume and not ckpt.exists():
        raise DifffogError(f"--resume: no checkpoint {ckpt} (a killed `difffog fit --out {out}` "
                           f"leaves one); run without --resume")
    progress = TqdmProgress("fit") if sys.stderr.isatty() and not args.quiet else NoProgress()
    t0 = time.perf_counter()
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always", IdentifiabilityWarning)
        result = fit(scene, targets, unknowns, optimizer=args.optimizer, forward=args.solver,
                     resolution=resolution, model_settings=settings or None, downsample=down,
                     weights=weights or None, loss=args.loss, max_steps=args.max_steps,
                     channel=args.channel, transfer=args.transfer, checkpoint=ckpt,
                     resume=args.resume, progress=progress, ladder=_ladder(args.ladder),
                     edge_weight=args.edge_weight,
                     model_error=(None if args.ladder != "none"
                                  else _model_error(args.model_error)),
                     model_floor=_model_floor(args.model_floor),
                     refine_steps=_refine_steps(args.refine_steps))
    for w in caught:  # the fit's own warnings are in result.warnings (and fit.json)
        if issubclass(w.category, MemoryWarning):
            print(f"difffog: warning: {w.message}", file=sys.stderr)
    del caught
    with atomic_folder(out) as tmp:
        report = result.to_json()
        report.update({
            "scene": scene.title,
            "source": str(scene.source) if scene.source else None,
            "overrides": args.overrides,
            "targets": {c: str(p) for c, p in _parse_kv(args.target, "--target")},
            "total_s": round(time.perf_counter() - t0, 3),
            "peak_memory_mb": peak_memory_mb(),
            "resumed": bool(args.resume),
        })
        (tmp / "fit.json").write_text(json.dumps(report, indent=1))
        for name, img in result.images.items():
            # .npy only: {name}_fit.png is the target/fitted/residual figure (_fit_plots)
            np.save(tmp / f"{name}_fit.npy", img)
            np.save(tmp / f"{name}_target.npy", result.targets[name])
            np.save(tmp / f"{name}_residual.npy", img - result.targets[name])
        _fit_plots(result, tmp)
    if result.converged and ckpt.exists():
        ckpt.unlink()
    if args.quiet:  # the summary that lists them is not printed: its warnings still are
        for said in result.warnings:
            print(f"difffog: warning: {said}", file=sys.stderr)
    else:
        print(result.summary())
        print(f"{out / 'fit.json'}: {result.iterations} steps, {report['total_s']:.1f} s")
        if not result.converged:
            print(f"the checkpoint {ckpt} is kept: add --resume (and a larger --max-steps) to "
                  f"continue")
    return 0 if result.converged else 1


def _density_plots(result, tmp: Path) -> None:
    """density.png: the estimate's middle slices along each axis, beside its loss."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import numpy as np

    d = result.density
    fig, ax = plt.subplots(1, 4, figsize=(15, 3.6))
    vmax = float(d.max()) or 1.0
    for a, (axis, label) in enumerate(((0, "x"), (1, "y"), (2, "z"))):
        sl = np.take(d, d.shape[axis] // 2, axis=axis)
        im = ax[a].imshow(sl.T, origin="lower", vmin=0, vmax=vmax, cmap="magma")
        ax[a].set_title(f"density, middle {label} slice")
        ax[a].set_xlabel("cell" if axis else "y cell")
        fig.colorbar(im, ax=ax[a])
    losses = [h["loss"] for h in result.history if "loss" in h]
    ax[3].semilogy(range(1, len(losses) + 1), losses, "o-", ms=3)
    ax[3].set_xlabel("evaluation")
    ax[3].set_ylabel("loss (relative misfit + prior)")
    ax[3].set_title("convergence")
    fig.tight_layout()
    fig.savefig(tmp / "density.png", dpi=100)
    plt.close(fig)


def _default_prior() -> str:
    from ..fit._density import DEFAULT_PRIOR, PRIORS

    return f"{DEFAULT_PRIOR}={PRIORS[DEFAULT_PRIOR]:g}"


def _run_density(args, scene, targets) -> int:
    """``difffog fit SCENE --unknown fog.density``: density tomography (``fit_density``)."""
    from .._output import atomic_folder, check_out_dir
    from .._progress import NoProgress, TqdmProgress
    from ..fit._density import BALANCE, DEFAULT_PRIOR, PRIORS, fit_density
    from ..fit._images import load_target

    # the model flags a density fit's levels do not take: refused, not ignored
    for flag, attr in (("--phase-order", "phase_order"), ("--first-collision", "first_collision"),
                       ("--devices", "devices")):
        if getattr(args, attr, None) is not None:
            raise DifffogError(f"{flag} does not apply to --unknown fog.density (its models take "
                               f"-N, -M, --scheme and --once-M); drop it")
    others = [u for u in args.unknown if u.partition("=")[0].strip() != "fog.density"]
    if others:
        raise DifffogError(f"--unknown fog.density is fitted alone; drop --unknown {others[0]} "
                           f"(fit the scalars first, then the density with them set)")
    if not solver_entry(args.solver).traces_density:
        able = [n for n, e in SOLVERS.items() if e.traces_density]
        raise DifffogError(f"--unknown fog.density: --solver {args.solver} does not trace the "
                           f"density; use --solver {' or '.join(able)}")
    kind, weight, balance = DEFAULT_PRIOR, None, None
    if args.prior is not None:
        kind, _, val = args.prior.partition("=")
        kind = kind.strip()
        if kind not in PRIORS or not val:
            raise DifffogError(f"--prior {args.prior}: use KIND=WEIGHT with KIND one of "
                               f"{', '.join(PRIORS)}, e.g. --prior {_default_prior()}")
        if val.strip() == "balance":
            if kind not in BALANCE:
                raise DifffogError(f"--prior {kind}=balance: {kind} has no balancing share "
                                   f"(only {' and '.join(BALANCE)} have); give {kind} a weight, "
                                   f"e.g. --prior {kind}={PRIORS[kind]:g}")
            balance = True
        else:
            weight = _float("--prior", kind, val)
            if weight < 0:
                raise DifffogError(f"--prior {kind}={val}: the weight must be >= 0")
    grid = None if args.grid is None else positive_int("--grid", args.grid)
    if scene.fog is None:
        raise DifffogError("--unknown fog.density: the scene has no [fog]; add one")
    start = None
    if scene.fog.density is None:
        import numpy as np

        start = np.ones((grid or 32,) * 3)
    images = {}
    for cam, path in targets.items():
        img, _ = load_target(path, channel=args.channel, transfer=args.transfer)
        images[cam] = img
    out = check_out_dir(args.out)
    ckpt = out.parent / f".{out.name}.density-checkpoint.npz"
    if args.resume and not ckpt.exists():
        raise DifffogError(f"--resume: no checkpoint {ckpt} (a killed or stopped `difffog fit "
                           f"--unknown fog.density --out {out}` leaves one); run without "
                           f"--resume")
    progress = TqdmProgress("density fit") if sys.stderr.isatty() and not args.quiet \
        else NoProgress()
    t0 = time.perf_counter()
    kw = {} if args.max_steps is None else {"max_steps": args.max_steps}
    if args.resolution is not None:  # the final level's lattice; coarser ones at most that
        kw["resolution"] = args.resolution
    if args.downsample is not None:
        kw["downsample"] = positive_int("--downsample", args.downsample)
    # the model settings a density fit takes from the flags (without --scheme: fit_density's
    # DENSITY_SCHEME)
    model = {k: getattr(args, k, None) for k in ("scheme", "once_M")}
    if model := {k: v for k, v in model.items() if v is not None}:
        kw["settings"] = model
    result = fit_density(scene, images, start=start, grid=grid, prior=kind, prior_weight=weight,
                         balance=balance, M=args.directions or 3, progress=progress, checkpoint=ckpt,
                         resume=args.resume, **kw)
    with atomic_folder(out) as tmp:
        result.save(tmp)
        report = json.loads((tmp / "fit.json").read_text())
        report.update({"scene": scene.title, "overrides": args.overrides,
                       "targets": {c: str(p) for c, p in targets.items()},
                       "total_s": round(time.perf_counter() - t0, 3),
                       "peak_memory_mb": peak_memory_mb(), "resumed": bool(args.resume)})
        (tmp / "fit.json").write_text(json.dumps(report, indent=1))
        _density_plots(result, tmp)
    ok = result.result == "successful"
    if ok and ckpt.exists():
        ckpt.unlink()
    if not args.quiet:
        lv = result.levels[-1]
        print(f"density {'x'.join(map(str, result.density.shape))}: {result.result}, loss "
              f"{lv['loss']:.3g} after {sum(x['steps'] for x in result.levels)} evaluations, "
              f"{result.time_s:.1f} s; {out / 'density.npz'}")
        bal = lv.get("balance")
        if bal:
            print(f"prior weight {' -> '.join(f'{w:.3g}' for w in bal['prior_weights'])} "
                  f"(prior/data {', '.join(f'{r:.2g}' for r in bal['shares'])}; aim "
                  f"{bal['target']:g})")
        if not ok and ckpt.exists():
            print(f"the checkpoint {ckpt} is kept: add --resume (and a larger --max-steps) to "
                  f"continue")
    return 0 if ok else 1
