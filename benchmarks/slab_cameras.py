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
    python benchmarks/slab_cameras.py --g 0.85 --taus 1 2 4 16 --albedos 0.9 0.99 --m 3 \
        --name slab_cameras_hg                             # issue 15's Henyey–Greenstein rows

With ``--g`` (a Henyey–Greenstein fog) the reference is adding-doubling at the cameras' own
angles (``difffog.study._slab.adding_doubling_radiance``, checked against the table's R and T
in each row), and under the sun at 60° the cameras stand at ``--azimuths`` azimuths around
the slab (the radiance then depends on the azimuth; R and T are read on those same angles, a
trapezoid in azimuth, and each image is held against the exact radiance at its angle).

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
from difffog.study._slab import (adding_doubling_radiance, exact_slab_collided,
                                 exact_slab_radiance, exact_slab_rt, half_range_gauss,
                                 isotropic_slab_rows)

LIGHTS = ("diffuse", "coll0", "coll60")


def flux(I, mus, wts):
    return 2 * math.pi * float(np.sum(wts * mus * I))


def slab_scene(tau, albedo, light, mus, pad=0.25, width=0.25, pixels=4, g=0.0, azimuths=(0.0,)):
    """The slab as a scene: cameras ``top{k}`` / ``bottom{k}`` at μ_k (``top{k}_{j}`` at
    azimuth j of ``azimuths``, degrees from the sun's, where there are several)."""
    from difffog.scene._description import Camera, Domain, Fog, Scene, Sky, Sun

    cams = []
    for k, mu in enumerate(mus):
        s = math.sqrt(max(0.0, 1 - mu * mu))
        for j, az in enumerate(azimuths):
            ca, sa = math.cos(math.radians(az)), math.sin(math.radians(az))
            tag = f"{k}" if len(azimuths) == 1 else f"{k}_{j}"
            for name, sign, z0 in (("top", 1.0, 1.0), ("bottom", -1.0, 0.0)):
                c = (width / 2, width / 2, z0)
                pos = (c[0] + 2.0 * s * ca, c[1] + 2.0 * s * sa, z0 + sign * 2.0 * mu)
                cams.append(Camera(f"{name}{tag}", "orthographic", pos, c, up=(-sa, ca, 0),
                                   resolution=(pixels, pixels),
                                   extent=(width / 2, width / 2)))
    phase = dict(phase="henyey-greenstein", g=g) if g else {}
    sun = None if light == "diffuse" else Sun(1.0, float(light[4:]), 0.0)
    return Scene(
        title=f"slab τ={tau} a={albedo} {light}",
        domain=Domain((0, 0, -pad), (width, width, 1 + pad), "periodic-xy"),
        fog=Fog(scattering=albedo * tau, absorption=(1 - albedo) * tau,
                region=((0, 0, 0), (width, width, 1)), **phase),
        sky=Sky(1.0) if light == "diffuse" else None, sun=sun, cameras=tuple(cams))


def camera_slab(tau, albedo, light, mus, N, M, scheme, first_collision, tol, g=0.0,
                azimuths=(0.0,), phase_order="auto", once_M=None):
    """(I_top, I_bottom, seconds, model, light field): each camera's image mean, shape
    (len(mus),), or (len(mus), len(azimuths)) where there are several azimuths."""
    import difffog as df

    pad = 0.25
    # 8 nodes across (the slab is laterally homogeneous): a lattice of 8 × 8 × 1.5 N
    scene = slab_scene(tau, albedo, light, mus, pad=pad, width=8.0 / N, g=g, azimuths=azimuths)
    extra = dict(phase_order=phase_order, once_M=once_M) if g else {}
    model = df.forward_model(scene, "sweep", accuracy=None, resolution=int(round(N * (1 + 2 * pad))),
                             M=M, tol=tol, max_iterations=20000, supersample=1, scheme=scheme,
                             first_collision=first_collision, **extra)
    t0 = time.perf_counter()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        out = df.render(model)
    secs = time.perf_counter() - t0
    def read(name):
        if len(azimuths) == 1:
            return np.array([float(np.asarray(out.images[f"{name}{k}"], np.float64).mean())
                             for k in range(len(mus))])
        return np.array([[float(np.asarray(out.images[f"{name}{k}_{j}"], np.float64).mean())
                          for j in range(len(azimuths))] for k in range(len(mus))])

    return read("top"), read("bottom"), secs, model, out.light


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


def table_rows(taus, albedos, lights, g=0.0):
    ref = isotropic_slab_rows(g)
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
    ap.add_argument("--g", type=float, default=0.0,
                    help="Henyey–Greenstein g (0: isotropic, the exact integral equation)")
    ap.add_argument("--azimuths", type=int, default=16,
                    help="with --g, under the 60° sun: azimuths around the slab (even)")
    ap.add_argument("--phase-order", default="auto", help="with --g: the light solve's L")
    ap.add_argument("--once-m", type=int, default=None,
                    help="with --g: the once-scattered sun's direction set (SweepSolver.once_M)")
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
        mus = half_range_gauss(a.mu)[0]
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
    mus, wts = half_range_gauss(a.mu)
    po = a.phase_order if a.phase_order == "auto" else int(a.phase_order)
    rows = []
    for tau, alb, light, R_ad, T_ad in table_rows(a.taus, a.albedos, a.lights, a.g):
        # azimuths: one unless the radiance depends on it (a Henyey–Greenstein slab under an
        # oblique sun); then 0…180° from the sun's side (the scene is symmetric about its
        # plane), weighted as a trapezoid over the full circle
        n_az = a.azimuths if (a.g and light not in ("diffuse", "coll0")) else 1
        az = np.arange(n_az // 2 + 1) * 360.0 / n_az if n_az > 1 else np.zeros(1)
        w_az = (np.r_[1.0, np.full(len(az) - 2, 2.0), 1.0] / n_az) if n_az > 1 else np.ones(1)
        if a.g:
            top_x, bot_x, inc, direct = adding_doubling_radiance(
                tau, alb, a.g, light, mus, azimuths=az if n_az > 1 else None)
        else:
            top_x, bot_x, inc, direct = exact_slab_radiance(tau, alb, light, mus)
        R_x, T_x = exact_slab_rt(tau, alb, light, g=a.g)
        for M in a.m:
            for N in a.n:
                top, bot, secs, model, lf = camera_slab(
                    tau, alb, light, mus, N, M, a.scheme, a.first_collision, a.tol, g=a.g,
                    azimuths=tuple(az), phase_order=po, once_M=a.once_m)
                lam = ([float("nan")] * 3 if light == "diffuse" or a.g
                       else fluence_ratios(model, lf, tau, alb, light).tolist())
                err_top, err_bot = top / top_x - 1, bot / bot_x - 1
                if n_az > 1:  # per μ: the azimuths' mean image and the worst one
                    worst_top = np.take_along_axis(err_top, np.abs(err_top).argmax(1)[:, None], 1)[:, 0]
                    worst_bot = np.take_along_axis(err_bot, np.abs(err_bot).argmax(1)[:, None], 1)[:, 0]
                    top, bot, top_x, bot_x = top @ w_az, bot @ w_az, top_x @ w_az, bot_x @ w_az
                else:
                    worst_top, worst_bot = err_top, err_bot
                R_c, T_c = flux(top, mus, wts) / inc, (flux(bot, mus, wts) + direct) / inc
                R_q, T_q = flux(top_x, mus, wts) / inc, (flux(bot_x, mus, wts) + direct) / inc
                row = dict(tau=tau, albedo=alb, light=light, N=N, M=M, R_ad=R_ad, T_ad=T_ad,
                           R_exact=R_x, T_exact=T_x, R=R_c * R_x / R_q,
                           T=T_c * T_x / T_q if T_q > 0 else float("nan"),
                           err_R=R_c / R_q - 1, err_T=T_c / T_q - 1 if T_q > 1e-300 else float("nan"),
                           top=(top / top_x - 1).tolist(), bottom=(bot / bot_x - 1).tolist(),
                           worst_top=worst_top.tolist(), worst_bottom=worst_bot.tolist(),
                           azimuths=az.tolist(),
                           scheme=model.solver.resolved_scheme(model.scene, model.lattice)
                           if hasattr(model, "lattice") else a.scheme, seconds=secs,
                           lam_top=lam[0], lam_mid=lam[1], lam_bottom=lam[2],
                           L=model.solver.resolved_phase_order(model.scene) if a.g else 0)
                rows.append(row)
                print(f"τ={tau:g} a={alb:g} {light:8s} N={N} M={M}: R {100 * row['err_R']:+.2f}% "
                      f"T {100 * row['err_T']:+.2f}%  (exact vs AD: R {100 * (R_x / R_ad - 1):+.3f}% "
                      f"T {100 * (T_x / T_ad - 1) if T_ad > 0 else float('nan'):+.3f}%)  "
                      f"top(μ) " + " ".join(f"{100 * e:+.1f}" for e in row["top"]) +
                      "  bottom(μ) " + " ".join(f"{100 * e:+.1f}" for e in row["bottom"]),
                      flush=True)
    mu_s = ", ".join(f"{m:.3f}" for m in mus)
    hg = (f"Henyey–Greenstein g = {a.g:g}; the exact radiance by adding-doubling at the cameras' "
          f"angles, L {a.phase_order}, once-M {a.once_m}; under the sun at 60° cameras at {a.azimuths} azimuths (0…180° by symmetry), "
          "I(μ) the error of their trapezoid mean, 'worst' the largest image error over the "
          "azimuths; ") if a.g else ""
    lines = [
        "# Slabs as cameras see them (" + (f"Henyey–Greenstein, g = {a.g:g})" if a.g
                                            else "isotropic)"),
        "",
        f"`python benchmarks/slab_cameras.py` (module docstring); {hg}scheme {a.scheme}, first "
        f"collision {a.first_collision}, {'float32' if a.f32 else 'float64'}, tol {a.tol:g}. "
        f"R, T: the cameras' images at μ = {mu_s} (Gauss–Legendre, above and below) "
        "integrated over the hemisphere, error against the exact slab on the same μ (whose R, "
        "T by a fine μ quadrature are checked against adding-doubling: column 'exact vs AD'). "
        "I(μ): each camera's error, smallest μ first.",
        "",
        *C.md_table(["τ", "a", "light", "N", "M", "scheme" + (", L" if a.g else ""), "R", "T",
                     "exact vs AD (R / T)",
                     ("worst image over azimuths: top, bottom (%)" if a.g else
                      "Λ / exact: top node, mid, bottom node"), "top I(μ) %", "bottom I(μ) %"],
                    [[f"{r['tau']:g}", f"{r['albedo']:g}", r["light"], r["N"], r["M"],
                      r["scheme"] + (f", {r['L']}" if a.g else ""),
                      f"{100 * r['err_R']:+.2f}%", _t_cell(r),
                      f"{100 * (r['R_exact'] / r['R_ad'] - 1):+.3f} / "
                      + (f"{100 * (r['T_exact'] / r['T_ad'] - 1):+.3f}" if r["T_ad"] > 0 else "–"),
                      (" ".join(f"{100 * e:+.1f}" for e in r["worst_top"]) + ", "
                       + " ".join(f"{100 * e:+.1f}" for e in r["worst_bottom"])
                       if len(r["azimuths"]) > 1 else "–") if a.g else
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
            "R", "T", "err_R", "err_T", "lam_top", "lam_mid", "lam_bottom", "L", "seconds"]
    with open(a.out / f"{a.name}.csv", "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(keys + [f"top_mu{k}" for k in range(a.mu)]
                   + [f"bottom_mu{k}" for k in range(a.mu)]
                   + [f"worst_top_mu{k}" for k in range(a.mu)]
                   + [f"worst_bottom_mu{k}" for k in range(a.mu)])
        for r in rows:
            w.writerow([r[k] for k in keys] + r["top"] + r["bottom"] + r["worst_top"]
                       + r["worst_bottom"])
    return rows


if __name__ == "__main__":
    main()
