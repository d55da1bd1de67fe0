"""Inverse fog estimation: fit ζ, γ, albedo (and nuisance parameters) to images.

``fit(scene, targets, unknowns)`` renders every target camera from one light solve per step,
compares with the targets and lets optimistix (Levenberg–Marquardt by default, Gauss–Newton or
BFGS on request) move the unknowns in unconstrained coordinates (``_unknowns.py``).
``fit_batch`` steps many fits of the same unknowns together, vmapped over devices.  Both run
the same per-step bookkeeping (:class:`_Tracker`): history, stall test, light-solve check.
"""

from __future__ import annotations

import dataclasses
import functools
import math
import os
import time
import warnings
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optimistix as optx

from .._cost import fit_edge_samples
from .._errors import (AdjointWarning, DifffogError, ResourceError, ThickStepWarning,
                       ThinLayerWarning)
from .._progress import as_meter, sibling
from .._results import RESULTS
from ..forward._model import AbstractForwardModel, batch_devices, map_batch
from ..forward._registry import check_settings, guard, solver_entry
from ..scene._description import Scene
from ..scene._params import SUN_PATHS, set_param
from . import _bound, _checkpoint, _misfit
from ._images import load_files
from ._misfit import MisfitWarning
from ._result import FitResult, IdentifiabilityWarning, level_label, result_name, statistics
from ._residuals import LOSSES, tangent_start
from ._stepper import make_optimizer, stepper_for
from ._targets import prepare_targets, reduced_scene
from ._unknowns import Coordinate, as_unknowns, coordinates, exposure_camera, within_bounds


def make_model(scene: Scene, forward="sweep", *, cameras: list[str], downsample: int = 1,
               resolution: int | None = None, model_settings: Mapping | None = None,
               unknowns: int = 1, sun: bool | float = False):
    """The forward model of a fit: ``forward`` as it is if it is a model, else the registry's
    solver of that name at its fit defaults (overridden by ``resolution`` and
    ``model_settings``), rendering the target cameras reduced by ``downsample``; its memory is
    checked for a Jacobian of ``unknowns`` columns.  ``sun``: the sun's angles are unknowns
    (the model is built with their derivatives, ``SweepModel.with_sun_derivatives``, with this
    step in degrees if a number)."""
    if isinstance(forward, AbstractForwardModel):
        if model_settings or resolution is not None:
            raise DifffogError("fit: resolution and model_settings apply when forward is a "
                               "solver name; the forward model given is already built")
        return _with_sun(forward, sun) if sun else forward
    if not isinstance(forward, str):
        raise DifffogError(f"forward: {type(forward).__name__} is not a forward model; pass a "
                           f"solver name ('sweep', 'splat') or difffog.forward_model(...)")
    entry = solver_entry(forward)
    settings = dict(model_settings or {})
    force = bool(settings.pop("force", False))
    check_settings(forward, settings, "fit: model_settings")
    if resolution is not None:
        settings["resolution"] = resolution
    small = reduced_scene(scene, cameras, downsample)
    full = {**entry.fit_defaults, **settings}
    if "edge_samples" in entry.settings and "edge_samples" not in settings:
        full["edge_samples"] = fit_edge_samples(downsample)
    # the memory guard: a fit's Jacobian holds one tangent solve's Krylov vectors per unknown
    # besides the forward solve (0 unknowns: a model that only renders, the model error's)
    est = guard(small, forward, force=force, tangent_solves=max(0, int(unknowns)),
                what=f"the fit's {forward} model", **full)
    if sun and not entry.traces_sun:  # before building it
        raise _fixed_sun(f"the {forward} forward model")
    key = _model_key(scene, forward, cameras, downsample, full, sun)
    model = _MODELS.pop(key, None) if key is not None else None
    if model is None:
        model = entry.build(small, **full)
        model = _with_sun(model, sun) if sun else model
    if key is not None and math.prod(getattr(est, "shape", (math.inf,))) <= MODEL_CACHE_NODES:
        _MODELS[key] = model  # the most recent last
        while len(_MODELS) > MODEL_CACHE_SIZE:
            _MODELS.pop(next(iter(_MODELS)))
    return model


# Forward models that fits built recently (a fit's own and its model error's finer ones), so
# that the same fit again in a process (a notebook cell run twice) does not prepare them
# again: ~1 s of host set-up for the README example's four.  Only lattices of up to
# MODEL_CACHE_NODES nodes are kept (their models hold tens of MB, not the GBs a fine cloud's
# would), at most MODEL_CACHE_SIZE of them.  A model is immutable, so sharing one is safe.
_MODELS: dict = {}
MODEL_CACHE_SIZE = 4
MODEL_CACHE_NODES = 80 ** 3


def _model_key(scene, forward, cameras, downsample, full, sun):
    """The cache key of a built model, or None where a setting cannot be hashed (with JAX's
    float64 switch: a model's arrays take the default dtype where it does not say one)."""
    key = (scene, forward, tuple(cameras), int(downsample),
           tuple(sorted(full.items())), sun if isinstance(sun, bool) else float(sun),
           bool(jax.config.jax_enable_x64))
    try:
        hash(key)
    except TypeError:
        return None
    return key


def _fixed_sun(what: str) -> DifffogError:
    return DifffogError(f"sun.zenith_deg / sun.azimuth_deg: {what} takes the sun's direction "
                        f"as fixed; fit the sun with forward=\"sweep\"")


def _has_sun(unknowns) -> bool:
    """Whether the sun's angles are among the unknowns."""
    return any(u.path in SUN_PATHS for u in as_unknowns(unknowns))


def _with_sun(model, step=True):
    """``model`` able to trace the sun's angles (a one-line error for a solver that cannot),
    its host quantities linearized with ``step`` degrees (True: the model's default, or the
    step it has)."""
    if not hasattr(model, "with_sun_derivatives"):
        raise _fixed_sun(f"a {type(model).__name__}")
    lin = getattr(model, "sun_lin", None)
    if step is True:
        return model if lin is not None else model.with_sun_derivatives()
    if lin is not None and float(lin.step) == float(step):
        return model
    return model.with_sun_derivatives(float(step))


@dataclass
class _Setup:
    """Everything a fit needs before its first step (shared by fit and fit_batch)."""

    model: Any
    names: list[str]
    tgt: dict
    flat_t: np.ndarray
    m: int
    data: tuple
    u0: Any
    coords: list
    inits: list
    stepper: Any
    settings: dict
    fingerprint: str
    target_files: dict
    mask_files: dict
    # what the compiled steps run: the model, or with the sun's angles as unknowns its
    # ``traced_sun_form`` (shared by the rounds that rebuild it at the estimated sun)
    run: Any

    @property
    def args(self):
        return (self.run, self.data)

    def values(self, u) -> dict[str, float]:
        return {c.path: float(c.to_v(x)) for c, x in zip(self.coords, np.asarray(u))}


def _inside(v: float, c: Coordinate) -> float:
    """v (1 where it is not a positive number) moved inside c's bounds by 1% where it is not."""
    v = v if math.isfinite(v) and v > 0 else 1.0
    if math.isinf(c.upper):
        return v if v > c.lower else c.lower * 1.01
    span = c.upper - c.lower
    return min(max(v, c.lower + 0.01 * span), c.upper - 0.01 * span)


def _exposure_starts(stepper, args, coords, inits, names, tgt, wts, dtype) -> list[float]:
    """``inits`` with each exposure given without a start (None) started at the gain that fits
    the first render y to the targets t by weighted least squares, Σw·y·t / Σw·y² (the
    global exposure over every camera, then each camera's own on top of it), at the other
    unknowns' starts: one light solve.  A photograph's scale (exposure time, aperture, ISO,
    the file's code values) is arbitrary, orders of magnitude from the scene's radiance; from
    1, a fit in log coordinates would spend several steps of 1 + n light solves each crossing
    them, and this gain is exact when the other unknowns are."""
    start = [_inside(1.0, c) if v is None else v for v, c in zip(inits, coords)]
    u = jnp.asarray([c.to_u(v) for c, v in zip(coords, start)], dtype)
    y = np.asarray(stepper.images(u, args)[0], np.float64)
    t = np.concatenate([tgt[n].ravel() for n in names])
    w = np.concatenate([wts[n].ravel() for n in names])
    ends = np.cumsum([tgt[n].size for n in names])
    part = {n: slice(e - tgt[n].size, e) for n, e in zip(names, ends)}
    auto = sorted((i for i, v in enumerate(inits) if v is None),
                  key=lambda i: exposure_camera(coords[i].path) != "")  # the global one first
    for i in auto:
        cam = exposure_camera(coords[i].path)
        sl = part[cam] if cam else slice(None)
        with np.errstate(invalid="ignore", divide="ignore"):
            gain = float(np.sum(w[sl] * y[sl] * t[sl]) / np.sum(w[sl] * y[sl] ** 2))
        new = _inside(start[i] * gain, coords[i])
        y[sl] *= new / start[i]
        start[i] = new
    return start


def _setup(scene: Scene, targets, unknowns, *, optimizer, forward, resolution, downsample,
           model_settings, weights, loss, loss_scale, rtol, atol, max_steps, stall_steps,
           dtype, channel, transfer, edge_weight=1.0, sun_step=None, sun_memo=None,
           fixed=None) -> _Setup:
    """What a fit at one resolution needs (``fit``'s arguments); ``fixed``: {path: value} of
    parameters held at a value other than the model's (an unknown held at its bound)."""
    unknowns = as_unknowns(unknowns)
    if loss not in LOSSES:
        raise DifffogError(f"loss '{loss}': choose one of {', '.join(LOSSES)}")
    for name, v in (("downsample", downsample), ("max_steps", max_steps)) + (
            (("resolution", resolution),) if resolution is not None else ()):
        if isinstance(v, bool) or not isinstance(v, (int, np.integer)) or v < 1:
            raise DifffogError(f"{name} must be a positive integer, got {v!r}")
    if isinstance(stall_steps, bool) or not isinstance(stall_steps, (int, np.integer)) \
            or stall_steps < 0:
        raise DifffogError(f"stall_steps must be an integer >= 0, got {stall_steps!r}")
    if not loss_scale > 0:
        raise DifffogError(f"loss_scale must be positive, got {loss_scale}")
    if isinstance(edge_weight, bool) or not isinstance(edge_weight, (int, float, np.number)) \
            or not 0.0 <= edge_weight <= 1.0:
        raise DifffogError(f"edge_weight must be a number in [0, 1] (1: edge pixels count as "
                           f"any other, 0: left out), got {edge_weight!r}")
    opt = make_optimizer(optimizer, rtol, atol)
    if not isinstance(targets, Mapping) or not targets:
        raise DifffogError("targets: give a dict {camera name: (H, W) image}, at least one")
    for name in targets:
        scene.camera(name)
    targets, weights, target_files, mask_files = load_files(targets, weights, channel=channel,
                                                            transfer=transfer)
    names = sorted(targets)  # a fixed order: fits of the same views share one compiled step
    model = make_model(scene, forward, cameras=names, downsample=downsample,
                       resolution=resolution, model_settings=model_settings,
                       unknowns=len(unknowns),
                       sun=_has_sun(unknowns) and (sun_step or True))
    tgt, wts = prepare_targets(scene, model, targets, weights, downsample, files=target_files)
    edge_share = _weigh_edges(model, names, wts, float(edge_weight))
    dtype = dtype or jnp.result_type(float)
    base = model.params(dtype)
    for path, v in (fixed or {}).items():
        base = set_param(base, model.scene, path, v)
    coords, given = coordinates(model.scene, base, unknowns)
    flat_t = np.concatenate([tgt[n].ravel() for n in names])
    flat_w = np.concatenate([wts[n].ravel() for n in names])
    m = int(np.count_nonzero(flat_w))
    scale = float(np.sqrt(np.sum(flat_w * flat_t ** 2) / np.sum(flat_w))) or 1.0
    run = _traced_sun_form(model, unknowns, sun_memo)
    data = (jnp.asarray(flat_t, dtype), jnp.asarray(np.sqrt(flat_w), dtype),
            jnp.asarray(scale, dtype), jnp.asarray(loss_scale, dtype), base,
            tangent_start(run, len(coords), dtype))
    stepper = stepper_for(run, coords, names, loss, opt)
    inits = (_exposure_starts(stepper, (run, data), coords, given, names, tgt, wts, dtype)
             if None in given else given)
    u0 = jnp.asarray([c.to_u(v) for c, v in zip(coords, inits)], dtype)
    settings = {
        "forward": forward if isinstance(forward, str) else type(forward).__name__,
        "optimizer": optimizer if isinstance(optimizer, str) else type(optimizer).__name__,
        "model": {k: v for k, v in model.settings().items()
                  if k in ("solver", "solver_options", "resolution", "supersample")},
        "downsample": downsample, "edge_weight": float(edge_weight),
        "edge_pixels": edge_share, "loss": loss, "loss_scale": loss_scale, "rtol": rtol,
        "atol": atol, "max_steps": max_steps, "stall_steps": stall_steps,
        "dtype": str(np.dtype(dtype)), "cameras": names,
        "image_shapes": {n: list(tgt[n].shape) for n in names},
        "unknowns": [dataclasses.asdict(c) for c in coords],
    }
    # the fingerprint leaves out the device count (a checkpoint resumes on any number of them),
    # max_steps (a stopped fit resumes with a larger one) and the exposures' starts from a
    # render (None: a light solve on other devices may differ in its last bits)
    fp_settings = dict(settings, model={k: v for k, v in settings["model"].items()
                                        if k != "solver_options"})
    del fp_settings["max_steps"]
    fp = _checkpoint.fingerprint(
        scene=repr(scene), settings=fp_settings,
        solver_options={k: v for k, v in settings["model"].get("solver_options", {}).items()
                        if k != "devices"},
        init=given, t=_checkpoint.digest(flat_t), w=_checkpoint.digest(flat_w))
    return _Setup(model, names, tgt, flat_t, m, data, u0, coords, inits, stepper, settings, fp,
                  target_files, mask_files, run)


def _traced_sun_form(model, unknowns, memo: dict | None):
    """What a fit's steps run: ``model``, or with the sun's angles among the unknowns its
    form for traced-sun programs (``SweepModel.traced_sun_form``), shaped like the last
    round's (``memo["form"]``, updated here) so that a round rebuilt at the estimated sun runs
    the steps compiled for the first instead of compiling them again."""
    paths = [u.path for u in unknowns if u.path in SUN_PATHS]
    if not paths or not hasattr(model, "traced_sun_form"):
        return model
    memo = {} if memo is None else memo
    form = model.traced_sun_form(paths, like=memo.get("form"))
    memo["form"] = form
    return form


def _weigh_edges(model, names, wts, edge_weight: float) -> dict[str, float] | None:
    """Multiply the weight of each pixel that straddles a geometric or a shadow edge (the
    model's ``edge_pixels``, from the exact geometry) by ``edge_weight``, in place; the share
    of each camera's pixels that do ({camera: fraction}), or None where the model does not know
    its edges (then nothing changes, and edge_weight < 1 says so in a warning)."""
    edges = model.edge_pixels()
    if edges is None:
        if edge_weight < 1.0:
            warnings.warn(f"edge_weight={edge_weight:g}: this forward model "
                          f"({type(model).__name__}) does not know which pixels straddle an "
                          f"edge; every pixel keeps its weight", UserWarning, stacklevel=4)
        return None
    for n in names:
        wts[n] = np.where(edges[n], edge_weight * wts[n], wts[n])
    if sum(float(w.sum()) for w in wts.values()) == 0:
        raise DifffogError("edge_weight=0 leaves no pixel with a weight: every weighted pixel "
                           "straddles an edge; use a larger edge_weight")
    return {n: round(float(edges[n].mean()), 4) for n in names}


class _Tracker:
    """One fit's per-step bookkeeping, the same for :func:`fit` and :func:`fit_batch`:
    the history, the optimizer's result, the stall test and the light-solve check."""

    def __init__(self, setup: _Setup, history: list | None = None, k: int = 0):
        self.setup = setup
        self.history = list(history or [])
        self.k = k
        self.done = False
        self.stalled = False
        self.code = optx.RESULTS.successful
        self.tangent_failures = 0  # steps whose Jacobian had an unconverged tangent solve

    def record(self, u, state, done, code, *, now: float, stall_steps: int, rtol: float):
        """After a step: append its history entry and decide whether the fit is over."""
        self.k += 1
        aux = getattr(state, "aux", None)
        loss, light = (aux[:2] if isinstance(aux, tuple) else (np.nan, RESULTS.successful))
        self.tangent_failures += int(light) == RESULTS.tangent_unconverged
        entry = {"step": self.k, "values": self.setup.values(u), "loss": float(loss),
                 "accepted_steps": (int(state.num_accepted_steps)
                                    if hasattr(state, "num_accepted_steps") else None),
                 "light_result": RESULTS(int(light)).name,
                 "time_s": now}
        self.history.append(entry)
        self.code = code
        if bool(done):
            self.done = True
        elif not np.all(np.isfinite(np.asarray(u))) or not math.isfinite(entry["loss"]):
            self.code, self.done = optx.RESULTS.nonfinite, True
        elif _stalled(self.history, stall_steps, rtol):
            self.stalled = self.done = True
        return entry


def _stalled(history: list[dict], stall_steps: int, rtol: float) -> bool:
    """The loss fell by less than rtol over ``stall_steps`` steps once the fit had made progress:
    the optimum to the precision of the forward model (its light solve stops at its
    tolerance), where LM keeps shrinking its trust region, rejecting step after step, without
    meeting the step-size criterion.  Rejected steps count (a fit of ζ and γ spent 12 of its 16
    steps rejecting steps that never moved the unknowns); progress means the unknowns moved,
    over the window or before it — not the first rejections of a too-long step from the start
    (LM's trust region, BFGS's line search)."""
    if not stall_steps or len(history) <= stall_steps:
        return False
    old, new = history[-1 - stall_steps], history[-1]
    if old["loss"] - new["loss"] > rtol * max(new["loss"], 1e-30):
        return False
    return old["values"] != new["values"] or old["values"] != history[0]["values"]


def _bound_runners(history: list[dict], coords, window: int = 10) -> list[tuple]:
    """(coordinate, value window steps ago, last value) of the unknowns in log coordinates
    that ran towards their lower bound (see :func:`_towards_bound`)."""
    if len(history) <= window:
        return []
    out = []
    for c in coords:
        if c.mode != "log" or not math.isfinite(c.lower):
            continue
        vals = [float(e["values"][c.path]) - c.lower for e in history[-1 - window:]]
        start = float(history[0]["values"][c.path]) - c.lower
        falling = all(b <= a for a, b in zip(vals, vals[1:]))
        # still falling fast (30% over the window), and far below where it started
        if falling and 0 < vals[-1] < min(0.7 * vals[0], 0.1 * start):
            out.append((c, vals[0] + c.lower, vals[-1] + c.lower))
    return out


def _towards_bound(history: list[dict], coords, window: int = 10) -> list[str]:
    """What to say of unknowns in log coordinates (a lower bound, no upper one) that ran
    towards their bound over the last ``window`` steps without getting there (still falling by
    30% over the window, at under a tenth of where they started): the optimum at
    the bound is at u → −∞, which LM approaches a step at a time (fog-balls' γ from images of
    γ = 0: 0.0104 → 0.0016 over 40 steps, each step a few per cent nearer).  One line each: the
    way, and what to do (hold it at the bound: another lower bound would be the new optimum's,
    as far away in these coordinates)."""
    out = []
    for c, before, last in _bound_runners(history, coords, window):
        at = f"{c.lower:g}"
        out.append(f"{c.path} fell from {before:.4g} to {last:.4g} over the last {window} "
                   f"steps towards its bound {at}: the images may need none of it; hold it at "
                   f"{at} (--set {c.path}={at} without --unknown {c.path}; in log coordinates "
                   f"the bound itself is never reached)")
    return out


def _held_at_bound(res: FitResult) -> dict[str, float]:
    """{path: bound} of the unknowns a fit that ran out of steps was running to the lower
    bound of, where holding them there is possible: a parameter of the model (not an
    exposure), and at least one unknown left to fit."""
    lin = getattr(res, "_linear", None)
    if res.result != "nonlinear_max_steps_reached" or lin is None:
        return {}
    model, held = lin["setup"].model, {}
    for c, _, _ in _bound_runners(res.history, lin["setup"].coords):
        try:
            set_param(model.params(), model.scene, c.path, c.lower)
        except DifffogError:  # not a parameter of the model (an exposure)
            continue
        held[c.path] = float(c.lower)
    return held if len(held) < len(res.paths) else {}


def _refit_at_bound(first: FitResult, held: dict[str, float], scene: Scene, targets, unknowns,
                    *, resolution, callback, **kw):
    """The fit again (the same model) with the ``held`` unknowns at their bounds and the
    others started where ``first`` left them: (its result, scene, forward), or None where it
    did not converge."""
    rest = [dataclasses.replace(u, init=within_bounds(u, first.estimates[u.path]))
            for u in as_unknowns(unknowns) if u.path not in held]
    out = _fit_sun_rounds(scene, targets, rest, resolution=resolution, callback=callback,
                          fixed=held, **kw)
    # the bound is the optimum only if the images fit there at least as well as where the
    # first fit stopped, on its way there
    return out if out[0].converged and out[0].loss <= first.loss * (1 + 1e-3) else None


def _finish(tr: _Tracker, u, state, *, time_s: float, rtol: float, atol: float,
            max_steps: int, stall_steps: int, extra_warnings=()) -> FitResult:
    st = tr.setup
    name = result_name(tr.code)
    message = "" if name == "successful" else str(optx.RESULTS[tr.code])
    if tr.stalled and name == "successful":
        name = "loss_stalled"
        message = (f"stopped: the loss fell by less than rtol = {rtol} (relative) over the last "
                   f"{stall_steps} steps — the optimum to the forward model's precision")
    if not tr.done and tr.k >= max_steps:
        name = "nonlinear_max_steps_reached"
        bound = _towards_bound(tr.history, st.coords)
        message = (f"stopped after max_steps = {max_steps} steps without meeting rtol = {rtol}, "
                   f"atol = {atol}; " + ("; ".join(bound) if bound else
                                         "raise max_steps or start closer"))
    if tr.tangent_failures:
        extra_warnings = [*extra_warnings, f"{RESULTS.tangent_unconverged.message} (the "
                          f"Jacobian of {tr.tangent_failures} of the {tr.k} steps)"]
    r, J, y, light, light_state = st.stepper.final(u, state, st.args)
    r, J, y, light = (np.asarray(a) for a in (r, J, y, light))
    r, J, y = (a.astype(np.float64) for a in (r, J, y))
    tangent_failed = int(light) == RESULTS.tangent_unconverged  # J's failed columns are 0
    if tangent_failed:
        name = "light_solve_failed"
        message = f"at the estimate, {RESULTS.tangent_unconverged.message}"
    elif int(light) != RESULTS.successful:
        failed = RESULTS(int(light))
        name = "light_solve_failed"
        message = (f"the light solve at the estimate did not converge ({failed.name}): "
                   f"{failed.message}; the estimate and its errors are not reliable")
    mask = np.asarray(st.data[1]) > 0
    se, corr, cond, msgs, _ = statistics(r[mask], J[mask], st.m, st.coords, np.asarray(u))
    if tangent_failed:
        msgs = []  # the zeroed J's identifiability says nothing
    for msg in msgs:
        warnings.warn(msg, IdentifiabilityWarning, stacklevel=3)
    msgs = list(msgs) + [str(w) for w in extra_warnings]
    p_est = _params_at(st, u)
    for check, category in (("step_warning", ThickStepWarning),
                            ("layer_warning", ThinLayerWarning)):
        said = None if p_est is None else getattr(st.model, check)(p_est)
        if said:
            warnings.warn(f"at the estimate, {said}", category, stacklevel=3)
            msgs.append(f"at the estimate, {said}")
    raw = (y - st.flat_t) * np.sqrt(np.asarray(st.data[1], np.float64) ** 2)
    images, off = {}, 0
    for n in st.names:
        size = st.tgt[n].size
        images[n] = y[off:off + size].reshape(st.tgt[n].shape).astype(np.float32)
        off += size
    res = FitResult(
        paths=[c.path for c in st.coords],
        estimates=st.values(u),
        stderr={c.path: float(s) for c, s in zip(st.coords, se)},
        uncertainty={c.path: float(s) for c, s in zip(st.coords, se)},  # a ladder adds to it
        correlation=corr,
        initial={c.path: v for c, v in zip(st.coords, st.inits)},
        residual_rms=float(np.sqrt(np.sum(raw ** 2) / st.m)),
        loss=float(0.5 * np.sum(r * r)),
        iterations=tr.k,
        time_s=time_s,
        result=name,
        message=message,
        warnings=msgs,
        history=tr.history,
        images=images,
        targets={n: st.tgt[n].astype(np.float32) for n in st.names},
        condition=cond,
        settings=st.settings,
        target_files=st.target_files,
        mask_files=st.mask_files,
    )
    # what a model-error estimate needs: the optimum and its linearization, and the residual
    # √w·(y − target)/scale without a robust loss's factor (the misfit's, a held unknown's);
    # not serialized
    residual = (np.asarray(st.data[1], np.float64) * (y - np.asarray(st.flat_t, np.float64))
                / float(st.data[2]))
    res._linear = dict(setup=st, u=np.asarray(u), J=J, y=y, light=light_state,
                       residual=residual)
    return res


def _params_at(st: _Setup, u):
    """The model's parameters at the estimate ``u`` (for its step and layer warnings), or None
    where an unknown is not one the parameters hold (e.g. a density grid)."""
    from ..scene._params import set_param

    p = st.model.params()
    try:
        for path, v in st.values(u).items():
            if exposure_camera(path) is None:
                p = set_param(p, st.model.scene, path, v)
    except DifffogError:
        return None
    return p


def _postfix(entry: dict) -> dict:
    out = {"loss": entry["loss"]}
    out.update({p.removeprefix("camera.") if exposure_camera(p) else p.split(".")[-1]: v
                for p, v in entry["values"].items()})
    return out


def fit(scene: Scene, targets: Mapping[str, Any], unknowns, *, forward="sweep",
        resolution: int | None = None, downsample: int = 1,
        model_settings: Mapping | None = None, optimizer="lm",
        weights: Mapping[str, Any] | None = None, loss: str = "linear",
        loss_scale: float = 0.05, rtol: float = 1e-4, atol: float = 1e-4, max_steps: int = 50,
        stall_steps: int = 3, dtype=None, channel: str = "luminance", transfer: str = "auto",
        checkpoint: str | os.PathLike | None = None, resume: bool = False, progress=None,
        callback: Callable[[dict], None] | None = None,
        ladder=None, model_error=None, model_floor="auto", refine_steps: int = 4,
        edge_weight: float = 1.0) -> FitResult:
    """Fit the unknowns of ``scene`` to target images.

    targets: {camera name: (H, W) image or image file}, one or several views, at the scene
        camera's resolution or already reduced by ``downsample``.  A file (a path: .npy, .png,
        .tif, .exr, .jpg) is read as linear radiance by ``difffog.fit._images.load_target``
        with ``channel`` and ``transfer``; the result's ``target_files`` records how.
    unknowns: dotted parameter paths (``fog.scattering``, ``fog.absorption``,
        ``shape.<name>.albedo``; ``fog.g``, ``sun.irradiance``, ``sky.radiance`` as nuisance
        parameters; ``exposure`` or ``camera.<name>.exposure``, a gain on every image or on one
        camera's, for photographs of unknown scale; ``sun.zenith_deg``, ``sun.azimuth_deg``,
        the sun's direction, for photographs whose sun is not known exactly: the sweep only,
        in rounds that rebuild the model at the estimated sun, ``FitResult.sun_rounds``): a
        list, a dict {path: init | (init, lower, upper) | None} or :class:`Unknown` objects.
        An exposure without an initial value starts at the gain that best fits the first
        render to the targets.
    forward: a solver name ("sweep", default, or "splat": built from the registry at its fit
        defaults, e.g. the sweep at N = 32, M = 3, light tol 1e-5) or a forward model
        (``difffog.forward_model(...)``, used as it is: its cameras must match the targets).
    resolution: the forward model's lattice resolution (default: the solver's fit default).
    downsample: render every camera at 1/k of its width and height (the target is box-averaged
        to match: a reduced pixel's footprint is k×k full pixels).
    model_settings: other settings of the named solver, e.g. ``{"M": 4, "devices": 2}``;
        ``{"force": True}`` builds the model even where its estimated memory exceeds what the
        machine has (a :class:`difffog.ResourceError` otherwise).
    optimizer: "lm" (Levenberg–Marquardt, default), "gauss-newton", "bfgs" or an optimistix
        least-squares solver / minimiser.
    weights: {camera: (H, W)} per-pixel weights ≥ 0 (a boolean mask works), or a mask file
        (a .npy of weights; an image: used where its alpha, else any channel, is nonzero); the
        residual is √w·(model − target) / RMS(target).
    edge_weight: the weight of a pixel whose footprint straddles a geometric or a shadow edge
        (a silhouette, a wall's rim, a shadow's edge; ``model.edge_pixels()``, from the exact
        geometry, not from the residuals) relative to the others, multiplying ``weights``: 1
        (default) counts them as any pixel, 0 leaves them out.  The model reproduces such a
        pixel less well (its value depends on how much of the footprint each side covers).
    loss: "linear" (least squares) or a robust "huber", "soft_l1", "cauchy" with threshold
        ``loss_scale`` in units of the target's RMS.
    rtol, atol: optimistix' termination on the unconstrained unknowns and the residuals; the
        fit also stops ("loss_stalled", converged) when, after progress, the loss fell by less
        than rtol over ``stall_steps`` steps, rejected steps included (0: never).
    dtype: of the parameters (default float32, or float64 with x64 on).
    channel: how colour target files become one channel: "luminance" (Y = 0.2126 R + 0.7152 G
        + 0.0722 B of the linear values) or "r", "g", "b".
    transfer: of target files: "auto" (sRGB for 8-bit files, linear for 16-bit and float
        ones), "srgb" (sRGB-encoded: undone) or "linear".
    checkpoint: a file written (atomically) after every step; ``resume=True`` continues from
        it and reaches the same answer as an uninterrupted fit.
    progress: True, a progress meter (``difffog.TqdmProgress("fit")``) or None/False.
    ladder: an estimate of the model's own error (experimental, off by default).  "auto" (for
        a named solver): fit first on a coarser lattice (3/4 of ``resolution``, and not so
        coarse that a shape is thinner than a voxel), then at ``resolution`` from that
        estimate; the change of each estimate between the two, extrapolated to first order in
        the voxel size (Richardson: × N_c/(N − N_c), 3 for 24 → 32), is its ``model_error``,
        and ``uncertainty`` is √(stderr² + model_error²).  A tuple (coarse, fine) chooses the
        resolutions.  None (default): one fit, ``uncertainty`` = ``stderr``.  Measured limit
        (docs/fitting.md): on small lattices the estimates jump between neighbouring
        resolutions, and two levels can miss most of the error.
    model_error: the forward model's own error in each estimate, added to the standard error
        in ``uncertainty``: "refine" (for a named solver) renders the fitted model once more at
        the estimate on a lattice twice as fine (or at the resolution given as an int) and,
        for the sweep, with one more direction (M + 1), takes the Gauss–Newton step that image
        change would cause, J⁺·Δy: to first order the estimate a fit with the finer model
        would reach; then further such steps from where the last one landed (defect
        correction: the finer model's images there, the fit's Jacobian), up to
        ``refine_steps`` renders in all, until a step moves every estimate by less than a
        tenth of its stated uncertainty.  That corrected estimate is returned in ``estimates``
        (the fit at ``resolution`` itself in ``fitted``, with its images).  Its
        ``model_error`` is the root sum of squares of three parts (``model_error_parts``): the
        correction × N/(N_f − N), first order in the voxel size (1 for a doubled lattice); how
        far a lattice between lands from the first step's first-order line; and the change
        with M + 1 on the fit's own lattice (a fourth, "refine_steps", the last step, where
        the steps did not become small).  Three light solves and their images after the fit,
        and one more per further step.  None (default): no correction, no estimate.
    refine_steps: the most renders of the finer model the correction of ``model_error``
        takes (default 4; 1: the one Gauss–Newton step).  Measured on cloud-plane (ζ = 60,
        fit at N = 24, γ's correction −17%): one step leaves γ +1.5% off the finer fit, two
        0.3%, three 0.1%.
    model_floor: with ``model_error="refine"``, a fourth part of the model error
        ("brightness"): how far each estimate moves (one Gauss–Newton step, as above) if one
        camera's images were this much (relative) too bright, root sum of squares over the
        cameras.  It stands for what a finer lattice does not reveal: the forward model's
        brightness against independent truth.  "auto" (default): the named solver's validated
        figure (the sweep 0.005: a fine render's image means within 0.5–0.6% of the Mitsuba
        references; the splat 0.25), 0 for a forward model of another kind.  A float sets it;
        0 leaves it out.  An unknown exposure absorbs it (a gain is such a bias).
    callback: called after every step with that step's history entry (of the last level).

    An unknown whose best value is its lower bound (γ of a fog that does not absorb: in log
    coordinates it only creeps towards it until ``max_steps``) is then held at the bound and the
    others are fit again from where they were, on the same model: its estimate is the bound,
    ``at_bound`` says how far above it the images allow it (95%, one-sided), and the message
    says so (``fit/_bound.py``).

    The result is "light_solve_failed" (not converged) when the light solve at the estimate
    did not converge, or a tangent solve of the estimate's Jacobian; an unconverged tangent
    solve of a step's Jacobian is listed in its warnings.
    See :func:`fit_batch` for many target sets at once.
    """
    if isinstance(refine_steps, bool) or not isinstance(refine_steps, (int, np.integer)) \
            or refine_steps < 1:
        raise DifffogError(f"refine_steps={refine_steps!r}: give the most renders of the finer "
                           f"model the correction takes, an integer ≥ 1 (default 4; 1: one "
                           f"Gauss–Newton step)")
    model_settings = _phase_order_for_g(scene, forward, unknowns, model_settings)
    levels = _ladder_levels(scene, forward, resolution, model_settings, ladder)
    fine_n = _refine_resolution(scene, forward, resolution, model_settings, model_error, levels)
    floor = _brightness_floor(forward, model_floor)
    kw = dict(forward=forward, downsample=downsample, model_settings=model_settings,
              optimizer=optimizer, weights=weights, loss=loss, loss_scale=loss_scale, rtol=rtol,
              atol=atol, max_steps=max_steps, stall_steps=stall_steps, dtype=dtype,
              channel=channel, transfer=transfer, progress=progress, edge_weight=edge_weight)
    if len(levels) < 2:
        res, scene, forward = _fit_sun_rounds(scene, targets, unknowns, resolution=resolution,
                                              checkpoint=checkpoint, resume=resume,
                                              callback=callback, **kw)
        first, held = res, _held_at_bound(res)
        refit = held and _refit_at_bound(first, held, scene, targets, unknowns,
                                         resolution=resolution, callback=callback, **kw)
        if held and not refit:
            res.warnings.append(f"holding {', '.join(held)} at the bound and fitting the "
                                f"others again did not converge, or fit the images worse")
        elif held:
            res, scene, forward = refit
        if fine_n is not None:
            t0 = time.perf_counter()
            _with_refined_error(res, scene, forward, fine_n, downsample, model_settings,
                                progress, floor, refine_steps)
            res.time_s += time.perf_counter() - t0
        if refit:
            _bound.with_held(res, first, list(held), held)
        return res
    if checkpoint is not None or resume:
        raise DifffogError("checkpoint/resume is not supported with a ladder yet (the coarse "
                           "level would be refitted); use ladder=None (--ladder none)")
    if _has_sun(unknowns):
        raise DifffogError("the sun's angles as unknowns are not supported with a ladder; use "
                           "model_error=\"refine\" (the measured honest one) or no ladder")
    t0 = time.perf_counter()
    unk = as_unknowns(unknowns)
    coarse = _fit_level(scene, targets, unk, resolution=levels[0], **kw)
    start = unk
    if coarse.converged:  # the fine fit starts from the coarse estimate (inside its bounds)
        start = [dataclasses.replace(u, init=within_bounds(u, coarse.estimates[u.path])) for u in unk]
    fine = _fit_level(scene, targets, start, resolution=levels[1], callback=callback, **kw)
    out = _with_model_error(fine, coarse, levels)  # (its ladder keeps each level's own time)
    out.time_s = time.perf_counter() - t0
    return out


#: a fit with the sun's angles as unknowns rebuilds its model at the estimated sun (the host's
#: shadows and paths are linearized about the model's own sun) until the sun moves less than
#: this (degrees; or than its standard error, where that is larger) in a round, at most
#: ``SUN_ROUNDS`` rounds
SUN_SETTLE_DEG = 0.05
SUN_ROUNDS = 6
#: the linearization's step in the first round (degrees): its central differences span
#: ±4°, so that a shadow can move that far within the round; later rounds take half the last
#: round's move, within [SUN_STEP_MIN, SUN_FIRST_STEP]
SUN_FIRST_STEP = 4.0
SUN_STEP_MIN = 0.5


def _finite_or(v, default: float) -> float:
    return float(v) if v is not None and math.isfinite(v) else default


def _fit_sun_rounds(scene: Scene, targets, unknowns, *, checkpoint=None, resume=False,
                    callback=None, **kw) -> tuple[FitResult, Scene, Any]:
    """:func:`_fit_level`, and with the sun's angles among the unknowns, again on a model
    rebuilt at the estimated sun until it settles (``SUN_SETTLE_DEG``): (the last round's
    result with every round's record, the scene with the sun it was built at, ``forward``
    (a solver name, or the model given rebuilt at that sun))."""
    unk = as_unknowns(unknowns)
    sun_paths = [u.path for u in unk if u.path in SUN_PATHS]
    if not sun_paths or scene.sun is None:  # (no sun: the unknown's own one-line error)
        res = _fit_level(scene, targets, unk, checkpoint=checkpoint, resume=resume,
                         callback=callback, **kw)
        return res, scene, kw["forward"]
    if resume:
        raise DifffogError("resume: not supported with the sun's angles as unknowns yet (each "
                           "round of the fit rebuilds the model at the estimated sun); run "
                           "without resume")
    t0 = time.perf_counter()
    rounds, history, first, last_move = [], [], None, None
    step = SUN_FIRST_STEP
    memo = {}  # the last round's traced-sun form: the next round runs its compiled steps
    for r in range(SUN_ROUNDS):
        res = _fit_level(scene, targets, unk, checkpoint=checkpoint, callback=callback,
                         sun_step=step, sun_memo=memo, **kw)
        first = first or res
        at = {p: float(getattr(scene.sun, attr)) for p, (_, attr) in SUN_PATHS.items()}
        moved = max(abs(res.estimates[p] - at[p]) for p in sun_paths)
        # settled: it moved less than SUN_SETTLE_DEG, or than the noise's standard error (the
        # host's shadows change in steps of their rays, so the estimate jitters with the sun
        # the model is built at)
        settle = {p: max(SUN_SETTLE_DEG, _finite_or(res.stderr.get(p), 0.0)) for p in sun_paths}
        rounds.append({"sun": at, "step_deg": step, "estimates": dict(res.estimates),
                       "iterations": res.iterations, "result": res.result,
                       "time_s": round(res.time_s, 3)})
        step = min(max(0.5 * moved, SUN_STEP_MIN), SUN_FIRST_STEP)
        history += [{**h, "round": r + 1} for h in res.history]
        if not res.converged or all(abs(res.estimates[p] - at[p]) <= settle[p]
                                    for p in sun_paths):
            break
        move = {k: res.estimates.get(k, at[k]) - at[k] for k in SUN_PATHS}
        if last_move is not None and sum(move[k] * last_move[k] for k in SUN_PATHS) < 0:
            # it turned back: the estimate jitters with the sun the model is built at (its
            # shadows change in steps of their rays); halve the move, or it can swing between
            # two suns for good
            move = {k: 0.5 * v for k, v in move.items()}
        last_move = move
        new = {attr: at[k] + move[k] for k, (_, attr) in SUN_PATHS.items()}
        scene = scene.replace(sun=dataclasses.replace(scene.sun, **new))
        unk = [dataclasses.replace(u, init=within_bounds(u, res.estimates[u.path])) for u in unk]
        if isinstance(kw.get("forward"), AbstractForwardModel):
            kw["forward"] = kw["forward"].at_sun(new["zenith_deg"], new["azimuth_deg"], step)
    else:
        res.warnings.append(f"the sun's estimate still moved {moved:.2g}° in the last of "
                            f"{SUN_ROUNDS} rounds (each rebuilds the model at the estimated "
                            f"sun); it may be off by about that much")
    res.initial = first.initial
    res.iterations = sum(rd["iterations"] for rd in rounds)
    res.history = history
    res.sun_rounds = rounds
    res.time_s = time.perf_counter() - t0
    return res, scene, kw["forward"]


def _phase_order_for_g(scene: Scene, forward, unknowns, model_settings):
    """``model_settings`` with the anisotropic phase order, for a named solver that takes one
    (the registry's settings), when ``fog.g`` is an unknown of a scene whose fog starts
    isotropic (``Scene.anisotropic`` false: phase "isotropic", or g = 0): "auto" would take
    order 0 there, the δ-isotropic scaling in which g only rescales ζ, and the fit would fit
    that (fog-balls from images of another absorption: g = −0.92 ± 0.001, "successful")."""
    from ..forward.sweep._solver import DEFAULT_PHASE_ORDER

    settings = dict(model_settings or {})
    if (not isinstance(forward, str) or "phase_order" in settings or scene.anisotropic
            or "phase_order" not in solver_entry(forward).settings
            or not any(u.path == "fog.g" for u in as_unknowns(unknowns))):
        return model_settings
    return {**settings, "phase_order": DEFAULT_PHASE_ORDER}


def _refine_resolution(scene: Scene, forward, resolution, model_settings, model_error,
                       levels) -> int | None:
    """The finer resolution of ``model_error`` ("refine": twice the fit's; an int: that one)."""
    if model_error is None:
        return None
    if levels:
        raise DifffogError("give one of ladder and model_error (both estimate the model's "
                           "error); model_error=\"refine\" is the one measured honest")
    if isinstance(forward, str):
        n = int(resolution or {**solver_entry(forward).fit_defaults,
                               **(model_settings or {})}.get("resolution", 32))
    elif hasattr(forward, "at_resolution"):
        n = int(forward.resolution)
    else:
        raise DifffogError(f"model_error needs a named solver or a model that can be rebuilt "
                           f"at another resolution ({type(forward).__name__} cannot); use "
                           f"model_error=None")
    if model_error == "refine":
        return 2 * n
    if isinstance(model_error, bool) or not isinstance(model_error, (int, np.integer)) \
            or model_error <= n:
        raise DifffogError(f"model_error={model_error!r}: use \"refine\", None or a resolution "
                           f"finer than the fit's ({n})")
    return int(model_error)


def _refined_models(scene: Scene, forward, st, fine_n: int, downsample: int,
                    model_settings) -> list[tuple[dict, Callable]]:
    """The finer models the model error renders, as (what, a function that builds it): the
    correction's, on the lattice ``fine_n`` with one more direction (M + 1) where the model has
    a direction set; a lattice between the fit's and ``fine_n`` (the lattice error's erratic
    part); and M + 1 on the fit's own lattice (the direction set's part)."""
    n = int(st.model.resolution)
    mid = int(round(0.5 * (n + fine_n)))
    if isinstance(forward, str):
        settings = dict(model_settings or {})
        entry = solver_entry(forward)
        m = (int({**entry.fit_defaults, **settings}.get("M", 3)) + 1
             if "M" in entry.settings else None)

        def build(resolution, M=None):
            extra = {} if M is None else {"M": M}
            # (it only renders, at the estimate: no Jacobian, no tangent solves)
            return make_model(scene, forward, cameras=st.names, downsample=downsample,
                              resolution=resolution, model_settings={**settings, **extra},
                              unknowns=0,
                              sun=_has_sun([c.path for c in st.coords]))
    else:
        solver = getattr(forward, "solver", None)
        m = (int(solver.M) + 1 if solver is not None and hasattr(solver, "M")
             and hasattr(forward, "with_solver") else None)

        def build(resolution, M=None):
            if M is None:
                return forward.at_resolution(resolution)
            return forward.with_solver(dataclasses.replace(solver, M=M), resolution=resolution)

    def check(resolution, M=None):
        return ({"resolution": resolution} if M is None else {"resolution": resolution, "M": M},
                functools.partial(build, resolution, M))

    return ([check(fine_n, m)] + ([check(mid)] if n < mid < fine_n else [])
            + ([check(n, m)] if m is not None else []))


def _unknown_model_error(res: FitResult) -> FitResult:
    """A fit whose model error could not be estimated: the model error and the total
    uncertainty are NaN (unknown; fit.json writes null), not the noise's standard error alone,
    which would understate it (the warnings say why)."""
    res.model_error = {p: float("nan") for p in res.paths}
    res.uncertainty = {p: float("nan") for p in res.paths}
    return res


def _brightness_floor(forward, model_floor) -> float:
    """``fit``'s ``model_floor`` as a number (``"auto"``: the solver's validated figure)."""
    if isinstance(model_floor, str) and model_floor == "auto":
        if isinstance(forward, str):
            return float(solver_entry(forward).brightness_floor)
        from ..forward.splat._model import SplatModel
        from ..forward.sweep._model import SweepModel

        for cls, name in ((SweepModel, "sweep"), (SplatModel, "splat")):
            if isinstance(forward, cls):
                return float(solver_entry(name).brightness_floor)
        return 0.0
    if isinstance(model_floor, bool) or not isinstance(model_floor, (int, float, np.floating)) \
            or not math.isfinite(model_floor) or not 0.0 <= model_floor < 1.0:
        raise DifffogError(f"model_floor={model_floor!r}: use \"auto\" or a relative "
                           f"brightness in [0, 1), e.g. 0.005 (0 leaves it out)")
    return float(model_floor)


def _gauss_newton_step(J, dy) -> np.ndarray:
    """The Gauss–Newton step, in the unknowns' unconstrained coordinates, that an image change
    ``dy`` (in the residual's units) causes: −J⁺·dy."""
    return -np.linalg.lstsq(J, dy, rcond=None)[0]


def _physical(st, x) -> dict[str, float]:
    """The estimates at the unconstrained unknowns ``x``."""
    return {c.path: float(c.to_v(float(v))) for c, v in zip(st.coords, x)}


def _moved_estimates(st, u, J, dy) -> dict[str, float]:
    """The estimates after the Gauss–Newton step an image change ``dy`` (in the residual's
    units) causes, taken in the unconstrained coordinates, so a moved albedo stays inside its
    bounds."""
    return _physical(st, np.asarray(u, np.float64) + _gauss_newton_step(J, dy))


def _floor_shifts(st, u, J, y, weight, fitted, floor) -> dict[str, float]:
    """Each estimate's shift (physical units) under a relative brightness bias ``floor`` (one
    for every camera, or {camera: bias}) of one camera's images at a time, root sum of squares
    over the cameras; ``weight`` turns an image change into the residual's units."""
    total = dict.fromkeys(fitted, 0.0)
    off = 0
    for name in st.names:
        size = st.tgt[name].size
        bias = floor.get(name, 0.0) if isinstance(floor, Mapping) else floor
        dy = np.zeros_like(y)
        dy[off:off + size] = bias * y[off:off + size]
        off += size
        if bias == 0:
            continue
        for p, v in _moved_estimates(st, u, J, weight * dy).items():
            total[p] += (v - fitted[p]) ** 2
    return {p: math.sqrt(t) for p, t in total.items()}


def _with_refined_error(res: FitResult, scene: Scene, forward, fine_n: int,
                        downsample: int, model_settings, progress=None,
                        floor: float = 0.0, refine_steps: int = 1) -> FitResult:
    """``res`` corrected to the lattice ``fine_n``, with its model error and total uncertainty
    (see ``fit``'s ``model_error``)."""
    lin = getattr(res, "_linear", None)
    if lin is None or not res.converged:
        res.warnings.append("the model error is not estimated: the fit did not converge")
        return _unknown_model_error(res)
    st, u, J, y = lin["setup"], lin["u"], lin["J"], lin["y"]
    n = int(st.model.resolution)
    sqrt_w, scale = np.asarray(st.data[1], np.float64), float(st.data[2])
    fitted = dict(res.estimates)
    moved = []  # (what, {path: the estimate the finer model would reach, to first order})
    corrected = None  # (estimates, steps, {path: the last step left}, a note) when iterated
    # the brightness floor's part (from J alone) and the noise: known before any render, they
    # are part of the uncertainty the iterated correction is held to
    shifts = (_floor_shifts(st, u, J, y, sqrt_w / scale, fitted, floor) if floor > 0 else {})
    known = {p: math.hypot(_finite_or(res.stderr.get(p), 0.0), shifts.get(p, 0.0))
             for p in res.paths}
    checks = _refined_models(scene, forward, st, fine_n, downsample, model_settings)
    # the light states at u so far, (model, state): each render starts from one, resampled
    sources = [] if lin.get("light") is None else [(st.model, lin["light"])]
    meter = sibling(progress, "model error")
    for i, (what, build) in enumerate(checks):
        label = level_label(what)
        meter.update(i, len(checks), **{"N" if k == "resolution" else k: v
                                        for k, v in what.items()})  # rendering this check
        try:
            model = build()
        except ResourceError as e:  # a finer model this machine cannot hold
            model, name = None, f"{e}"
            smaller = round(1.5 * n)
            if not moved and n < smaller < fine_n:  # a less fine lattice that may fit
                meter.close()
                res.warnings.append(f"the model error is estimated at N = {smaller}, not "
                                    f"{fine_n}: {name}")
                return _with_refined_error(res, scene, forward, smaller, downsample,
                                           model_settings, progress, floor, refine_steps)
        if model is not None:
            y_f, name, light = _finer_images(st, model, u, _start(model, sources))
            if light is not None:
                sources.append((model, light))
            if i == 0 and y_f is not None:  # the finer model's change at u, in the residual's
                # units: the goodness of fit's lattice error and a held unknown's (_bound)
                res._fine_change = sqrt_w * (y_f - y) / scale
        if name is not None:
            if not moved:  # the correction itself
                res.warnings.append(f"the estimate is not corrected and the model error not "
                                    f"estimated: at {label}, {name}")
                meter.close()
                return _unknown_model_error(res)
            res.warnings.append(f"the model error leaves out its check at {label}: {name}; "
                                f"the uncertainty may be too small")
            continue
        # the Gauss–Newton step that model's images take the estimate
        u_moved = np.asarray(u, np.float64) + _gauss_newton_step(J, sqrt_w * (y_f - y) / scale)
        moved.append((what, _physical(st, u_moved)))
        if i == 0 and refine_steps > 1:  # iterate the correction with that model
            corrected = _iterated_correction(
                st, model, u, u_moved, J, y, sqrt_w / scale, known, n / (fine_n - n),
                refine_steps, label, light,
                lambda k, w=what: meter.update(0, len(checks), **{
                    "N" if a == "resolution" else a: b for a, b in w.items()}, step=k))
    meter.update(len(checks), len(checks))
    meter.close()
    first = moved[0][1]  # the first Gauss–Newton step's estimate
    if corrected is None:
        refined, steps, left = first, 1, {}
    else:
        refined, steps, left, note = corrected
        if note:
            res.warnings.append(note)
    # θ(h) = θ* + c·h: the corrected estimate stands for θ(h_f), whose own error is
    # θ(h_f) − θ* = (θ(h) − θ(h_f))·h_f/(h − h_f) = shift·N/(N_f − N) (1 for a doubled lattice).
    # Where the lattice between lands off that line the error is not first order (it follows
    # where the nodes fall against the shapes): the distance counts too.  The direction set's
    # own error: the change with M + 1 on the fit's lattice.
    factor = n / (fine_n - n)
    parts = {p: {"lattice": factor * abs(refined[p] - fitted[p])} for p in res.paths}
    for p, v in left.items():  # an iterated correction stopped before its steps were small
        parts[p]["refine_steps"] = v
    for what, est in moved[1:]:
        if "M" in what:  # M + 1 on the fit's own lattice
            for p in res.paths:
                parts[p]["directions"] = abs(est[p] - fitted[p])
            continue
        # (the checks are single steps: the line they are held to is the first step's)
        t = (1 / what["resolution"] - 1 / n) / (1 / fine_n - 1 / n)  # its place on the line
        for p in res.paths:
            parts[p]["lattice_between"] = abs(est[p] - (fitted[p] + t * (first[p] - fitted[p])))
    if floor > 0:  # the brightness the validation vouches for, not the lattice
        for p, v in shifts.items():
            parts[p]["brightness"] = v
        res.model_floor = floor
    _with_misfit(res, st, u, J, y, sqrt_w, scale, fitted, parts, fine_n / (fine_n - n), floor)
    if len(res.sun_rounds) >= 2:  # how far the last rebuild at the estimated sun moved each
        before, last = res.sun_rounds[-2]["estimates"], res.sun_rounds[-1]["estimates"]
        for p in res.paths:
            parts[p]["sun_rounds"] = abs(last[p] - before[p])
    res.fitted = fitted
    res.estimates = refined
    res.model_error = {p: float(math.sqrt(sum(v * v for v in parts[p].values())))
                       for p in res.paths}
    res.model_error_parts = {p: {k: float(v) for k, v in parts[p].items()} for p in res.paths}
    res.uncertainty = {p: math.hypot(res.stderr[p], res.model_error[p]) for p in res.paths}
    res.ladder = [{"resolution": n, "estimates": fitted},
                  {**moved[0][0], "estimates": refined, "linearized": True, "steps": steps}] + [
        {**what, "estimates": est, "linearized": True} for what, est in moved[1:]]
    return res


def _with_misfit(res: FitResult, st, u, J, y, sqrt_w, scale: float, fitted, parts,
                 lattice_factor: float, floor: float) -> None:
    """The goodness of fit (``res.goodness_of_fit``), the misfit's part of each estimate's
    model error (``parts[p]["misfit"]``, where some camera's residual is more than the noise,
    the lattice and the floor explain) and a :class:`MisfitWarning` where it is more than
    ``_misfit.MISFIT_RATIO`` times that (``fit/_misfit.py``)."""
    change = getattr(res, "_fine_change", None)
    if change is None:  # (no render of the finer model at the estimate: nothing to hold it to)
        return
    target = np.asarray(st.flat_t, np.float64)
    cams = _misfit.per_camera(st, y, target, sqrt_w, change, lattice_factor, floor, J, scale)
    res.goodness_of_fit = cams
    excess = {c: v["residual"] * math.sqrt(v["unexplained"]) for c, v in cams.items()}
    if not any(excess.values()):
        return
    bright = _floor_shifts(st, u, J, y, sqrt_w / scale, fitted, excess)
    cov_u = _misfit.regional_spread(st, J, res._linear["residual"], cams)
    d = np.array([c.dv_du(float(x)) for c, x in zip(st.coords, u)])
    spread = np.sqrt(np.clip(np.diag(cov_u), 0, None)) * np.abs(d)
    for p, s in zip(res.paths, spread):
        parts[p]["misfit"] = math.hypot(bright.get(p, 0.0), float(s))
    said = _misfit.message(cams)
    if said:
        warnings.warn(said, MisfitWarning, stacklevel=4)
        res.warnings.append(said)


def _start(model, sources):
    """Where ``model``'s light solve at the estimate starts: the light state of a render there
    with another model (``sources``, (model, state)) resampled onto its lattice (that
    model's own lattice if one had it, else the finest), or None (from zero).  A close start
    saves GMRES steps, the same answer to the tolerance (the README example: the N = 56,
    M = 4 render from the N = 28, M = 3 fit's light, 11 steps instead of 13)."""
    resample = getattr(model, "resampled_state", None)
    lattice = getattr(model, "lattice", None)
    if resample is None or lattice is None:
        return None
    usable = [(m, s) for m, s in sources if getattr(m, "lattice", None) is not None]
    if not usable:
        return None

    def key(ms):
        lat = ms[0].lattice
        same = tuple(lat.shape) == tuple(lattice.shape) and lat.h == lattice.h
        return (same, -lat.h)
    src, state = max(usable, key=key)
    return resample(state, src)


def _finer_images(st, model, u, init=None):
    """(``model``'s images at the unconstrained unknowns ``u`` (float64, flattened as the
    residual), None, its light state) or (None, why not (its light solve did not converge),
    None); ``init``: the light state of an earlier render with ``model`` to start from."""
    y_f, code, state = st.stepper.images(jnp.asarray(u, st.data[0].dtype), (model, st.data),
                                         init)
    if int(code) != RESULTS.successful:
        return None, f"that light solve did not converge ({RESULTS(int(code)).name})", None
    return np.asarray(y_f, np.float64), None, state


def _iterated_correction(st, model, u, u_first, J, y, weight, known, factor: float,
                         refine_steps: int, label: str, light, show):
    """The finer model's own best fit, by defect correction from the fit at ``u``: the step
    u_k+1 = u_k − J⁺·w·(y_f(u_k) − y(u)) with the fit's Jacobian J, whose fixed point has
    Jᵀ·w·(y_f − target) = Jᵀ·w·(y(u) − target) = 0 (the fit's own optimality): the finer
    model's least squares, to the extent J's columns span its Jacobian's.  The first step is
    the plain correction; each further one costs one render of ``model``.  Stops when a step
    moves every estimate by less than a tenth of the uncertainty it will be stated with, as far
    as it is known before the checks render (``known``: the standard error and the brightness
    floor's part; and the lattice part, factor × the correction; the steps shrink about tenfold
    each on cloud-plane, so what is left is a hundredth of it), or after
    ``refine_steps`` renders (``u_first``: where the first step landed; ``light``: the light
    state of the first render, where the next starts: its estimate is close).  Returns (estimates,
    renders, {path: the last step, where the steps did not become small}, a note or None)."""
    fitted = before = _physical(st, u)

    def tolerance(p, v):
        return max(0.1 * math.hypot(known[p], factor * (v - fitted[p])), 1e-6 * abs(v))

    uk = u_first
    renders = 1
    while True:
        now = _physical(st, uk)
        last = {p: abs(now[p] - before[p]) for p in now}
        if all(last[p] <= tolerance(p, now[p]) for p in now):
            return now, renders, {}, None
        if renders >= refine_steps:
            return now, renders, last, (
                f"the correction to {label} stopped after {renders} steps, its last still "
                f"larger than a tenth of the uncertainty; that step is counted in the model "
                f"error (\"refine_steps\"); refine_steps={refine_steps} sets how many")
        show(renders + 1)
        y_f, why, light = _finer_images(st, model, uk, light)
        if why is not None:
            return now, renders, last, (
                f"the correction to {label} stopped after {renders} steps: at the next, {why}; "
                f"its last step is counted in the model error (\"refine_steps\")")
        renders += 1
        before = now
        uk = uk + _gauss_newton_step(J, weight * (y_f - y))


def _ladder_levels(scene: Scene, forward, resolution, model_settings, ladder) -> tuple:
    """The resolutions of the ladder, coarse to fine (one level: no ladder)."""
    if ladder is None:
        return ()
    if not isinstance(forward, str):
        raise DifffogError("ladder needs a named solver (forward=\"sweep\" or \"splat\"): a "
                           "forward model object has one resolution; use ladder=None")
    if isinstance(ladder, str):
        if ladder != "auto":
            raise DifffogError(f"ladder={ladder!r}: use \"auto\", None or two resolutions "
                               "(coarse, fine), e.g. (24, 32)")
        from ..geometry._lattice import thin_resolution

        fine = int(resolution or {**solver_entry(forward).fit_defaults,
                                  **(model_settings or {})}.get("resolution", 32))
        coarse = max(round(0.75 * fine), thin_resolution(scene))
        return (coarse, fine) if coarse < fine else ()
    levels = tuple(int(n) for n in ladder)
    if len(levels) != 2 or not 2 <= levels[0] < levels[1]:
        raise DifffogError(f"ladder={ladder!r}: give two resolutions, coarse then fine, e.g. "
                           "(24, 32)")
    if resolution is not None and int(resolution) != levels[1]:
        raise DifffogError(f"ladder {levels} ends at {levels[1]}, but resolution={resolution}; "
                           "give one of them")
    return levels


def _with_model_error(fine: FitResult, coarse: FitResult, levels) -> FitResult:
    """``fine`` with its model error (first-order Richardson from the ladder's two levels) and
    total uncertainty."""
    nc, nf = levels
    factor = nc / (nf - nc)  # θ(h) = θ* + c·h  ⇒  θ(h_f) − θ* = (θ_f − θ_c)·h_f / (h_c − h_f)
    ok = coarse.converged and fine.converged
    fine.model_error = {p: (factor * abs(fine.estimates[p] - coarse.estimates[p]) if ok
                            else float("nan")) for p in fine.paths}
    fine.uncertainty = {p: math.hypot(fine.stderr[p], fine.model_error[p]) for p in fine.paths}
    fine.ladder = [{"resolution": n, "estimates": r.estimates, "iterations": r.iterations,
                    "time_s": r.time_s, "result": r.result} for n, r in zip(levels, (coarse, fine))]
    if not coarse.converged:
        fine.warnings.append(f"the model error is not estimated: the fit at the ladder's coarse "
                             f"resolution {nc} did not converge ({coarse.result})")
    return fine


def _fit_level(scene: Scene, targets: Mapping[str, Any], unknowns, *, progress,
               checkpoint=None, resume: bool = False, callback=None, **settings) -> FitResult:
    """One fit at one resolution (:func:`fit` without the ladder); ``settings`` are
    :func:`_setup`'s (``fit``'s arguments of that name, resolution included)."""
    t_start = time.perf_counter()
    st = _setup(scene, targets, unknowns, **settings)
    rtol, max_steps, stall_steps = settings["rtol"], settings["max_steps"], settings["stall_steps"]
    stepper, args = st.stepper, st.args
    state = stepper.init(st.u0, args)
    u = st.u0
    history, k0, elapsed0 = [], 0, 0.0
    ckpt = Path(checkpoint) if checkpoint is not None else None
    if resume:
        if ckpt is None:
            raise DifffogError("resume=True needs checkpoint=PATH (the file a killed fit wrote)")
        u, state, k0, history, elapsed0 = _checkpoint.load_checkpoint(ckpt, st.u0, state,
                                                                      st.fingerprint)
    tr = _Tracker(st, history, k0)
    meter = as_meter(progress, "fit")
    if k0 > 0:
        done_arr, tr.code = stepper.terminate(u, state, args)
        tr.done = bool(done_arr)
    t_loop = time.perf_counter()
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always", AdjointWarning)
        while not tr.done and tr.k < max_steps:
            u, state, _ = stepper.step(u, state, args)
            done_arr, code = stepper.terminate(u, state, args)
            entry = tr.record(u, state, done_arr, code, stall_steps=stall_steps, rtol=rtol,
                              now=round(elapsed0 + time.perf_counter() - t_loop, 3))
            if ckpt is not None:
                _checkpoint.save_checkpoint(ckpt, u, state, tr.k, tr.history, st.fingerprint,
                                            entry["time_s"])
            meter.update(tr.k, max_steps, **_postfix(entry))
            if callback is not None:
                callback(entry)
    meter.close()
    extra = _rewarn(caught)
    res = _finish(tr, u, state, time_s=0.0, rtol=rtol, atol=settings["atol"],
                  max_steps=max_steps, stall_steps=stall_steps, extra_warnings=extra)
    # the wall time, the final statistics pass (a Jacobian at the estimate) included
    res.time_s = elapsed0 + time.perf_counter() - t_start
    return res


def _rewarn(caught) -> list[str]:
    """Adjoint warnings caught during the steps (one line each, deduplicated); any other
    warning is re-issued as it was."""
    out = []
    for w in caught:
        if issubclass(w.category, AdjointWarning):
            if str(w.message) not in out:
                out.append(str(w.message))
        else:
            warnings.warn_explicit(w.message, w.category, w.filename, w.lineno)
    return out


def fit_batch(scene: Scene, targets: Sequence[Mapping[str, Any]], unknowns, *,
              devices: int = 1, max_steps: int = 50, rtol: float = 1e-4, atol: float = 1e-4,
              stall_steps: int = 3, progress=None, **kwargs) -> list[FitResult]:
    """Fit the same unknowns to many target sets at once (a parameter study, a time series, a
    set of images): one forward model and one compiled step, ``vmap``-ed over the fits and
    split over ``devices`` JAX devices (each device steps its share, no communication).

    targets: a list of {camera: image} dicts, all with the same cameras.
    devices: JAX devices sharing the fits (on a CPU, N host devices need
        ``XLA_FLAGS=--xla_force_host_platform_device_count=N`` before JAX starts).
    kwargs: :func:`fit`'s other arguments (not checkpoint, resume or callback).
    All fits step together; a fit that has converged (or stalled, or failed) is frozen while
    the others go on, so every result equals what :func:`fit` returns for that target set.
    """
    for bad in ("checkpoint", "resume", "callback"):
        if bad in kwargs:
            raise DifffogError(f"fit_batch: {bad} is not supported; run fit() per target set "
                               f"for checkpoints and callbacks")
    if _has_sun(unknowns):
        raise DifffogError("fit_batch: the sun's angles as unknowns need a model rebuilt at "
                           "each fit's estimated sun; run fit() per target set")
    unknown = set(kwargs) - set(_SETUP_DEFAULTS)
    if unknown:
        raise DifffogError(f"fit_batch: unknown keyword {', '.join(sorted(unknown))}; it takes "
                           f"fit()'s: {', '.join(sorted(_SETUP_DEFAULTS))}")
    targets = list(targets)
    if not targets:
        raise DifffogError("fit_batch: targets is empty; give a list of {camera: image} dicts")
    if len({tuple(sorted(t)) for t in targets}) != 1:
        raise DifffogError("fit_batch: every target set must have the same cameras "
                           f"(got {sorted({tuple(sorted(t)) for t in targets})})")
    if devices > 1:
        batch_devices(devices)  # a clear error when there are not enough devices
    t_start = time.perf_counter()
    setups = []
    opts = {**_SETUP_DEFAULTS, **kwargs}
    opts["model_settings"] = _phase_order_for_g(scene, opts.get("forward", "sweep"), unknowns,
                                                opts.get("model_settings"))
    for t in targets:  # the first builds the forward model, the others reuse it
        st = _setup(scene, t, unknowns, max_steps=max_steps, rtol=rtol, atol=atol,
                    stall_steps=stall_steps, **opts)
        opts.update(forward=st.model, resolution=None, model_settings=None)
        setups.append(st)
    model = setups[0].model
    stepper = setups[0].stepper
    states = [stepper.init(s.u0, s.args) for s in setups]
    static = eqx.partition(states[0], eqx.is_array)[1]
    stack = lambda xs: jax.tree.map(lambda *a: jnp.stack(a), *xs)  # noqa: E731
    x = stack([(s.u0, eqx.partition(q, eqx.is_array)[0], s.data) for s, q in zip(setups, states)])

    def one(model, xi):
        u, dyn, data = xi
        u2, state2, _ = stepper.step_impl(u, eqx.combine(dyn, static), (model, data))
        done, code = stepper.term_impl(u2, state2, (model, data))
        return u2, eqx.partition(state2, eqx.is_array)[0], done, code

    trackers = [_Tracker(s) for s in setups]
    meter = as_meter(progress, f"fit x{len(setups)}")
    t_loop = time.perf_counter()
    step = 0
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always", AdjointWarning)
        while not all(t.done for t in trackers) and step < max_steps:
            u2, dyn2, done2, code2 = map_batch(one, model, x, devices)
            step += 1
            keep = jnp.asarray([t.done for t in trackers])
            x = (jax.tree.map(lambda a, b: jnp.where(keep.reshape((-1,) + (1,) * (a.ndim - 1)),
                                                     a, b), (x[0], x[1]), (u2, dyn2)) + (x[2],))
            now = round(time.perf_counter() - t_loop, 3)
            for i, tr in enumerate(trackers):
                if tr.done:
                    continue
                state_i = eqx.combine(jax.tree.map(lambda a: a[i], x[1]), static)
                tr.record(x[0][i], state_i, done2[i], jax.tree.map(lambda a: a[i], code2),
                          now=now, stall_steps=stall_steps, rtol=rtol)
            meter.update(sum(t.done for t in trackers), len(trackers), step=step)
    meter.close()
    extra = _rewarn(caught)
    elapsed = time.perf_counter() - t_start
    out = []
    for i, tr in enumerate(trackers):
        state_i = eqx.combine(jax.tree.map(lambda a: a[i], x[1]), static)
        res = _finish(tr, x[0][i], state_i, time_s=elapsed, rtol=rtol, atol=atol,
                      max_steps=max_steps, stall_steps=stall_steps, extra_warnings=extra)
        res.settings = dict(res.settings, devices=devices, batch=len(trackers))
        out.append(res)
    return out


# fit()'s keywords that fit_batch passes through, with fit()'s own defaults
import inspect as _inspect  # noqa: E402

_SETUP_DEFAULTS = {k: _inspect.signature(fit).parameters[k].default
                   for k in ("optimizer", "forward", "resolution", "downsample",
                             "model_settings", "weights", "loss", "loss_scale", "dtype",
                             "channel", "transfer", "edge_weight")}
