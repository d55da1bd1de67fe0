"""Issue 14's thick cube by an independent method: a float64 Monte Carlo random walk.

The cube (``difffog.study._semi_infinite.thick_cube``: the unit cube of fog with γ = 0.001, a
ball of albedo 0.6 inside, a sun at 30° of irradiance 2, a sky of 0.2 above the horizon, a
camera looking straight down at the middle 0.8 × 0.8 of the top face) has no closed-form image:
the semi-infinite medium's value (0.773) is its limit only where light cannot reach the cube's
sides, its bottom or the ball.  This script estimates the camera's mean radiance with a
method that shares nothing with the lattice: camera paths enter at random points of the view,
fly exponential free paths through the fog, scatter isotropically (the weight times the
single-scattering albedo), reflect off the ball (Lambertian, weight × 0.6) and at every
collision add the sun's and the sky's light by next-event estimation (the sun's beam
attenuated to the cube's face, one sky direction drawn uniformly over the upper hemisphere;
the ball shadows both).  Russian roulette below a weight of 0.05.  Everything in float64,
which matters: Mitsuba 3's float32 images of the same cube read 0.7286 at ζ = 100 (this
script: 0.7271 ± 0.0007) but 0.785 at ζ = 1000, and a wide slab of ζ = 1000, which can
return no more than the half-space's 0.773, reads 0.785 too: its rays start a
float32 ray epsilon (~2·10⁻⁴ here) from where they should, a fifth of a mean free path at
ζ = 1000 (docs/validation.md, "The thick cube against independent truth").

Prints one JSON line per ζ (mean, standard error from the spread of ``--reps`` independent
runs and from the paths, paths, seconds).  Checked against Mitsuba 3 at ζ = 10 (0.4866 ±
0.0007 against 0.4880 ± 0.0005) and ζ = 100 (0.7271 ± 0.0007 against 0.7286 ± 0.0003); the
wide slab (``--slab 5``) at ζ = 100 reads 0.7577 ± 0.0011 here (4 × 10⁵ paths) and 0.7610 ±
0.0008 in Mitsuba: its float32 bias is +0.4% ± 0.2% there.

    python benchmarks/thick_cube_mc.py                       # ζ 10 100 1000 (~4 min on 2 cores)
    python benchmarks/thick_cube_mc.py --zetas 10000 --paths 10000 --reps 1   # ~22 min
    python benchmarks/thick_cube_mc.py --zetas 100 --slab 5 --reps 4           # ~1 min
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
import time

import numpy as np

from difffog.study._semi_infinite import thick_cube

ROULETTE = 0.05


@dataclasses.dataclass(frozen=True)
class Setting:
    """What the walk needs of ``thick_cube(zeta)`` (read from the scene, not repeated here): the
    fog's box (lo, hi), its ζ and γ, the ball (None: a slab without it), the sun, the sky and
    the camera's view window on the top face."""

    lo: np.ndarray
    hi: np.ndarray
    zeta: float
    absorption: float
    ball: object  # the scene's Sphere, or None
    to_sun: np.ndarray
    irradiance: float
    sky: float
    view_lo: np.ndarray  # (x, y) corner of the camera's window
    view_size: np.ndarray


def setting(zeta: float, slab: float | None = None) -> Setting:
    """The cube (or with ``slab`` = W the slab [0.5 − W, 0.5 + W]² × [0, 1] of the same fog
    without the ball: what Mitsuba's float32 check renders)."""
    sc = thick_cube(zeta)
    cam = sc.cameras[0]
    lo, hi = np.array(sc.domain.min, float), np.array(sc.domain.max, float)
    if slab is not None:
        lo[:2], hi[:2] = 0.5 - slab, 0.5 + slab
    return Setting(lo=lo, hi=hi, zeta=sc.fog.scattering, absorption=sc.fog.absorption,
                   ball=None if slab is not None else sc.shapes[0], to_sun=sc.sun.direction,
                   irradiance=sc.sun.irradiance, sky=sc.sky.radiance,
                   view_lo=np.array(cam.position[:2]) - 0.5 * np.array(cam.extent),
                   view_size=np.array(cam.extent, float))


def _exit_distance(st: Setting, x: np.ndarray, d: np.ndarray) -> np.ndarray:
    """Distance from ``x`` (inside the fog's box) along ``d`` to its boundary."""
    with np.errstate(divide="ignore", invalid="ignore"):
        t = np.where(d > 0, (st.hi - x) / d, np.where(d < 0, (st.lo - x) / d, np.inf))
    return t.min(axis=1)


def _ball_distance(st: Setting, x: np.ndarray, d: np.ndarray) -> np.ndarray:
    """Distance along ``d`` to the ball (inf where the ray misses it); ``x`` outside it."""
    if st.ball is None:
        return np.full(x.shape[0], np.inf)
    oc = x - np.asarray(st.ball.center)
    b = np.einsum("ij,ij->i", oc, d)
    disc = b * b - (np.einsum("ij,ij->i", oc, oc) - st.ball.radius ** 2)
    t = -b - np.sqrt(np.maximum(disc, 0.0))
    return np.where((disc > 0) & (t > 0), t, np.inf)


def _free(st: Setting, x: np.ndarray, d: np.ndarray) -> np.ndarray:
    """Distance out of the fog along ``d``, inf where the ball is in the way."""
    t = _exit_distance(st, x, d)
    return np.where(_ball_distance(st, x, d) < t, np.inf, t)


def _sphere_directions(n: int, rng) -> np.ndarray:
    mu, phi = 2.0 * rng.random(n) - 1.0, 2.0 * np.pi * rng.random(n)
    s = np.sqrt(1.0 - mu * mu)
    return np.stack([s * np.cos(phi), s * np.sin(phi), mu], 1)


def _lambert_directions(normal: np.ndarray, rng) -> np.ndarray:
    n = normal.shape[0]
    u1, u2 = rng.random(n), rng.random(n)
    r, phi = np.sqrt(u1), 2.0 * np.pi * u2
    helper = np.where(np.abs(normal[:, :1]) > 0.9, [[0.0, 1.0, 0.0]], [[1.0, 0.0, 0.0]])
    t = np.cross(normal, helper)
    t /= np.linalg.norm(t, axis=1, keepdims=True)
    b = np.cross(normal, t)
    return (r * np.cos(phi))[:, None] * t + (r * np.sin(phi))[:, None] * b \
        + np.sqrt(1.0 - u1)[:, None] * normal


def camera_paths(st: Setting, n: int, seed: int) -> np.ndarray:
    """(n,) radiance estimates of camera paths through the camera's window on the top face."""
    rng = np.random.default_rng(seed)
    sigma_t = st.zeta + st.absorption
    ssa = st.zeta / sigma_t
    xy = st.view_lo + st.view_size * rng.random((n, 2))
    x = np.concatenate([xy, np.full((n, 1), st.hi[2])], 1)
    d = np.tile([0.0, 0.0, -1.0], (n, 1))
    w, out = np.ones(n), np.zeros(n)
    live = np.arange(n)
    while live.size:
        xs, ds = x[live], d[live]
        t = -np.log(rng.random(live.size)) / sigma_t
        t_exit, t_ball = _exit_distance(st, xs, ds), _ball_distance(st, xs, ds)
        ball = (t_ball < t_exit) & (t_ball < t)
        escape = (t_exit <= t) & ~ball
        coll = ~escape & ~ball
        i = live[coll]
        if i.size:  # a collision: the sun's and the sky's light scattered here, then scatter
            p = xs[coll] + t[coll, None] * ds[coll]
            x[i] = p
            est = st.irradiance * np.exp(
                -sigma_t * _free(st, p, np.broadcast_to(st.to_sun, p.shape))) / (4.0 * np.pi)
            mu, phi = rng.random(i.size), 2.0 * np.pi * rng.random(i.size)
            s = np.sqrt(1.0 - mu * mu)
            to_sky = np.stack([s * np.cos(phi), s * np.sin(phi), mu], 1)  # pdf 1/(2π)
            est += st.sky * np.exp(-sigma_t * _free(st, p, to_sky)) / 2.0  # (1/4π)·2π
            out[i] += w[i] * ssa * est
            w[i] *= ssa
            d[i] = _sphere_directions(i.size, rng)
        j = live[ball]
        if j.size:  # the ball (≥ 0.3·ζ mean free paths deep: no light of its own reaches it)
            centre, radius = np.asarray(st.ball.center), st.ball.radius
            p = xs[ball] + t_ball[ball, None] * ds[ball]
            normal = (p - centre) / radius
            x[j] = centre + normal * radius * (1.0 + 1e-12)
            d[j] = _lambert_directions(normal, rng)
            w[j] *= st.ball.albedo
        live = live[~escape]
        small = w[live] < ROULETTE
        if small.any():
            k = live[small]
            keep = rng.random(k.size) < w[k] / ROULETTE
            w[k[keep]] = ROULETTE
            live = np.concatenate([live[~small], k[keep]])
    return out


def estimate(zeta: float, paths: int, reps: int, slab: float | None = None) -> dict:
    t0 = time.perf_counter()
    st = setting(zeta, slab)
    means, path_se = [], []
    for r in range(reps):
        v = camera_paths(st, paths, seed=r)
        means.append(float(v.mean()))
        path_se.append(float(v.std() / math.sqrt(paths)))
    stderr_paths = math.sqrt(sum(s * s for s in path_se)) / reps
    stderr_reps = float(np.std(means, ddof=1) / math.sqrt(reps)) if reps > 1 else math.nan
    return {"zeta": zeta, "mean": round(float(np.mean(means)), 5),
            "stderr": round(max(stderr_paths, 0.0 if math.isnan(stderr_reps) else stderr_reps), 5),
            "stderr_paths": round(stderr_paths, 5), "stderr_reps": round(stderr_reps, 5),
            "paths": paths * reps, "time_s": round(time.perf_counter() - t0, 1)}


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--zetas", nargs="+", type=float, default=[10.0, 100.0, 1000.0])
    ap.add_argument("--paths", type=int, default=100_000, help="camera paths per run")
    ap.add_argument("--reps", type=int, default=2, help="independent runs (seeds 0, 1, ...)")
    ap.add_argument("--slab", type=float, default=None,
                    help="half-width W of a slab of the same fog without the ball instead")
    a = ap.parse_args(argv)
    for z in a.zetas:
        print(json.dumps({**estimate(z, a.paths, a.reps, a.slab), "slab": a.slab}), flush=True)


if __name__ == "__main__":
    main()
