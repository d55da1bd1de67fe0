"""Inverse fog estimation: fit ζ, γ, albedo (and nuisance parameters) to images.

``fit(scene, targets, unknowns)`` renders every target camera from one light solve per step,
compares with the targets and lets optimistix (Levenberg–Marquardt by default, Gauss–Newton or
BFGS on request) move the unknowns in unconstrained coordinates: log for coefficients and
light intensities, logit for albedo, a scaled logit for bounded values and for ``fog.g``.

The Jacobian (pixels × unknowns) is computed once per evaluated point, by forward mode: each of
its n columns costs one tangent linear solve of the light field (the transpose of the
implicit adjoint of ``SweepSolver.solve``) and one pass of the camera.  The camera march has
a hand-written reverse pass (``jax.custom_vjp``), so the column J·t is obtained as the
transpose of the (linear) vector–Jacobian product: ``jax.linear_transpose(vjp)``.  Reverse
mode would need one adjoint solve per *pixel*.  The residual handed to optimistix is a
``jax.custom_jvp`` function whose tangent is ``J @ t`` with that J, so optimistix materialises
J once per step and its state stays a small array pytree — which is what the per-step
checkpoint stores.

Statistics at the optimum use the Gauss–Newton approximation: Cov(u) = s²(JᵀJ)⁻¹ with
s² = Σr²/(m − n) the residual variance, mapped to physical units by the derivative of each
transform (delta method).
"""

from __future__ import annotations

import dataclasses
import hashlib
import inspect
import json
import math
import os
import sys
import tempfile
import time
import warnings
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Mapping, Sequence

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optimistix as optx

from ._errors import DifffogError
from ._params import Params, get_param, param_paths, set_param
from ._scene import Scene


class IdentifiabilityWarning(UserWarning):
    """The unknowns are not (well) determined by the given views: near-singular JᵀJ or a
    correlation above 0.99 between two estimates."""


# --------------------------------------------------------------------------------------------
# unknowns and their unconstrained coordinates
# --------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class Unknown:
    """One parameter to fit: a dotted path (see :func:`difffog.param_paths`), its initial value
    (None: the scene's value) and optional bounds (None: the natural ones: (0, ∞) for
    coefficients and lights, (0, 1) for albedo, (−0.99, 0.99) for ``fog.g``)."""

    path: str
    init: float | None = None
    lower: float | None = None
    upper: float | None = None


def _kind(path: str) -> str:
    if path.endswith(".albedo"):
        return "albedo"
    if path == "fog.g":
        return "g"
    return "positive"


_NATURAL = {"albedo": (0.0, 1.0), "g": (-0.99, 0.99), "positive": (0.0, math.inf)}


@dataclass(frozen=True)
class _Coord:
    """Map between a physical value v and an unconstrained u (static, hashable)."""

    path: str
    lower: float
    upper: float

    @property
    def mode(self) -> str:
        if math.isinf(self.upper):
            return "log"  # v = lower + exp(u)
        if self.lower > 0 and self.upper / self.lower > 10:
            return "loglogit"  # log v = log lo + (log hi − log lo)·σ(u)
        return "logit"  # v = lo + (hi − lo)·σ(u)

    def to_u(self, v: float) -> float:
        lo, hi = self.lower, self.upper
        if self.mode == "log":
            return math.log(v - lo)
        if self.mode == "loglogit":
            s = (math.log(v) - math.log(lo)) / (math.log(hi) - math.log(lo))
        else:
            s = (v - lo) / (hi - lo)
        return math.log(s) - math.log1p(-s)

    def to_v(self, u):
        lo, hi = self.lower, self.upper
        if self.mode == "log":
            return lo + jnp.exp(u)
        s = jax.nn.sigmoid(u)
        if self.mode == "loglogit":
            return jnp.exp(math.log(lo) + (math.log(hi) - math.log(lo)) * s)
        return lo + (hi - lo) * s

    def dv_du(self, u: float) -> float:
        lo, hi = self.lower, self.upper
        if self.mode == "log":
            return math.exp(u)
        s = 1.0 / (1.0 + math.exp(-u))
        if self.mode == "loglogit":
            return float(self.to_v(u)) * (math.log(hi) - math.log(lo)) * s * (1.0 - s)
        return (hi - lo) * s * (1.0 - s)


def _as_unknowns(unknowns) -> list[Unknown]:
    if isinstance(unknowns, (str, Unknown)):
        unknowns = [unknowns]
    out: list[Unknown] = []
    if isinstance(unknowns, Mapping):
        for path, spec in unknowns.items():
            if spec is None or isinstance(spec, (int, float)):
                out.append(Unknown(path, None if spec is None else float(spec)))
            elif isinstance(spec, Unknown):
                out.append(dataclasses.replace(spec, path=path))
            elif isinstance(spec, (tuple, list)) and len(spec) == 3:
                out.append(Unknown(path, *(None if s is None else float(s) for s in spec)))
            elif isinstance(spec, Mapping):
                out.append(Unknown(path, **spec))
            else:
                raise DifffogError(
                    f"unknown '{path}': give an initial value, (init, lower, upper) or "
                    f"an Unknown, got {spec!r}")
    else:
        for u in unknowns:
            out.append(u if isinstance(u, Unknown) else Unknown(str(u)))
    if not out:
        raise DifffogError("no unknowns: name at least one parameter path to fit, "
                           "e.g. fog.scattering")
    seen = set()
    for u in out:
        if u.path in seen:
            raise DifffogError(f"unknown '{u.path}' is listed twice")
        seen.add(u.path)
    return out


def _coords(scene: Scene, base: Params, unknowns: list[Unknown]) -> tuple[list[_Coord], list[float]]:
    coords, inits = [], []
    valid = param_paths(scene)
    for u in unknowns:
        if u.path not in valid:
            import difflib

            close = difflib.get_close_matches(u.path, valid, n=1)
            hint = f" Did you mean '{close[0]}'?" if close else ""
            raise DifffogError(f"unknown '{u.path}' is not a parameter of scene "
                               f"'{scene.title}'.{hint} Valid: {', '.join(valid)}")
        kind = _kind(u.path)
        nlo, nhi = _NATURAL[kind]
        lo = nlo if u.lower is None else float(u.lower)
        hi = nhi if u.upper is None else float(u.upper)
        if lo < nlo or hi > nhi or not lo < hi:
            raise DifffogError(
                f"unknown '{u.path}': bounds [{lo}, {hi}] must satisfy {nlo} <= lower < upper "
                f"<= {nhi}")
        v0 = float(get_param(base, scene, u.path)) if u.init is None else float(u.init)
        if not (lo < v0 < hi) or not math.isfinite(v0):
            src = "the scene's value" if u.init is None else "the initial value"
            raise DifffogError(
                f"unknown '{u.path}': {src} {v0:g} lies outside the open interval ({lo:g}, "
                f"{hi:g}); give an initial value inside the bounds, e.g. {u.path}="
                f"{(lo + 1.0) if math.isinf(hi) else 0.5 * (lo + hi):g}")
        coords.append(_Coord(u.path, lo, hi))
        inits.append(v0)
    return coords, inits


# --------------------------------------------------------------------------------------------
# the forward model
# --------------------------------------------------------------------------------------------
def _reduced_scene(scene: Scene, names: list[str], downsample: int) -> Scene:
    cams = []
    for c in scene.cameras:
        if c.name not in names:
            continue
        if c.width % downsample or c.height % downsample:
            raise DifffogError(
                f"downsample {downsample}: camera '{c.name}' is {c.width}x{c.height}, not "
                f"divisible by {downsample}; choose a common divisor of its width and height")
        cams.append(dataclasses.replace(c, resolution=(c.width // downsample,
                                                       c.height // downsample)))
    return scene.replace(cameras=tuple(cams))


def make_forward(scene: Scene, forward="sweep", *, cameras: list[str], resolution: int = 32,
                 directions: int = 3, downsample: int = 1, supersample: int = 2,
                 light_tol: float = 1e-5, max_iterations: int = 1000,
                 adjoint_rtol: float = 1e-4, devices: int = 1):
    """The forward model of a fit: an object with ``.params(dtype)``, ``__call__(params)`` →
    {camera: (H, W)}, ``.scene`` and ``.cameras``.  ``forward`` is "sweep", "splat" or such an
    object (returned as it is)."""
    if not isinstance(forward, str):
        for attr in ("params", "scene", "cameras"):
            if not hasattr(forward, attr) or not callable(forward):
                raise DifffogError(
                    f"forward: {type(forward).__name__} is not a forward model; pass 'sweep', "
                    f"'splat' or an object with .params(), .scene, .cameras and __call__(params)")
        return forward
    small = _reduced_scene(scene, cameras, downsample)
    if forward == "sweep":
        from ._render import Renderer
        from ._solver import SweepSolver

        # the Jacobian's tangent solves need far less accuracy than the images: LM converges
        # with an approximate Jacobian, and the estimates depend only on the residual
        solver = SweepSolver(M=directions, tol=light_tol, max_iterations=max_iterations,
                             adjoint_rtol=adjoint_rtol, devices=devices)
        return Renderer(small, resolution=resolution, solver=solver, supersample=supersample)
    if forward == "splat":
        try:
            from ._splat import SplatRenderer  # type: ignore[import-not-found]
        except ImportError as e:
            raise DifffogError(
                "forward 'splat': the splat renderer is not available in this version of "
                "difffog; use forward='sweep'") from e
        if devices != 1:
            raise DifffogError("forward 'splat' renders on one device; devices applies to the "
                               "sweep (or share many fits over devices with fit_batch)")
        return SplatRenderer(small, resolution=resolution, supersample=supersample)
    raise DifffogError(f"forward '{forward}': choose 'sweep', 'splat' or a forward-model object")


def _block_mean(img: np.ndarray, k: int) -> np.ndarray:
    H, W = img.shape
    return img.reshape(H // k, k, W // k, k).mean(axis=(1, 3))


def _prepare_targets(scene: Scene, fwd, targets: Mapping[str, Any], weights, downsample: int):
    """Check and downsample targets (and weights) to the forward model's camera shapes."""
    if not isinstance(targets, Mapping) or not targets:
        raise DifffogError("targets: give a dict {camera name: (H, W) image}, at least one")
    out_t, out_w = {}, {}
    fcams = {c.name: c for c in fwd.cameras}
    weights = {} if weights is None else weights
    for name in weights:
        if name not in targets:
            raise DifffogError(f"weights: camera '{name}' has no target; weights must be keyed "
                               f"like the targets ({', '.join(targets)})")
    for name, img in targets.items():
        scene.camera(name)  # clear error for an unknown camera
        if name not in fcams:
            raise DifffogError(f"target '{name}': the forward model has no camera '{name}' "
                               f"(it has {', '.join(fcams)})")
        cam = fcams[name]
        full = scene.camera(name)
        a = np.asarray(img, np.float64)
        w = weights.get(name)
        w = np.ones_like(a) if w is None else np.asarray(w, np.float64)
        if w.dtype == bool:
            w = w.astype(np.float64)
        if w.shape != a.shape:
            raise DifffogError(f"weights '{name}': shape {w.shape} differs from its target's "
                               f"{a.shape}")
        want = (cam.height, cam.width)
        if a.shape == want:
            pass
        elif a.shape == (full.height, full.width) and (full.height, full.width) != want:
            k = full.height // cam.height
            if (full.height, full.width) != (cam.height * k, cam.width * k):
                raise DifffogError(f"target '{name}': shape {a.shape} cannot be reduced to the "
                                   f"forward model's {want}")
            # the reduced camera's pixel is the box-filtered footprint of k×k full pixels:
            # the weighted mean of the target over it, with the total weight
            wa = _block_mean(w * a, k)
            ws = _block_mean(w, k)
            a = np.where(ws > 0, wa / np.where(ws > 0, ws, 1.0), 0.0)
            w = ws
        else:
            extra = (f" or {(full.height, full.width)} (the scene camera's, reduced by "
                     f"downsample {downsample})") if want != (full.height, full.width) else ""
            raise DifffogError(f"target '{name}': shape {a.shape}, expected (height, width) = "
                               f"{want}{extra}")
        if not np.all(np.isfinite(a[w > 0])):
            raise DifffogError(f"target '{name}': has NaN or infinite pixels; mask them with a "
                               f"zero weight or replace them")
        if np.any(w < 0) or not np.all(np.isfinite(w)):
            raise DifffogError(f"weights '{name}': must be finite and >= 0")
        out_t[name], out_w[name] = np.where(w > 0, a, 0.0), w
    if sum(float(w.sum()) for w in out_w.values()) == 0:
        raise DifffogError("weights: every pixel has zero weight; nothing to fit")
    return out_t, out_w


# --------------------------------------------------------------------------------------------
# residuals and their Jacobian
# --------------------------------------------------------------------------------------------
_LOSSES = ("linear", "huber", "soft_l1", "cauchy")


def _robust_factor(z, loss: str):
    """sqrt(ρ(z)/z) for z = (r/c)² ≥ 0: the residual r becomes r·factor so that Σ r̃² = c²Σρ."""
    if loss == "linear":
        return jnp.ones_like(z)
    if loss == "soft_l1":  # ρ = 2(√(1+z) − 1) → ρ/z = 2/(√(1+z) + 1)
        return jnp.sqrt(2.0 / (jnp.sqrt(1.0 + z) + 1.0))
    if loss == "huber":  # ρ = z (z ≤ 1), 2√z − 1
        big = z > 1.0
        zs = jnp.where(big, z, 1.0)
        return jnp.sqrt(jnp.where(big, (2.0 * jnp.sqrt(zs) - 1.0) / zs, 1.0))
    if loss == "cauchy":  # ρ = log(1+z)
        small = z < 1e-6
        zs = jnp.where(small, 1.0, z)
        return jnp.sqrt(jnp.where(small, 1.0 - z / 2.0, jnp.log1p(zs) / zs))
    raise AssertionError(loss)


@dataclass(frozen=True, eq=False)
class _Problem:
    """The fit problem (static, hashed by identity): model images (flattened over the cameras)
    of the unknowns u, given the parameters ``base`` that are not fitted."""

    forward: Any
    coords: tuple[_Coord, ...]
    names: tuple[str, ...]
    loss: str

    def params(self, u, base: Params) -> Params:
        p = base
        for i, c in enumerate(self.coords):
            p = set_param(p, self.forward.scene, c.path, c.to_v(u[i]))
        return p

    def model(self, u, base: Params):
        imgs = self.forward(self.params(u, base))
        return jnp.concatenate([jnp.ravel(imgs[n]) for n in self.names])

    def model_and_jacobian(self, u, base: Params):
        """(images (P,), J (P, n)) by forward mode: J·e_i as the transpose of the VJP."""
        y, vjp = jax.vjp(lambda x: self.model(x, base), u)
        jvp = jax.linear_transpose(vjp, y)
        eye = jnp.eye(u.shape[0], dtype=u.dtype)
        cols = jax.vmap(lambda e: jvp((e,))[0])(eye)
        return y, cols.T


def _model_cj(problem: _Problem, u, base: Params):
    @jax.custom_jvp
    def model(u, base):
        return problem.model(u, base)

    @model.defjvp
    def _jvp(primals, tangents):
        (u_, base_), (t, _) = primals, tangents  # base is data: its tangent is ignored
        y, J = problem.model_and_jacobian(u_, base_)
        return y, J @ t

    return model(u, base)


def _residual(problem: _Problem, u, data):
    """Weighted, normalised (and robustly rescaled) residuals; data = (target, sqrt_w, scale,
    loss_scale, base), the images flattened over the cameras."""
    target, sw, scale, c, base = data
    r = sw * (_model_cj(problem, u, base) - target) / scale
    if problem.loss != "linear":
        r = r * _robust_factor((r / c) ** 2, problem.loss)
    return r


# --------------------------------------------------------------------------------------------
# the result
# --------------------------------------------------------------------------------------------
@dataclass
class FitResult:
    """What a fit found and how sure it is.

    estimates / stderr / initial: {path: value} in physical units; stderr from the
    Gauss–Newton covariance s²(JᵀJ)⁻¹ at the optimum (s² the residual variance), NaN where JᵀJ
    is singular.  correlation: (n, n) in the order of ``paths``.  residual_rms: root mean
    square of the weighted image residual (radiance units) over pixels with weight > 0.
    result: optimistix' result name ("successful", "nonlinear_max_steps_reached", …);
    converged: result is "successful" or "loss_stalled" (the loss stopped falling).
    history: one dict per step (step, values, loss,
    accepted, time_s).  images / targets: fitted and target images per camera (the forward
    model's resolution).
    """

    paths: list[str]
    estimates: dict[str, float]
    stderr: dict[str, float]
    correlation: np.ndarray
    initial: dict[str, float]
    residual_rms: float
    loss: float
    iterations: int
    time_s: float
    result: str
    message: str
    warnings: list[str]
    history: list[dict]
    images: dict[str, np.ndarray] = field(repr=False, default_factory=dict)
    targets: dict[str, np.ndarray] = field(repr=False, default_factory=dict)
    condition: float = float("nan")  # of the column-normalised J (√ of JᵀJ's)
    settings: dict = field(default_factory=dict)

    @property
    def converged(self) -> bool:
        return self.result in ("successful", "loss_stalled")

    def relative_error(self, truth: Mapping[str, float]) -> dict[str, float]:
        return {p: (self.estimates[p] - truth[p]) / truth[p] for p in self.paths if p in truth}

    def summary(self, truth: Mapping[str, float] | None = None) -> str:
        w = max(len(p) for p in self.paths)
        head = f"{'unknown':<{w}}  {'initial':>10}  {'estimate':>10}  {'std err':>9}"
        if truth:
            head += f"  {'truth':>10}  {'error %':>8}"
        lines = [head, "-" * len(head)]
        for p in self.paths:
            s = (f"{p:<{w}}  {self.initial[p]:>10.4g}  {self.estimates[p]:>10.4g}  "
                 f"{self.stderr[p]:>9.2g}")
            if truth and p in truth:
                s += f"  {truth[p]:>10.4g}  {100 * (self.estimates[p] / truth[p] - 1):>+8.3f}"
            lines.append(s)
        lines.append(f"{self.result} after {self.iterations} steps in {self.time_s:.1f} s; "
                     f"residual RMS {self.residual_rms:.3g}")
        if len(self.paths) > 1:
            lines.append("correlation:")
            for i, p in enumerate(self.paths):
                lines.append(f"  {p:<{w}} " + " ".join(f"{x:+.3f}" for x in self.correlation[i]))
        if not self.converged:
            lines.append(f"not converged: {self.message}")
        elif self.message:
            lines.append(self.message)
        lines += [f"warning: {m}" for m in self.warnings]
        return "\n".join(lines)

    __str__ = summary

    def to_json(self) -> dict:
        return {
            "estimates": self.estimates,
            "stderr": {k: (None if not math.isfinite(v) else v) for k, v in self.stderr.items()},
            "correlation": [[None if not math.isfinite(x) else float(x) for x in row]
                            for row in np.asarray(self.correlation)],
            "paths": self.paths,
            "initial": self.initial,
            "residual_rms": self.residual_rms,
            "loss": self.loss,
            "iterations": self.iterations,
            "time_s": self.time_s,
            "result": self.result,
            "converged": self.converged,
            "message": self.message,
            "warnings": self.warnings,
            "condition": None if not math.isfinite(self.condition) else self.condition,
            "history": self.history,
            "settings": self.settings,
        }


def _result_name(code) -> str:
    for name in ("successful", "nonlinear_max_steps_reached", "nonlinear_divergence",
                 "nonfinite", "singular", "breakdown", "stagnation", "max_steps_reached"):
        try:
            if bool(code == getattr(optx.RESULTS, name)):
                return name
        except AttributeError:
            continue
    return "failed"


# --------------------------------------------------------------------------------------------
# the optimiser
# --------------------------------------------------------------------------------------------
def _make_solver(solver, rtol: float, atol: float):
    if isinstance(solver, (optx.AbstractLeastSquaresSolver, optx.AbstractMinimiser)):
        return solver
    table = {
        "lm": lambda: optx.LevenbergMarquardt(rtol=rtol, atol=atol),
        "levenberg-marquardt": lambda: optx.LevenbergMarquardt(rtol=rtol, atol=atol),
        "gauss-newton": lambda: optx.GaussNewton(rtol=rtol, atol=atol),
        "gn": lambda: optx.GaussNewton(rtol=rtol, atol=atol),
        "bfgs": lambda: optx.BFGS(rtol=rtol, atol=atol),
    }
    if solver not in table:
        raise DifffogError(f"solver '{solver}': choose 'lm' (Levenberg–Marquardt, default), "
                           f"'gauss-newton', 'bfgs' or an optimistix solver instance")
    return table[solver]()


class _Stepper:
    """Jitted init/step/terminate of an optimistix solver on the fit problem, stepped from
    Python so that every step can be checkpointed and reported."""

    def __init__(self, problem: _Problem, solver):
        self.problem = problem
        self.solver = solver
        self.minimise = isinstance(solver, optx.AbstractMinimiser)
        self.options = {} if self.minimise else {"jac": "fwd"}

        def fn(u, args):
            r = _residual(problem, u, args)
            loss = 0.5 * jnp.sum(r * r)
            return (loss, loss) if self.minimise else (r, loss)

        self.fn = fn
        self._static = None
        self._step = eqx.filter_jit(self._step_impl)
        self._term = eqx.filter_jit(self._term_impl)
        self._rj = eqx.filter_jit(self._rj_impl)

    def init(self, u0, data):
        f_struct, aux_struct = jax.eval_shape(self.fn, u0, data)
        state = self.solver.init(self.fn, u0, data, self.options, f_struct, aux_struct,
                                 frozenset())
        # The state's static part holds a closure-converted jaxpr (the linearised residual)
        # that compares by identity: reuse the first fit's so that later fits with this stepper
        # hit the compilation cache instead of compiling the step again.
        dyn, static = eqx.partition(state, eqx.is_array)
        if self._static is None:
            self._static = static
        return eqx.combine(dyn, self._static)

    def _step_impl(self, u, state, data):
        return self.solver.step(self.fn, u, data, self.options, state, frozenset())

    def _term_impl(self, u, state, data):
        return self.solver.terminate(self.fn, u, data, self.options, state, frozenset())

    def step(self, u, state, data):
        return self._step(u, state, data)

    def terminate(self, u, state, data):
        return self._term(u, state, data)

    def _rj_impl(self, u, data):
        """Residual and its Jacobian at u (for the statistics), and the model images."""
        target, sw, scale, c, base = data
        y, J = self.problem.model_and_jacobian(u, base)
        r = sw * (y - target) / scale
        Jr = (sw / scale)[:, None] * J
        if self.problem.loss != "linear":
            f = _robust_factor((r / c) ** 2, self.problem.loss)
            # d(r·f(r))/dr, by autodiff of the scalar map
            dfr = jax.vmap(jax.grad(lambda x: x * _robust_factor((x / c) ** 2,
                                                                  self.problem.loss)))(r)
            Jr = dfr[:, None] * Jr
            r = r * f
        return r, Jr, y

    def residual_and_jacobian(self, u, data):
        return self._rj(u, data)

    def final(self, u, state, data):
        """Residual, Jacobian and images at the final u.  A least-squares solver's state holds
        the residual and the (linearised) Jacobian at u already: reuse them, so only the
        images' forward pass is computed again (BFGS: everything)."""
        info = getattr(state, "f_info", None)
        if isinstance(info, optx.FunctionInfo.ResidualJac):
            r, J = self._from_state(info)
            y = self._model(u, data[4])
            return r, J, y
        return self.residual_and_jacobian(u, data)

    @eqx.filter_jit
    def _from_state(self, info):
        return info.residual, info.jac.as_matrix()

    @eqx.filter_jit
    def _model(self, u, base):
        return self.problem.model(u, base)


# Compiled steppers of recent fits, so that fitting new targets (or from a new start) with
# the same forward model, unknowns and solver does not compile again.
_STEPPERS: dict = {}


def _stepper(forward, coords, names, loss, opt) -> _Stepper:
    key = (id(forward), tuple(coords), tuple(names), loss, repr(opt))
    hit = _STEPPERS.get(key)
    if hit is not None and hit.problem.forward is forward:
        return hit
    st = _Stepper(_Problem(forward, tuple(coords), tuple(names), loss), opt)
    _STEPPERS[key] = st
    while len(_STEPPERS) > 4:
        _STEPPERS.pop(next(iter(_STEPPERS)))
    return st


def _fingerprint(**kw) -> str:
    return hashlib.sha256(json.dumps(kw, sort_keys=True, default=str).encode()).hexdigest()[:16]


def _save_checkpoint(path: Path, u, state, k: int, history: list, fingerprint: str,
                     elapsed: float) -> None:
    leaves = jax.tree.leaves(eqx.filter((u, state), eqx.is_array))
    meta = json.dumps({"fingerprint": fingerprint, "step": k, "history": history,
                       "elapsed_s": elapsed})
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=".ckpt-", suffix=".npz", dir=path.parent)
    try:
        with os.fdopen(fd, "wb") as f:
            np.savez(f, meta=np.array(meta), **{f"leaf{i}": np.asarray(x)
                                                for i, x in enumerate(leaves)})
        os.replace(tmp, path)  # atomic: a kill leaves the previous checkpoint intact
    finally:
        if os.path.exists(tmp):
            os.unlink(tmp)


def _load_checkpoint(path: Path, u0, state0, fingerprint: str):
    if not path.exists():
        raise DifffogError(f"resume: no checkpoint at {path}; run the fit without resume first")
    with np.load(path, allow_pickle=False) as z:
        meta = json.loads(str(z["meta"]))
        if meta["fingerprint"] != fingerprint:
            raise DifffogError(
                f"resume: the checkpoint {path} belongs to a different fit (scene, targets, "
                f"unknowns or settings changed); delete it or run without resume")
        dyn, static = eqx.partition((u0, state0), eqx.is_array)
        old = jax.tree.leaves(dyn)
        new = [z[f"leaf{i}"] for i in range(len(old))]
    for a, b in zip(old, new):
        if a.shape != b.shape or np.dtype(a.dtype) != b.dtype:
            raise DifffogError(f"resume: the checkpoint {path} does not match this fit's "
                               f"solver state; delete it or run without resume")
    dyn = jax.tree.unflatten(jax.tree.structure(dyn), [jnp.asarray(b) for b in new])
    u, state = eqx.combine(dyn, static)
    return u, state, meta["step"], meta["history"], meta["elapsed_s"]


def _statistics(r: np.ndarray, J: np.ndarray, m: int, coords, u: np.ndarray):
    """Standard errors (physical units), correlation, condition and warnings."""
    n = J.shape[1]
    dof = max(m - n, 1)
    s2 = float(np.sum(r * r)) / dof
    norms = np.linalg.norm(J, axis=0)
    msgs = []
    if np.any(norms == 0):
        zero = [c.path for c, nm in zip(coords, norms) if nm == 0]
        msgs.append(f"the images do not depend on {', '.join(zero)} (zero Jacobian column): "
                    f"it cannot be estimated from these views")
    Jn = J / np.where(norms > 0, norms, 1.0)
    sv = np.linalg.svd(Jn, compute_uv=False)
    cond = float(sv[0] / sv[-1]) if sv[-1] > 0 else math.inf
    JtJ = J.T @ J
    if cond < 1e7 and not np.any(norms == 0):
        cov_u = s2 * np.linalg.inv(JtJ)
    else:
        cov_u = np.full((n, n), np.nan)
    d = np.array([c.dv_du(float(x)) for c, x in zip(coords, u)])
    cov = cov_u * np.outer(d, d)
    se = np.sqrt(np.clip(np.diag(cov), 0, None))
    with np.errstate(invalid="ignore", divide="ignore"):
        corr = cov / np.outer(se, se)
    np.fill_diagonal(corr, 1.0)
    if cond >= 1e4:
        msgs.append(f"JᵀJ is near-singular (condition {cond ** 2:.2g} after scaling the "
                    f"columns): some combination of the unknowns is not determined by these "
                    f"views; add a view, fix a nuisance parameter or give bounds")
    for i in range(n):
        for j in range(i + 1, n):
            if abs(corr[i, j]) > 0.99:
                msgs.append(f"{coords[i].path} and {coords[j].path} are correlated "
                            f"{corr[i, j]:+.3f}: the views determine a combination of them, not "
                            f"each; their standard errors are large")
    return se, corr, cond, msgs, s2


@dataclass
class _Setup:
    """Everything a fit needs before its first step (shared by :func:`fit` and
    :func:`fit_batch`)."""

    fwd: Any
    names: list[str]
    tgt: dict
    flat_t: np.ndarray
    flat_w: np.ndarray
    m: int
    data: tuple
    u0: Any
    coords: list
    inits: list
    stepper: _Stepper
    settings: dict
    fingerprint: str

    def values(self, u) -> dict[str, float]:
        return {c.path: float(c.to_v(x)) for c, x in zip(self.coords, np.asarray(u))}


def _setup(scene: Scene, targets, unknowns, *, solver, forward, resolution, directions,
           downsample, supersample, light_tol, weights, loss, loss_scale, rtol, atol, max_steps,
           stall_steps, dtype, devices) -> _Setup:
    unknowns = _as_unknowns(unknowns)
    if loss not in _LOSSES:
        raise DifffogError(f"loss '{loss}': choose one of {', '.join(_LOSSES)}")
    for name, v in (("resolution", resolution), ("directions", directions),
                    ("downsample", downsample), ("supersample", supersample),
                    ("max_steps", max_steps), ("devices", devices)):
        if not isinstance(v, (int, np.integer)) or v < 1:
            raise DifffogError(f"{name} must be a positive integer, got {v!r}")
    if not isinstance(stall_steps, (int, np.integer)) or stall_steps < 0:
        raise DifffogError(f"stall_steps must be an integer >= 0, got {stall_steps!r}")
    if not loss_scale > 0:
        raise DifffogError(f"loss_scale must be positive, got {loss_scale}")
    opt = _make_solver(solver, rtol, atol)
    if not isinstance(targets, Mapping) or not targets:
        raise DifffogError("targets: give a dict {camera name: (H, W) image}, at least one")
    for name in targets:
        scene.camera(name)
    names = sorted(targets)  # a fixed order: fits of the same views share one compiled step
    fwd = make_forward(scene, forward, cameras=names, resolution=resolution,
                       directions=directions, downsample=downsample, supersample=supersample,
                       light_tol=light_tol, devices=devices)
    tgt, wts = _prepare_targets(scene, fwd, targets, weights, downsample)
    dtype = dtype or jnp.result_type(float)
    base = fwd.params(dtype)
    coords, inits = _coords(fwd.scene, base, unknowns)
    flat_t = np.concatenate([tgt[n].ravel() for n in names])
    flat_w = np.concatenate([wts[n].ravel() for n in names])
    m = int(np.count_nonzero(flat_w))
    scale = float(np.sqrt(np.sum(flat_w * flat_t ** 2) / np.sum(flat_w))) or 1.0
    data = (jnp.asarray(flat_t, dtype), jnp.asarray(np.sqrt(flat_w), dtype),
            jnp.asarray(scale, dtype), jnp.asarray(loss_scale, dtype), base)
    u0 = jnp.asarray([c.to_u(v) for c, v in zip(coords, inits)], dtype)
    settings = {
        "forward": forward if isinstance(forward, str) else type(forward).__name__,
        "solver": solver if isinstance(solver, str) else type(solver).__name__,
        "resolution": resolution, "directions": directions, "downsample": downsample,
        "supersample": supersample, "light_tol": light_tol, "loss": loss,
        "loss_scale": loss_scale, "rtol": rtol, "atol": atol, "max_steps": max_steps,
        "stall_steps": stall_steps, "devices": devices,
        "dtype": str(np.dtype(dtype)), "cameras": names,
        "image_shapes": {n: list(tgt[n].shape) for n in names},
        "unknowns": [dataclasses.asdict(c) for c in coords],
    }
    # the fingerprint leaves out the device count: a checkpoint resumes on any number of them
    fp = _fingerprint(scene=repr(scene), settings={k: v for k, v in settings.items()
                                                   if k != "devices"}, init=inits,
                      t=hashlib.sha256(np.ascontiguousarray(flat_t).tobytes()).hexdigest(),
                      w=hashlib.sha256(np.ascontiguousarray(flat_w).tobytes()).hexdigest())
    return _Setup(fwd, names, tgt, flat_t, flat_w, m, data, u0, coords, inits,
                  _stepper(fwd, coords, names, loss, opt), settings, fp)


def _stalled(history: list[dict], stall_steps: int, rtol: float) -> bool:
    """The unknowns moved but the loss fell by less than rtol over ``stall_steps`` steps: the
    optimum to the precision of the forward model (its light solve stops at light_tol).  LM
    would keep shrinking its trust region without meeting the step-size criterion."""
    if not stall_steps or len(history) <= stall_steps:
        return False
    old, new = history[-1 - stall_steps], history[-1]
    return old["values"] != new["values"] and old["loss"] - new["loss"] <= rtol * max(
        new["loss"], 1e-30)


def _finish(st: _Setup, u, state, *, k: int, done: bool, stalled: bool, result_code,
            history: list, time_s: float, rtol: float, atol: float, max_steps: int,
            stall_steps: int) -> FitResult:
    name = _result_name(result_code)
    message = "" if name == "successful" else str(optx.RESULTS[result_code])
    if stalled and name == "successful":
        name = "loss_stalled"
        message = (f"stopped: the loss fell by less than rtol = {rtol} (relative) over the last "
                   f"{stall_steps} steps — the optimum to the forward model's precision")
    if not done and k >= max_steps:
        name = "nonlinear_max_steps_reached"
        message = (f"stopped after max_steps = {max_steps} steps without meeting rtol = {rtol}, "
                   f"atol = {atol}; raise max_steps or start closer")
    r, J, y = (np.asarray(a, np.float64) for a in st.stepper.final(u, state, st.data))
    mask = np.asarray(st.data[1]) > 0
    se, corr, cond, msgs, _ = _statistics(r[mask], J[mask], st.m, st.coords, np.asarray(u))
    for msg in msgs:
        warnings.warn(msg, IdentifiabilityWarning, stacklevel=3)
    raw = (y - st.flat_t) * np.sqrt(st.flat_w)
    images, off = {}, 0
    for n in st.names:
        size = st.tgt[n].size
        images[n] = y[off:off + size].reshape(st.tgt[n].shape).astype(np.float32)
        off += size
    return FitResult(
        paths=[c.path for c in st.coords],
        estimates=st.values(u),
        stderr={c.path: float(s) for c, s in zip(st.coords, se)},
        correlation=corr,
        initial={c.path: v for c, v in zip(st.coords, st.inits)},
        residual_rms=float(np.sqrt(np.sum(raw ** 2) / st.m)),
        loss=float(0.5 * np.sum(r * r)),
        iterations=k,
        time_s=time_s,
        result=name,
        message=message,
        warnings=msgs,
        history=history,
        images=images,
        targets={n: st.tgt[n].astype(np.float32) for n in st.names},
        condition=cond,
        settings=st.settings,
    )


def fit(scene: Scene, targets: Mapping[str, Any], unknowns, *, solver="lm", forward="sweep",
        resolution: int = 32, directions: int = 3, downsample: int = 1, supersample: int = 2,
        light_tol: float = 1e-5, weights: Mapping[str, Any] | None = None,
        loss: str = "linear", loss_scale: float = 0.05, rtol: float = 1e-4,
        atol: float = 1e-4, max_steps: int = 50, stall_steps: int = 3, dtype=None,
        devices: int = 1, checkpoint: str | os.PathLike | None = None, resume: bool = False,
        progress: bool | None = None, callback: Callable[[dict], None] | None = None,
        ) -> FitResult:
    """Fit the unknowns of ``scene`` to target images.

    targets: {camera name: (H, W) image}, one or several views, either at the scene camera's
    resolution or already reduced by ``downsample``.  unknowns: dotted parameter paths
    (``fog.scattering``, ``fog.absorption``, ``shape.<name>.albedo``; ``fog.g``,
    ``sun.irradiance``, ``sky.radiance`` as nuisance parameters), as a list, a dict
    {path: init | (init, lower, upper) | None} or :class:`Unknown` objects.

    solver: "lm" (Levenberg–Marquardt, default), "gauss-newton", "bfgs" or an optimistix
    least-squares solver / minimiser.  forward: "sweep" (``Renderer`` with ``SweepSolver(M=
    directions, tol=light_tol, devices=devices)`` at ``resolution``), "splat", or any object
    with ``.params()``, ``__call__(params)`` → images, ``.scene`` and ``.cameras``.
    downsample: render every camera at 1/k of its width and height (the target is box-averaged
    to match: a reduced pixel's footprint is k×k full pixels).  weights: {camera: (H, W)}
    per-pixel weights ≥ 0 (a boolean mask works); the residual is √w·(model − target) /
    RMS(target).  loss: "linear" (least squares) or a robust "huber", "soft_l1", "cauchy" with
    threshold ``loss_scale`` in units of the target's RMS.  rtol, atol: optimistix' termination
    on the unconstrained unknowns and the residuals; besides, the fit stops ("loss_stalled",
    counted as converged) when the unknowns moved but the loss fell by less than rtol over
    ``stall_steps`` steps (0: never).  devices: JAX devices that share each light solve
    (``SweepSolver(devices=...)``; the same estimates as on one).
    checkpoint: a file written (atomically) after every step;
    ``resume=True`` continues from it and reaches the same answer as an uninterrupted fit.
    progress: a line per step on stderr (default: when stderr is a terminal).
    callback(entry): called after every step with that step's history entry.
    See :func:`fit_batch` for many target sets at once.
    """
    t_start = time.perf_counter()
    st = _setup(scene, targets, unknowns, solver=solver, forward=forward,
                resolution=resolution, directions=directions, downsample=downsample,
                supersample=supersample, light_tol=light_tol, weights=weights, loss=loss,
                loss_scale=loss_scale, rtol=rtol, atol=atol, max_steps=max_steps,
                stall_steps=stall_steps, dtype=dtype, devices=devices)
    stepper, data = st.stepper, st.data
    state = stepper.init(st.u0, data)
    u = st.u0
    history: list[dict] = []
    k0, elapsed0 = 0, 0.0
    ckpt = Path(checkpoint) if checkpoint is not None else None
    if resume:
        if ckpt is None:
            raise DifffogError("resume=True needs checkpoint=PATH (the file a killed fit wrote)")
        u, state, k0, history, elapsed0 = _load_checkpoint(ckpt, st.u0, state, st.fingerprint)
    progress = sys.stderr.isatty() if progress is None else progress
    bar = None
    if progress:
        from tqdm import tqdm

        bar = tqdm(total=max_steps, initial=k0, desc="fit", unit="step", file=sys.stderr,
                   leave=True)
    k = k0
    done = False
    stalled = False
    result_code = optx.RESULTS.successful
    if k0 > 0:
        done_arr, result_code = stepper.terminate(u, state, data)
        done = bool(done_arr)
    t_loop = time.perf_counter()
    while not done and k < max_steps:
        u, state, aux = stepper.step(u, state, data)
        done_arr, result_code = stepper.terminate(u, state, data)
        done = bool(done_arr)
        k += 1
        accepted = None
        if hasattr(state, "num_accepted_steps"):
            accepted = int(state.num_accepted_steps)
        # the solver's aux lags one step behind y; its state holds the aux of y itself
        entry = {"step": k, "values": st.values(u), "loss": float(getattr(state, "aux", aux)),
                 "accepted_steps": accepted,
                 "time_s": round(elapsed0 + time.perf_counter() - t_loop, 3)}
        history.append(entry)
        if not np.all(np.isfinite(np.asarray(u))) or not math.isfinite(entry["loss"]):
            result_code = optx.RESULTS.nonfinite
            done = True
        if not done and _stalled(history, stall_steps, rtol):
            stalled = done = True
        if ckpt is not None:
            _save_checkpoint(ckpt, u, state, k, history, st.fingerprint, entry["time_s"])
        if bar is not None:
            bar.update(1)
            bar.set_postfix_str(f"loss {entry['loss']:.3e} " + " ".join(
                f"{p.split('.')[-1]}={v:.4g}" for p, v in entry["values"].items()))
        if callback is not None:
            callback(entry)
    if bar is not None:
        bar.close()
    return _finish(st, u, state, k=k, done=done, stalled=stalled, result_code=result_code,
                   history=history, time_s=elapsed0 + time.perf_counter() - t_start, rtol=rtol,
                   atol=atol, max_steps=max_steps, stall_steps=stall_steps)


# the settings fit_batch passes through, with fit()'s own defaults (read from its signature)
_SETUP_DEFAULTS = {k: inspect.signature(fit).parameters[k].default
                   for k in ("solver", "resolution", "directions", "downsample", "supersample",
                             "light_tol", "weights", "loss", "loss_scale", "dtype")}


def fit_batch(scene: Scene, targets: Sequence[Mapping[str, Any]], unknowns, *,
              devices: int = 1, forward="sweep", max_steps: int = 50, rtol: float = 1e-4,
              atol: float = 1e-4, stall_steps: int = 3, progress: bool | None = None,
              **kwargs) -> list[FitResult]:
    """Fit the same unknowns to many target sets at once (a parameter study, a time series,
    a set of images): one forward model and one compiled step, ``vmap``-ed over the fits and
    split over ``devices`` JAX devices (``shard_map``, no communication: each device steps its
    share of the fits).

    targets: a list of {camera: image} dicts, all with the same cameras; the other keyword
    arguments are :func:`fit`'s (except checkpoint/resume/callback).  All fits step together;
    a fit that has converged (or stalled, or failed) is frozen while the others go on, so every
    result equals what :func:`fit` returns for that target set.  On a CPU, N host devices need
    ``XLA_FLAGS=--xla_force_host_platform_device_count=N`` before JAX is imported (the CLI sets
    it for ``--devices``).
    """
    from ._batch import batch_devices, map_batch

    for bad in ("checkpoint", "resume", "callback"):
        if bad in kwargs:
            raise DifffogError(f"fit_batch: {bad} is not supported; run fit() per target set "
                               f"for checkpoints and callbacks")
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
    if not isinstance(devices, (int, np.integer)) or devices < 1:
        raise DifffogError(f"devices must be a positive integer, got {devices!r}")
    if devices > 1:
        batch_devices(devices)  # a clear error when there are not enough devices
    t_start = time.perf_counter()
    setups = []
    for t in targets:  # the first builds the forward model, the others reuse it
        st = _setup(scene, t, unknowns, forward=forward, max_steps=max_steps, rtol=rtol,
                    atol=atol, stall_steps=stall_steps, devices=1,
                    **{**_SETUP_DEFAULTS, **kwargs})
        forward = st.fwd
        setups.append(st)
    stepper = setups[0].stepper
    states = [stepper.init(s.u0, s.data) for s in setups]
    static = eqx.partition(states[0], eqx.is_array)[1]
    stack = lambda xs: jax.tree.map(lambda *a: jnp.stack(a), *xs)  # noqa: E731
    x = stack([(s.u0, eqx.partition(q, eqx.is_array)[0], s.data) for s, q in zip(setups, states)])

    def one(xi):
        u, dyn, data = xi
        u2, state2, _ = stepper._step_impl(u, eqx.combine(dyn, static), data)
        done, code = stepper._term_impl(u2, state2, data)
        return u2, eqx.partition(state2, eqx.is_array)[0], done, code

    B = len(setups)

    def bstep(xb):  # every device steps its share of the fits (no communication)
        return map_batch(one, xb, devices)

    k = np.zeros(B, int)
    done = np.zeros(B, bool)
    stalled = np.zeros(B, bool)
    codes = [optx.RESULTS.successful] * B
    histories: list[list[dict]] = [[] for _ in range(B)]
    progress = sys.stderr.isatty() if progress is None else progress
    bar = None
    if progress:
        from tqdm import tqdm

        bar = tqdm(total=B, desc=f"fit x{B}", unit="fit", file=sys.stderr, leave=True)
    t_loop = time.perf_counter()
    step = 0
    while not done.all() and step < max_steps:
        u2, dyn2, done2, code2 = bstep(x)
        step += 1
        live = ~done
        keep = jnp.asarray(done)
        x = (jax.tree.map(lambda a, b: jnp.where(keep.reshape((-1,) + (1,) * (a.ndim - 1)), a, b),
                          (x[0], x[1]), (u2, dyn2)) + (x[2],))
        done2, u_np = np.asarray(done2), np.asarray(x[0])
        now = round(time.perf_counter() - t_loop, 3)
        for i in np.flatnonzero(live):
            k[i] += 1
            state_i = eqx.combine(jax.tree.map(lambda a: a[i], x[1]), static)
            codes[i] = jax.tree.map(lambda a: a[i], code2)
            entry = {"step": int(k[i]), "values": setups[i].values(u_np[i]),
                     "loss": float(getattr(state_i, "aux", np.nan)),
                     "accepted_steps": (int(state_i.num_accepted_steps)
                                        if hasattr(state_i, "num_accepted_steps") else None),
                     "time_s": now}
            histories[i].append(entry)
            if done2[i]:
                done[i] = True
            elif not np.all(np.isfinite(u_np[i])) or not math.isfinite(entry["loss"]):
                codes[i], done[i] = optx.RESULTS.nonfinite, True
            elif _stalled(histories[i], stall_steps, rtol):
                stalled[i] = done[i] = True
        if bar is not None:
            bar.n = int(done.sum())
            bar.set_postfix_str(f"step {step}")
            bar.refresh()
    if bar is not None:
        bar.close()
    elapsed = time.perf_counter() - t_start
    out = []
    for i, st in enumerate(setups):
        u_i = x[0][i]
        state_i = eqx.combine(jax.tree.map(lambda a: a[i], x[1]), static)
        res = _finish(st, u_i, state_i, k=int(k[i]), done=bool(done[i]),
                      stalled=bool(stalled[i]), result_code=codes[i], history=histories[i],
                      time_s=elapsed, rtol=rtol, atol=atol, max_steps=max_steps,
                      stall_steps=stall_steps)
        res.settings = dict(res.settings, devices=devices, batch=B)
        out.append(res)
    return out
