"""What a fit estimates: the unknowns (dotted parameter paths with bounds) and the
unconstrained coordinates the optimizer moves: log for coefficients and light intensities,
logit for albedo, a scaled logit (or log-logit over wide ranges) for bounded values."""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Mapping
from dataclasses import dataclass

import jax
import jax.numpy as jnp

from .._errors import DifffogError
from ..scene._description import Scene
from ..scene._params import Params, get_param


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
class Coordinate:
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


def as_unknowns(unknowns) -> list[Unknown]:
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


def coordinates(scene: Scene, base: Params, unknowns: list[Unknown]):
    """(Coordinate per unknown, initial physical value per unknown), checked: the path names a
    parameter of ``scene`` (one-line error with the closest path otherwise), the bounds are
    inside the natural ones, the initial value inside the bounds."""
    coords, inits = [], []
    for u in unknowns:
        scene_value = float(get_param(base, scene, u.path))  # raises for an unknown path
        kind = _kind(u.path)
        nlo, nhi = _NATURAL[kind]
        lo = nlo if u.lower is None else float(u.lower)
        hi = nhi if u.upper is None else float(u.upper)
        if lo < nlo or hi > nhi or not lo < hi:
            raise DifffogError(
                f"unknown '{u.path}': bounds [{lo}, {hi}] must satisfy {nlo} <= lower < upper "
                f"<= {nhi}")
        v0 = scene_value if u.init is None else float(u.init)
        if not (lo < v0 < hi) or not math.isfinite(v0):
            src = "the scene's value" if u.init is None else "the initial value"
            raise DifffogError(
                f"unknown '{u.path}': {src} {v0:g} lies outside the open interval ({lo:g}, "
                f"{hi:g}); give an initial value inside the bounds, e.g. {u.path}="
                f"{(lo + 1.0) if math.isinf(hi) else 0.5 * (lo + hi):g}")
        coords.append(Coordinate(u.path, lo, hi))
        inits.append(v0)
    return coords, inits
