"""Thick slabs as cameras see them: R, T and the emergent radiance per angle against exact.

The slab rows of ``slab_balance.py`` read R and T by a formula (``slab_reflectance``: each
node's source constant or linear over its cell, the sun's single scattering from the node's
mean), which is not how the cameras read fog (the march blends the nodes' extrapolations,
drops a node's slope towards a neighbour without fog and scatters the sun along its own
profile).  Here the slab is a scene: a periodic-xy domain with fog in z ∈ [0, 1] (vertical
optical depth τ, albedo a), a sky of radiance 1 or a sun of irradiance 1, and orthographic
cameras above and below at the Gauss–Legendre μ of ``--mu`` points; each image's mean is the
emergent radiance I(μ), and R, T are 2π Σ w μ I / incident (+ the sun's direct beam in T).

The exact I(μ) is ``difffog.study._slab.exact_slab_radiance`` (the slab's integral equation
for the collided mean intensity on cells of 1/64 mean free path, solved directly; the single
scattering in closed form); its R and T are checked against the adding-doubling table
(``difffog/data/references/slab_adding_doubling.csv``) in each row.

    python benchmarks/slab_cameras.py                       # τ 16 64, a .9 .99 .999, N 32, M 2
    python benchmarks/slab_cameras.py --m 2 3 --scheme linear --first-collision deposit
    python benchmarks/slab_cameras.py --quick --out /tmp/sc  # τ 4, a 0.9, diffuse, N 16

Writes ``slab_cameras.md`` (``--name``) to ``--out`` (default ``benchmarks/results``).
"""

from __future__ import annotations

import argparse
import csv
import math
import time
import warnings
from pathlib import Path

import numpy as np
import _common as C
from difffog.study._slab import (exact_slab_collided, exact_slab_radiance, exact_slab_rt,
                                 isotropic_slab_rows)

LIGHTS = ("diffuse", "coll0", "coll60")


def flux(I, mus, wts):
    return 2 * math.pi * float(np.sum(wts * mus * I))


def slab_scene(tau, albedo, light, mus, pad=0.25, width=0.25, pixels=4):
    from difffog.scene._description import Camera, Domain, Fog, Scene, Sky, Sun

    cams = []
    for k, mu in enumerate(mus):
        s = math.sqrt(max(0.0, 1 - mu * mu))
        for name, sign, z0 in (("top", 1.0, 1.0), ("bottom", -1.0, 0.0)):
            c = (width / 2, width / 2, z0)
            pos = (c[0] + 2.0 * s, c[1], z0 + sign * 2.0 * mu)
            cams.append(Camera(f"{name}{k}", "orthographic", pos, c, up=(0, 1, 0),
                               resolution=(pixels, pixels), extent=(width / 2, width / 2)))
    sun = None if light == "diffuse" else Sun(1.0, float(light[4:]), 0.0)
    return Scene(
        title=f"slab τ={tau} a={albedo} {light}",
        domain=Domain((0, 0, -pad), (width, width, 1 + pad), "periodic-xy"),
        fog=Fog(scattering=albedo * tau, absorption=(1 - albedo) * tau,
                region=((0, 0, 0), (width, width, 1))),
        sky=Sky(1.0) if light == "diffuse" else None, sun=sun, cameras=tuple(cams))


def camera_slab(tau, albedo, light, mus, N, M, scheme, first_collision, tol):
    import difffog as df

    pad = 0.25
    # 8 nodes across (the slab is laterally homogeneous): a lattice of 8 × 8 × 1.5 N
    scene = slab_scene(tau, albedo, light, mus, pad=pad, width=8.0 / N)
    model = df.forward_model(scene, "sweep", accuracy=None, resolution=int(round(N * (1 + 2 * pad))),
                             M=M, tol=tol, max_iterations=20000, supersample=1, scheme=scheme,
                             first_collision=first_collision)
    t0 = time.perf_counter()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        out = df.render(model)
    secs = time.perf_counter() - t0
    top = np.array([float(np.asarray(out.images[f"top{k}"], np.float64).mean())
                    for k in range(len(mus))])
    bot = np.array([float(np.asarray(out.images[f"bottom{k}"], np.float64).mean())
                    for k in range(len(mus))])
    return top, bot, secs, model, out.light


def collided_profile(tau, albedo, light, z):
    """The exact slab's collided fluence (4π·J) at heights z ∈ (0, 1) (z = 1 the top)."""
    t, J = exact_slab_collided(tau, albedo, light)
    return 4 * math.pi * np.interp((1 - np.asarray(z)) * tau, 0.5 * (t[1:] + t[:-1]), J)


def fluence_ratios(model, light_field, tau, albedo, light):
    """The lattice's collided fluence Λ over the exact one at the top fog node, the bottom one
    and mid-depth (sunlit rows: with a sky the lattice's Λ carries the uncollided sky too)."""
    lam = np.asarray(light_field.fluence, np.float64)[0, 0]
    lam = lam if lam.ndim == 1 else lam[:, 0]
    z = model.lattice.origin[2] + (np.arange(lam.shape[0]) + 0.5) * model.lattice.h
    fog = np.nonzero((z > 0) & (z < 1))[0]
    idx = [fog[-1], fog[len(fog) // 2], fog[0]]
    return lam[idx] / collided_profile(tau, albedo, light, z[idx])


def _t_cell(r):
    """T's error, or where the exact slab lets (almost) nothing through, both values."""
    if r["T_exact"] < 1e-6:
        return f"{r['T']:.1e} (exact {r['T_exact']:.1e})"
    return f"{100 * r['err_T']:+.2f}%"


def reading_from_exact_nodes(tau, albedo, light, N, mus):
    """How the cameras' reading of a face alone errs: the exact collided source (a·J,
    ``exact_slab_collided``) sampled at the N nodes, read back as the march reads it
    (between nodes the blend of their linear extrapolations, central slopes; from the face
    node to the face its value, "const", or its one-sided slope extrapolated, "slope") and
    integrated towards the top at each μ, against the exact source's emergent radiance.
    Returns {"const": errors, "slope": errors}, relative, per μ."""
    t, J = exact_slab_collided(tau, albedo, light)
    src = albedo * J
    d = t[1] - t[0]
    mid = 0.5 * (t[1:] + t[:-1])
    h = tau / N
    nodes = (np.arange(N) + 0.5) * h
    sn = np.interp(nodes, mid, src)
    sl = np.r_[sn[1] - sn[0], 0.5 * (sn[2:] - sn[:-2]), sn[-1] - sn[-2]]
    keep = mid < (N - 1) * h
    x = mid[keep]

    def emerge(S):
        return np.array([(S * np.exp(-x / mu) * -np.expm1(-d / mu)).sum() for mu in mus])

    exact = emerge(src[keep])
    u = x / h - 0.5
    k = np.clip(np.floor(u).astype(int), 0, N - 2)
    w = u - k
    inner = (1 - w) * (sn[k] + sl[k] * w) + w * (sn[k + 1] + sl[k + 1] * (w - 1))
    out = {}
    for face, face_val in (("const", sn[0] + 0 * u), ("slope", sn[0] + sl[0] * u)):
        out[face] = emerge(np.where(u < 0, face_val, inner)) / exact - 1
    return out


def table_rows(taus, albedos, lights):
    ref = isotropic_slab_rows()
    return [(t, a, li, *ref[(t, a, li)]) for t in taus for a in albedos for li in lights
            if (t, a, li) in ref]


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--taus", type=float, nargs="+", default=[16.0, 64.0])
    ap.add_argument("--albedos", type=float, nargs="+", default=[0.9, 0.99, 0.999])
    ap.add_argument("--lights", nargs="+", default=list(LIGHTS), choices=LIGHTS)
    ap.add_argument("--n", type=int, nargs="+", default=[32])
    ap.add_argument("--m", type=int, nargs="+", default=[2])
    ap.add_argument("--mu", type=int, default=6, help="Gauss–Legendre μ points (cameras per side)")
    ap.add_argument("--scheme", default="auto", choices=["auto", "step", "linear", "substep"])
    ap.add_argument("--first-collision", default="beam", choices=["beam", "deposit"])
    ap.add_argument("--tol", type=float, default=1e-8)
    ap.add_argument("--f32", action="store_true", help="float32 (default float64)")
    ap.add_argument("--quick", action="store_true")
    ap.add_argument("--reading", action="store_true",
                    help="only the face reading from the exact source at the nodes (numpy)")
    ap.add_argument("--out", type=Path, default=C.RESULTS)
    ap.add_argument("--name", default="slab_cameras")
    a = ap.parse_args(argv)
    if a.quick:
        a.taus, a.albedos, a.lights, a.n, a.m = [4.0], [0.9], ["diffuse"], [16], [2]
    if a.reading:
        x, w = np.polynomial.legendre.leggauss(a.mu)
        mus = 0.5 * (x + 1)
        for tau, alb, light, _, _ in table_rows(a.taus, a.albedos, a.lights):
            for N in a.n:
                e = reading_from_exact_nodes(tau, alb, light, N, mus)
                print(f"τ={tau:g} a={alb:g} {light:8s} N={N} (h = {tau / N:.3g} mfp): "
                      + "  ".join(f"{k} " + " ".join(f"{100 * v:+.1f}" for v in e[k])
                                  for k in ("const", "slope")), flush=True)
        return []
    if not a.f32:
        import jax

        jax.config.update("jax_enable_x64", True)
    x, w = np.polynomial.legendre.leggauss(a.mu)
    mus, wts = 0.5 * (x + 1), 0.5 * w
    rows = []
    for tau, alb, light, R_ad, T_ad in table_rows(a.taus, a.albedos, a.lights):
        top_x, bot_x, inc, direct = exact_slab_radiance(tau, alb, light, mus)
        R_x, T_x = exact_slab_rt(tau, alb, light)
        for M in a.m:
            for N in a.n:
                top, bot, secs, model, lf = camera_slab(tau, alb, light, mus, N, M, a.scheme,
                                                        a.first_collision, a.tol)
                lam = ([float("nan")] * 3 if light == "diffuse"
                       else fluence_ratios(model, lf, tau, alb, light).tolist())
                R_c, T_c = flux(top, mus, wts) / inc, (flux(bot, mus, wts) + direct) / inc
                R_q, T_q = flux(top_x, mus, wts) / inc, (flux(bot_x, mus, wts) + direct) / inc
                row = dict(tau=tau, albedo=alb, light=light, N=N, M=M, R_ad=R_ad, T_ad=T_ad,
                           R_exact=R_x, T_exact=T_x, R=R_c * R_x / R_q,
                           T=T_c * T_x / T_q if T_q > 0 else float("nan"),
                           err_R=R_c / R_q - 1, err_T=T_c / T_q - 1 if T_q > 1e-300 else float("nan"),
                           top=(top / top_x - 1).tolist(), bottom=(bot / bot_x - 1).tolist(),
                           scheme=model.solver.resolved_scheme(model.scene, model.lattice)
                           if hasattr(model, "lattice") else a.scheme, seconds=secs,
                           lam_top=lam[0], lam_mid=lam[1], lam_bottom=lam[2])
                rows.append(row)
                print(f"τ={tau:g} a={alb:g} {light:8s} N={N} M={M}: R {100 * row['err_R']:+.2f}% "
                      f"T {100 * row['err_T']:+.2f}%  (exact vs AD: R {100 * (R_x / R_ad - 1):+.3f}% "
                      f"T {100 * (T_x / T_ad - 1) if T_ad > 0 else float('nan'):+.3f}%)  "
                      f"top(μ) " + " ".join(f"{100 * e:+.1f}" for e in row["top"]) +
                      "  bottom(μ) " + " ".join(f"{100 * e:+.1f}" for e in row["bottom"]),
                      flush=True)
    mu_s = ", ".join(f"{m:.3f}" for m in mus)
    lines = [
        "# Thick slabs as cameras see them (isotropic)",
        "",
        f"`python benchmarks/slab_cameras.py` (module docstring); scheme {a.scheme}, first "
        f"collision {a.first_collision}, {'float32' if a.f32 else 'float64'}, tol {a.tol:g}. "
        f"R, T: the cameras' images at μ = {mu_s} (Gauss–Legendre, above and below) "
        "integrated over the hemisphere, error against the exact slab on the same μ (whose R, "
        "T by a fine μ quadrature are checked against adding-doubling: column 'exact vs AD'). "
        "I(μ): each camera's error, smallest μ first.",
        "",
        *C.md_table(["τ", "a", "light", "N", "M", "scheme", "R", "T", "exact vs AD (R / T)",
                     "Λ / exact: top node, mid, bottom node", "top I(μ) %", "bottom I(μ) %"],
                    [[f"{r['tau']:g}", f"{r['albedo']:g}", r["light"], r["N"], r["M"], r["scheme"],
                      f"{100 * r['err_R']:+.2f}%", _t_cell(r),
                      f"{100 * (r['R_exact'] / r['R_ad'] - 1):+.3f} / "
                      + (f"{100 * (r['T_exact'] / r['T_ad'] - 1):+.3f}" if r["T_ad"] > 0 else "–"),
                      "–" if r["light"] == "diffuse" else
                      f"{r['lam_top']:.3f} / {r['lam_mid']:.3f} / {r['lam_bottom']:.3f}",
                      " ".join(f"{100 * e:+.1f}" for e in r["top"]),
                      " ".join(f"{100 * e:+.1f}" for e in r["bottom"])] for r in rows]),
    ]
    within = [r for r in rows if abs(r["err_R"]) <= 0.03 and (
        r["T_exact"] < 1e-6 or abs(r["err_T"]) <= 0.03)]
    lines += ["", f"Rows with R and T within 3% (T where the exact slab lets through more than "
              f"1e-6 of the light): {len(within)} of {len(rows)}.", "", "## Machine", "",
              *C.machine_lines(C.machine())]
    print("wrote", C.write_text(a.out / f"{a.name}.md", "\n".join(lines) + "\n"))
    keys = ["tau", "albedo", "light", "N", "M", "scheme", "R_ad", "T_ad", "R_exact", "T_exact",
            "R", "T", "err_R", "err_T", "lam_top", "lam_mid", "lam_bottom", "seconds"]
    with open(a.out / f"{a.name}.csv", "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(keys + [f"top_mu{k}" for k in range(a.mu)]
                   + [f"bottom_mu{k}" for k in range(a.mu)])
        for r in rows:
            w.writerow([r[k] for k in keys] + r["top"] + r["bottom"])
    return rows


if __name__ == "__main__":
    main()
