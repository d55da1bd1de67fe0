"""What a fit estimates: the unknowns (dotted parameter paths with bounds) and the
unconstrained coordinates the optimizer moves: log for coefficients, light intensities and
exposures, logit for albedo, a scaled logit (or log-logit over wide ranges) for bounded values.

Besides the scene's parameters, the images' gains: ``exposure`` multiplies every rendered image
and ``camera.<name>.exposure`` one camera's, before the residual (a photograph's scale is
unknown).  A gain is the same as scaling every light source (sun, sky, emission), so it is not
determined together with all of them; the fit's identifiability warning then says so."""

from __future__ import annotations

import dataclasses
import difflib
import math
from collections.abc import Mapping
from dataclasses import dataclass

import jax
import jax.numpy as jnp

from .._errors import DifffogError, SceneError
from ..scene._description import Scene
from ..scene._params import SUN_PATHS, Params, get_param


@dataclass(frozen=True)
class Unknown:
    """One parameter to fit: a dotted path (see :func:`difffog.param_paths`), its initial value
    (None: the scene's value) and optional bounds (None: the natural ones: (0, ∞) for
    coefficients and lights, (0, 1) for albedo, (−0.99, 0.99) for ``fog.g``)."""

    path: str
    init: float | None = None
    lower: float | None = None
    upper: float | None = None


def exposure_camera(path: str) -> str | None:
    """The camera an exposure unknown scales: "" for ``exposure`` (every camera), the name for
    ``camera.<name>.exposure``; None for a parameter of the scene."""
    if path == "exposure":
        return ""
    head, tail = "camera.", ".exposure"
    if path.startswith(head) and path.endswith(tail) and len(path) > len(head) + len(tail):
        return path[len(head):-len(tail)]
    return None


def _kind(path: str) -> str:
    if path.endswith(".albedo"):
        return "albedo"
    if path == "fog.g":
        return "g"
    if path in SUN_PATHS:
        return SUN_PATHS[path][1]  # the scene's Sun attribute: "zenith_deg", "azimuth_deg"
    return "positive"


#: the sun's angles in degrees: a sun above the horizon, an azimuth free to turn either way
_NATURAL = {"albedo": (0.0, 1.0), "g": (-0.99, 0.99), "positive": (0.0, math.inf),
            "zenith_deg": (0.0, 90.0), "azimuth_deg": (-360.0, 360.0)}



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


def _scene_value(scene: Scene, base: Params, path: str) -> float | None:
    """The scene's value of a parameter path (None for an exposure: the scene has none), or a
    one-line error naming the closest path."""
    cam = exposure_camera(path)
    if cam is not None:
        names = [c.name for c in scene.cameras]
        if cam and cam not in names:
            raise DifffogError(f"unknown '{path}': camera '{cam}' has no target (the targets' "
                               f"cameras: {', '.join(names)})")
        return None
    if path == "fog.density":
        raise DifffogError("unknown 'fog.density' is a grid, not a scalar: fit it with "
                           "difffog.fit_density(scene, targets) (the command line: difffog fit "
                           "SCENE --unknown fog.density)")
    try:
        return float(get_param(base, scene, path))
    except SceneError as e:
        gains = ["exposure"] + [f"camera.{c.name}.exposure" for c in scene.cameras]
        close = difflib.get_close_matches(path, gains, n=1)
        hint = f" Did you mean '{close[0]}'?" if close and "Did you mean" not in str(e) else ""
        raise SceneError(f"{e}; and the images' gains: {', '.join(gains)}.{hint}") from None


def coordinates(scene: Scene, base: Params, unknowns: list[Unknown]):
    """(Coordinate per unknown, initial physical value per unknown), checked: the path names a
    parameter of ``scene`` or an exposure of one of its cameras (one-line error with the
    closest path otherwise), the bounds are inside the natural ones, the initial value inside
    the bounds.  An exposure given without an initial value gets None: the fit starts it from
    the targets (``_driver._exposure_starts``)."""
    coords, inits = [], []
    for u in unknowns:
        scene_value = _scene_value(scene, base, u.path)
        kind = _kind(u.path)
        nlo, nhi = _NATURAL[kind]
        lo = nlo if u.lower is None else float(u.lower)
        hi = nhi if u.upper is None else float(u.upper)
        if lo < nlo or hi > nhi or not lo < hi:
            raise DifffogError(
                f"unknown '{u.path}': bounds [{lo}, {hi}] must satisfy {nlo} <= lower < upper "
                f"<= {nhi}")
        coords.append(Coordinate(u.path, lo, hi))
        if u.init is None and scene_value is None:
            inits.append(None)
            continue
        v0 = scene_value if u.init is None else float(u.init)
        if not (lo < v0 < hi) or not math.isfinite(v0):
            src = "the scene's value" if u.init is None else "the initial value"
            raise DifffogError(
                f"unknown '{u.path}': {src} {v0:g} lies outside the open interval ({lo:g}, "
                f"{hi:g}); give an initial value inside the bounds, e.g. {u.path}="
                f"{(lo + 1.0) if math.isinf(hi) else 0.5 * (lo + hi):g}")
        inits.append(v0)
    return coords, inits


def within_bounds(u: Unknown, v: float) -> float:
    """``v`` moved just inside ``u``'s bounds (the natural ones where not given) if it lies on
    or beyond one: an estimate can round onto a bound (an albedo of 1.0 in float32), which is
    not a valid start."""
    nlo, nhi = _NATURAL[_kind(u.path)]
    lo = nlo if u.lower is None else float(u.lower)
    hi = nhi if u.upper is None else float(u.upper)
    if lo < v < hi:
        return v
    eps = 1e-3 * ((hi - lo) if math.isfinite(hi) else max(abs(lo), 1.0))
    return min(max(v, lo + eps), hi - eps) if math.isfinite(hi) else max(v, lo + eps)
