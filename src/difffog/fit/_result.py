"""What a fit returns: the estimates, their standard errors and correlation (Gauss–Newton
covariance at the optimum, mapped to physical units by the delta method), the result code and
the history."""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass, field

import numpy as np
import optimistix as optx

from ..scene._params import SUN_PATHS
from ._misfit import MISFIT_RATIO


class IdentifiabilityWarning(UserWarning):
    """The unknowns are not (well) determined by the given views: near-singular JᵀJ or a
    correlation above 0.99 between two estimates."""


@dataclass
class FitResult:
    """What a fit found and how sure it is.

    paths: the unknowns' dotted paths, in order.
    estimates, stderr, initial: {path: value} in physical units; stderr from the Gauss–Newton
        covariance s²(JᵀJ)⁻¹ at the optimum (s² the residual variance), NaN where JᵀJ is
        singular.  It covers the noise only, not the forward model's own error.
    correlation: (n, n) in the order of ``paths``.
    residual_rms: root mean square of the weighted image residual (radiance) over pixels with
        weight > 0.
    loss: ½Σr² of the normalised residual at the optimum.
    iterations: optimizer steps; time_s: wall time.
    result: optimistix' result name ("successful", "nonlinear_max_steps_reached", ...),
        "loss_stalled" (the loss stopped falling: converged to the forward model's precision)
        or "light_solve_failed" (the light solve at the estimate, or a tangent solve of its
        Jacobian, did not converge).
    message: what the result means, when it is not plain success.
    warnings: identifiability and accuracy warnings.
    history: one dict per step (step, values, loss, accepted_steps, light_result, time_s).
    images, targets: fitted and target images per camera (the forward model's resolution).
    condition: of the column-normalised J (√ of JᵀJ's).
    settings: the fit's settings (JSON-able).
    target_files: {camera: how its target file was read} (path, format, dtype, transfer,
        channel, ...; ``_images.load_target``) for the targets given as files.
    mask_files: {camera: path} for the weights given as files.
    model_error: {path: value}: the forward model's own discretization error in each estimate,
        from ``fit(model_error="refine")`` or the resolution ladder (``fit(ladder=...)``);
        empty without either.
    uncertainty: {path: value}: the total, one standard deviation: √(stderr² + model_error²)
        (the standard error alone without a model error).
    fitted: {path: value}: with ``model_error="refine"``, the best fit of the model at the
        fit's own resolution, the point ``images`` are rendered at; ``estimates`` are then that
        fit corrected to the finer model (the doubled lattice; for the sweep with M + 1) by
        Gauss–Newton steps on that model's images with the fit's Jacobian (``fit``'s
        ``refine_steps``).  Otherwise the estimates.
    ladder: one dict per level of the ladder (resolution, estimates, iterations, time_s,
        result); with ``model_error="refine"`` the fit and each finer model's linearized
        estimate (resolution, M where it changes, estimates; the correction's ``steps``, the
        renders its iteration took).
    model_error_parts: with ``model_error="refine"``, {path: {part: value}}: the correction's
        step taken as first order in the voxel size, × N/(N_f − N) ("lattice"); how far the
        estimate of a lattice between (1.5 N, the fit's M) lands from the line through the fit
        and the correction's first step ("lattice_between"); the change with M + 1 on the
        fit's own lattice ("directions"); where the correction's iteration stopped before its
        steps were small (``refine_steps`` reached), its last step ("refine_steps"); with the
        sun's angles as unknowns, how far the last round's
        rebuild at the estimated sun moved each estimate ("sun_rounds"); how far a relative
        brightness bias of ``fit``'s ``model_floor`` in one camera's images at a time moves it
        ("brightness", the model's brightness against independent truth, which no finer
        lattice reveals).  ``model_error`` is their root sum of squares.
        With a misfit (below), a "misfit" part: how far the residual that noise, the lattice
        and the floor do not explain can move each estimate (``fit/_misfit.py``).
    model_floor: the relative brightness bias behind the "brightness" part (0: none).
    at_bound: {path: {bound, upper_95}} for the unknowns a fit ran to their lower bound (a fog
        that does not absorb) and held there, fitting the others again (``fit/_bound.py``):
        the estimate is the bound, the standard error that of the joint linear model there,
        and the images allow the unknown up to ``upper_95`` (95%, one-sided).
    goodness_of_fit: with ``model_error="refine"``, {camera: {residual, noise, lattice, floor,
        expected, ratio, unexplained}}: the residual's RMS relative to the target's mean,
        against what the target's own noise, the model's lattice error in the images and the
        brightness floor explain (``expected``, their root sum of squares; ``ratio`` =
        residual / expected; ``unexplained`` the share of the residual's variance they do not
        explain).  A ratio above 2 warns (:class:`difffog.MisfitWarning`): something the fit
        holds fixed differs from the images.
    sun_rounds: with the sun's angles as unknowns, one dict per round of the fit (the sun the
        round's model was built at, its estimates, iterations, result): each round rebuilds
        the model at the previous round's sun, until the sun moves less than
        ``_driver.SUN_SETTLE_DEG``.
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
    target_files: dict = field(default_factory=dict)
    mask_files: dict = field(default_factory=dict)
    model_error: dict = field(default_factory=dict)
    uncertainty: dict = field(default_factory=dict)
    ladder: list = field(default_factory=list)
    fitted: dict = field(default_factory=dict)
    model_error_parts: dict = field(default_factory=dict)
    sun_rounds: list = field(default_factory=list)
    model_floor: float = 0.0
    goodness_of_fit: dict = field(default_factory=dict)
    at_bound: dict = field(default_factory=dict)

    @property
    def converged(self) -> bool:
        return self.result in ("successful", "loss_stalled")

    def relative_error(self, truth: Mapping[str, float]) -> dict[str, float]:
        """{path: (estimate − truth) / truth} (the sun's angles, and a truth of 0: estimate −
        truth, in the unknown's units)."""
        return {p: (self.estimates[p] - truth[p]) / (
            1.0 if p in SUN_PATHS or truth[p] == 0 else truth[p])
            for p in self.paths if p in truth}

    def summary(self, truth: Mapping[str, float] | None = None) -> str:
        w = max(len(p) for p in self.paths)
        model = bool(self.model_error)
        corrected = bool(self.fitted) and self.fitted != self.estimates
        head = f"{'unknown':<{w}}  {'initial':>10}  "
        if corrected:
            fit_n = "fit N=" + str(self.ladder[0]["resolution"])
            head += f"{fit_n:>10}  "
        head += f"{'estimate':>10}  {'std err':>9}"
        if model:
            head += f"  {'model err':>9}  {'total ±':>9}"
        if truth:
            head += f"  {'truth':>10}  {'error %':>8}"
        lines = [head, "-" * len(head)]
        for p in self.paths:
            s = f"{p:<{w}}  {self.initial[p]:>10.4g}  "
            if corrected:
                s += f"{self.fitted[p]:>10.4g}  "
            s += f"{self.estimates[p]:>10.4g}  {self.stderr[p]:>9.2g}"
            if model:
                s += f"  {self.model_error[p]:>9.2g}  {self.uncertainty[p]:>9.2g}"
            if truth and p in truth:
                if p in SUN_PATHS:  # an angle: off by degrees
                    s += f"  {truth[p]:>10.4g}  {self.estimates[p] - truth[p]:>+7.3f}°"
                elif truth[p] == 0:  # no relative error: the estimate itself, marked
                    s += f"  {truth[p]:>10.4g}  {self.estimates[p]:>+8.2g} (absolute)"
                else:
                    s += f"  {truth[p]:>10.4g}  {100 * (self.estimates[p] / truth[p] - 1):>+8.3f}"
            lines.append(s)
        if model:
            by = {"model error": [], "noise": []}
            for p in self.paths:
                if math.isfinite(self.model_error[p]) and math.isfinite(self.stderr[p]):
                    by["model error" if self.model_error[p] > self.stderr[p] else "noise"].append(p)
            if self.model_error_parts:
                source = "model error from " + "; ".join(level_label(lv) for lv in self.ladder[1:])
                if self.model_floor:
                    source += f"; a {self.model_floor:.2%} brightness floor"
            else:
                source = ("model error from resolution "
                          + " → ".join(str(lv["resolution"]) for lv in self.ladder))
            if any(by.values()):
                lines.append("uncertainty dominated by " + "; ".join(
                    f"{k}: {', '.join(v)}" for k, v in by.items() if v) + f" ({source})")
        if corrected:
            k = int(self.ladder[1].get("steps", 1))
            how = ("one Gauss–Newton step" if k == 1
                   else f"{k} Gauss–Newton steps (defect correction)")
            lines.append(f"estimate: the fit at {level_label(self.ladder[0])} corrected to "
                         f"{level_label(self.ladder[1])} by {how} on that "
                         f"model's images (the fitted images are at the "
                         f"{level_label(self.ladder[0])} fit)")
        lines.append(f"{self.result} after {self.iterations} steps in {self.time_s:.1f} s; "
                     f"residual RMS {self.residual_rms:.3g}")
        if self.goodness_of_fit:
            lines.append("residual / what noise, lattice and floor explain: " + ", ".join(
                f"{n} {c['residual']:.2%} / {c['expected']:.2%}"
                + (" (misfit)" if c["ratio"] > MISFIT_RATIO else "")
                for n, c in self.goodness_of_fit.items()))
        if self.sun_rounds:
            n = len(self.sun_rounds)
            lines.append("the sun: 1 round, on a model built at the starting sun" if n == 1 else
                         f"the sun: {n} rounds, each on a model built at the last estimated sun")
        for cam, f in self.target_files.items():
            lines.append(f"target {cam}: {f['path']} ({f['dtype']}, transfer {f['transfer']}, "
                         f"{f['channel']})")
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
            "stderr": _finite_or_none(self.stderr),
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
            "target_files": self.target_files,
            "mask_files": self.mask_files,
            "model_error": _finite_or_none(self.model_error),
            "uncertainty": _finite_or_none(self.uncertainty),
            "ladder": self.ladder,
            "fitted": self.fitted or self.estimates,
            "model_error_parts": self.model_error_parts,
            "sun_rounds": self.sun_rounds,
            "model_floor": self.model_floor,
            "goodness_of_fit": self.goodness_of_fit,
            "at_bound": self.at_bound,
        }


def level_label(level: Mapping) -> str:
    """A model of the ladder or the model error's checks in words: "N = 48, M = 4"."""
    return f"N = {level['resolution']}" + (f", M = {level['M']}" if "M" in level else "")


def _finite_or_none(d: Mapping[str, float]) -> dict:
    return {k: (None if not math.isfinite(v) else v) for k, v in d.items()}


def result_name(code) -> str:
    for name in ("successful", "nonlinear_max_steps_reached", "nonlinear_divergence",
                 "nonfinite", "singular", "breakdown", "stagnation", "max_steps_reached"):
        try:
            if bool(code == getattr(optx.RESULTS, name)):
                return name
        except AttributeError:
            continue
    return "failed"



def statistics(r: np.ndarray, J: np.ndarray, m: int, coords, u: np.ndarray):
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
