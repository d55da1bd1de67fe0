"""Validation ladder steps 2 and 4: slab R and T against adding-doubling, as N and M grow.

A laterally infinite homogeneous slab (isotropic scattering, g = 0) of optical thickness τ and
single-scattering albedo a under a uniform sky, as a periodic lattice one node wide with N fog
nodes across the slab (``difffog.study.slab_problem``), solved in float64 with
``SweepSolver(M, max_iterations=5000, tol=1e-8)``.  Total reflectance R and transmittance T
(unscattered sky included) come from the converged source by the formal solution along a fine
μ quadrature (``difffog.study.slab_reflectance``), and are compared with the adding-doubling
table shipped with difffog (``difffog.study.references.slab_table()``, or ``--references DIR``;
iadpython, 64 quadrature points).

Two treatments of the sky: ``lattice`` (sky_quadrature=(0, 0), the default for periodic
domains: the sky enters along the lattice's downward directions) and ``first-collision``
(sky_quadrature=(16, 16): the uncollided sky is swept along 16 μ × 16 φ directions and only its
first scattering enters the lattice).

Writes ``slab_convergence.csv`` and ``slab_convergence.md`` to ``--out`` (default
``benchmarks/results``); the markdown ends with the run's machine (JAX backend and devices, copy
bandwidth, measured in the same run).

    python benchmarks/slab_convergence.py                 # a {0.5,0.9,0.99} × τ {0.1,1,4}
    python benchmarks/slab_convergence.py --n 16 32 --m 2 3 --variants lattice
    python benchmarks/slab_convergence.py --quick --out /tmp/slab   # N 8 16, M 2, a 0.9, τ 1
"""

from __future__ import annotations

import argparse
import csv
import time
from pathlib import Path

import numpy as np

import _common as C

ALBEDOS = (0.5, 0.9, 0.99)
TAUS = (0.1, 1.0, 4.0)
NS = (16, 32, 64, 128)
MS = (2, 3, 5)
VARIANTS = {"lattice": (0, 0), "first-collision": (16, 16)}


def ad_reference(table: list[dict], albedo: float, tau: float) -> tuple[float, float]:
    """(R, T) of the adding-doubling table's diffusely lit slab (g = 0)."""
    for r in table:
        if (r["albedo"] == albedo and r["tau"] == tau and r["g"] == 0
                and r["illumination"] == "diffuse"):
            return float(r["R_total"]), float(r["T_total"])
    raise KeyError((albedo, tau))


def run_column(N: int, M: int, sky_q: tuple[int, int], cases, max_iterations: int, tol: float,
               scheme: str = "step"):
    """R, T, iterations, warm solve seconds for every (albedo, τ) on one compiled lattice."""
    import equinox as eqx
    import jax.numpy as jnp

    from difffog import Params, SweepSolver
    from difffog.study import slab_problem, slab_reflectance

    solver = SweepSolver(M=M, max_iterations=max_iterations, tol=tol, sky_quadrature=sky_q,
                         scheme=scheme)
    scene0, lat, margin = slab_problem(1.0, 0.5, N, M)
    geom = solver.prepare(scene0, lat)  # the lattice does not depend on (albedo, τ)
    solve = eqx.filter_jit(solver.solve)
    density = np.asarray(lat.density, np.float64)[0, 0]
    out = []
    for albedo, tau in cases:
        scene, _, _ = slab_problem(tau, albedo, N, M)
        params = Params.from_scene(scene, jnp.float64)
        t = C.time_calls(lambda: solve(geom, params), 1)  # after the compile (first case) / warm-up
        light, dt = t.value, t.times[0]
        sigma = float(params.scattering + params.absorption) * density  # g = 0
        slope = (None if light.source_slope is None
                 else np.asarray(light.source_slope)[0, 0, :, 2])  # the linear scheme's
        R, T = slab_reflectance(sigma, np.asarray(light.source)[0, 0], None, margin, lat.h,
                                sky=1.0, slope=slope)
        out.append((albedo, tau, R, T, int(light.iterations), float(light.error_estimate), dt))
    return out


def markdown(rows, ns, ms, variants, machine: dict | None = None) -> str:
    idx = {(r["variant"], r["albedo"], r["tau"], r["N"], r["M"]): r for r in rows}
    cases = sorted({(r["albedo"], r["tau"]) for r in rows})
    lines = [
        "# Slab R and T against adding-doubling (g = 0, uniform sky)",
        "",
        "Relative error in % of the sweep solver (float64, tol 1e-8) against the adding-doubling "
        "table, as `R / T` per cell; N = fog nodes across the slab, M = direction half-width. "
        "Reproduce with `python benchmarks/slab_convergence.py`.",
    ]
    for v in variants:
        lines += ["", f"## Sky through {'the lattice directions' if v == 'lattice' else 'first-collision quadrature'}"
                  f" (`sky_quadrature={VARIANTS[v]}`)", ""]
        cols = [(n, m) for m in ms for n in ns]
        lines.append("| a | τ | " + " | ".join(f"N{n} M{m}" for n, m in cols) + " |")
        lines.append("|---|---|" + "---:|" * len(cols))
        for a, t in cases:
            cells = []
            for n, m in cols:
                r = idx.get((v, a, t, n, m))
                cells.append("" if r is None else f"{100 * r['err_R']:+.1f} / {100 * r['err_T']:+.1f}")
            lines.append(f"| {a:g} | {t:g} | " + " | ".join(cells) + " |")
    # first-collision vs lattice at a glance: mean |error| per (N, M)
    lines += ["", "## Mean and max |error| over the slabs, % (R / T)", "",
              "| sky | M | " + " | ".join(f"N{n}" for n in ns) + " |",
              "|---|---:|" + "---:|" * len(ns)]
    for v in variants:
        for m in ms:
            cells = []
            for n in ns:
                sel = [r for r in rows if r["variant"] == v and r["N"] == n and r["M"] == m]
                if not sel:
                    cells.append("")
                    continue
                eR = [abs(r["err_R"]) for r in sel]
                eT = [abs(r["err_T"]) for r in sel]
                cells.append(f"{100 * np.mean(eR):.1f} / {100 * np.mean(eT):.1f} "
                             f"(max {100 * max(eR):.1f} / {100 * max(eT):.1f})")
            lines.append(f"| {v} | {m} | " + " | ".join(cells) + " |")
    lines += ["", "## Conclusion", ""] + conclusion(rows, ns, ms, variants)
    if machine is not None:
        lines += ["", "## Machine", "", *C.machine_lines(machine)]
    return "\n".join(lines) + "\n"


def conclusion(rows, ns, ms, variants) -> list[str]:
    """Facts read off the table (generated, so they follow the data)."""
    out = []
    for v in variants:
        sel = [r for r in rows if r["variant"] == v]
        if not sel:
            continue
        worst = max(sel, key=lambda r: max(abs(r["err_R"]), abs(r["err_T"])))
        which = "R" if abs(worst["err_R"]) >= abs(worst["err_T"]) else "T"
        # does the error fall with N (at each M, mean |err| over slabs) and with M (at largest N)?
        def mean_err(n, m, key):
            s = [abs(r[key]) for r in sel if r["N"] == n and r["M"] == m]
            return np.mean(s) if s else np.nan
        byN = {m: [mean_err(n, m, "err_R") + mean_err(n, m, "err_T") for n in ns] for m in ms}
        byM = [mean_err(ns[-1], m, "err_R") + mean_err(ns[-1], m, "err_T") for m in ms]
        fallsN = [m for m in ms if all(np.diff(byN[m]) <= 1e-4)]
        fallsM = bool(np.all(np.diff(byM) <= 1e-4))
        thin = [r for r in sel if r["tau"] < 0.5 and r["N"] == ns[-1]] or [{"err_R": np.nan}]
        thick = [r for r in sel if r["tau"] >= 0.5 and r["N"] == ns[-1]] or [
            {"err_R": np.nan, "err_T": np.nan}]
        out.append(
            f"- **{v} sky**: mean |R err| + |T err| over the slabs vs N "
            + "; ".join(f"M={m}: " + " → ".join(f"{100 * x:.1f}" for x in byN[m]) + "%"
                        for m in ms)
            + f". It falls monotonically with N at M ∈ {fallsN or 'none'}; with M at N={ns[-1]}: "
            + " → ".join(f"{100 * x:.1f}" for x in byM) + "% ("
            + ("monotone" if fallsM else "not monotone") + "). Worst case: "
            + f"a={worst['albedo']:g}, τ={worst['tau']:g}, N={worst['N']}, M={worst['M']}: "
            + f"{which} {100 * worst['err_' + which]:+.1f}%. At N={ns[-1]}: thin slabs (τ=0.1) "
            + f"|R err| up to {100 * max(abs(r['err_R']) for r in thin):.1f}%, "
            + f"thicker slabs (τ≥1) up to {100 * max(abs(r['err_R']) for r in thick):.1f}% in R, "
            + f"{100 * max(abs(r['err_T']) for r in thick):.1f}% in T."
        )
    out += extra_findings(rows, ns, ms, variants)
    return out


def extra_findings(rows, ns, ms, variants) -> list[str]:
    """Where the error comes from: angular floor (thin slabs), step optical depth, sky variant."""
    out = []
    lat = [r for r in rows if r["variant"] == variants[0]]
    thin = [r for r in lat if r["tau"] < 0.5]
    if thin and len(ns) > 1:
        spread = max(
            np.ptp([r["err_R"] for r in thin if r["albedo"] == a and r["M"] == m])
            for a in {r["albedo"] for r in thin} for m in ms
        )
        worst_by_m = {m: max(abs(r["err_R"]) for r in thin if r["M"] == m) for m in ms}
        out.append(
            f"- Thin slabs (τ<0.5) set an angular floor: their R error changes by at most "
            f"{100 * spread:.2f} points from N={ns[0]} to N={ns[-1]} ({variants[0]} sky) but falls "
            f"with M (max |R err| " + " → ".join(f"{100 * worst_by_m[m]:.1f}%" for m in ms)
            + f" at M = {', '.join(map(str, ms))}): the cube's integer directions resolve "
            "near-grazing scattering poorly, whatever the lattice spacing."
        )
    if lat:
        w = max(lat, key=lambda r: max(abs(r["err_R"]), abs(r["err_T"])))
        out.append(
            f"- Thick slabs at coarse N get worse with M: the worst {variants[0]}-sky case "
            f"(a={w['albedo']:g}, τ={w['tau']:g}, N={w['N']}, M={w['M']}) has a segment optical "
            f"depth τ·M/N = {w['tau'] * w['M'] / w['N']:.2f} (a lattice ray spans M planes; "
            "DESIGN.md: keep it ≤ 0.3). A larger M pays off only once N is large enough for it."
        )
    if len(variants) > 1:
        def mean_abs(v, key, thick):
            s = [abs(r[key]) for r in rows if r["variant"] == v and r["N"] == ns[-1]
                 and (r["tau"] >= 0.5) == thick]
            return 100 * np.mean(s) if s else np.nan
        out.append(
            f"- Sky variants at N={ns[-1]} (mean |R err|, all M): τ≥1 "
            + ", ".join(f"{v} {mean_abs(v, 'err_R', True):.2f}%" for v in variants)
            + "; τ<0.5 " + ", ".join(f"{v} {mean_abs(v, 'err_R', False):.2f}%" for v in variants)
            + ". The first-collision sky is better in optically thick slabs but overestimates "
            "thin-slab reflectance, increasingly with albedo and less with M: probably because "
            "in a periodic column the lattice's horizontal directions never leave the slab and "
            "over-weight grazing radiance, which the lattice sky (missing the horizontal sky) "
            "offsets; this supports the (0, 0) default for periodic domains."
        )
    return out


def read_csv(path: Path) -> list[dict]:
    ints = {"N", "M", "iterations"}
    with open(path, newline="") as f:
        return [{k: (v if k == "variant" else int(v) if k in ints else float(v))
                 for k, v in r.items()} for r in csv.DictReader(f)]


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    C.add_sizes(ap, NS, (8, 16), flag="--n", what="fog nodes across the slab")
    C.add_sizes(ap, MS, (2,), flag="--m", what="direction half-widths M")
    ap.add_argument("--albedos", nargs="+", type=float, default=None,
                    help=f"default {' '.join(map(str, ALBEDOS))}; with --quick 0.9")
    ap.add_argument("--taus", nargs="+", type=float, default=None,
                    help=f"default {' '.join(map(str, TAUS))}; with --quick 1")
    ap.add_argument("--variants", nargs="+", choices=list(VARIANTS), default=None,
                    help="default both; with --quick lattice")
    ap.add_argument("--max-iterations", type=int, default=5000)
    ap.add_argument("--tol", type=float, default=1e-8)
    ap.add_argument("--references", type=Path, default=None,
                    help="folder of the references (default: the shipped ones)")
    ap.add_argument("--out", type=Path, default=C.RESULTS)
    ap.add_argument("--scheme", choices=("step", "linear", "substep"), default="step",
                    help="SweepSolver.scheme (default step)")
    ap.add_argument("--name", default="slab_convergence",
                    help="stem of the result files (default slab_convergence)")
    ap.add_argument("--from-csv", action="store_true",
                    help="only rebuild the markdown from an existing slab_convergence.csv")
    args = C.parse(ap, argv)
    args.albedos = args.albedos or ([0.9] if args.quick else list(ALBEDOS))
    args.taus = args.taus or ([1.0] if args.quick else list(TAUS))
    args.variants = args.variants or (["lattice"] if args.quick else list(VARIANTS))
    if args.from_csv:
        rows = read_csv(args.out / f"{args.name}.csv")
        variants = [v for v in VARIANTS if any(r["variant"] == v for r in rows)]
        md = markdown(rows, sorted({r["N"] for r in rows}), sorted({r["M"] for r in rows}),
                      variants)
        (args.out / f"{args.name}.md").write_text(md)
        print(md)
        return
    import jax

    jax.config.update("jax_enable_x64", True)
    from difffog.study import references

    try:
        table = references.slab_table(args.references)
    except OSError as e:
        raise SystemExit(f"no adding-doubling table: {e}") from None
    info = C.machine()
    t_all = time.perf_counter()
    cases = [(a, t) for a in args.albedos for t in args.taus]
    refs = {c: ad_reference(table, *c) for c in cases}
    args.out.mkdir(parents=True, exist_ok=True)
    rows = []
    for v in args.variants:
        for M in args.m:
            for N in args.n:
                t0 = time.perf_counter()
                res = run_column(N, M, VARIANTS[v], cases, args.max_iterations, args.tol,
                                 args.scheme)
                for a, tau, R, T, it, err, dt in res:
                    Rr, Tr = refs[(a, tau)]
                    rows.append({"variant": v, "albedo": a, "tau": tau, "N": N, "M": M,
                                 "R": R, "T": T, "R_ref": Rr, "T_ref": Tr,
                                 "err_R": R / Rr - 1.0, "err_T": T / Tr - 1.0,
                                 "iterations": it, "error_estimate": err, "solve_s": dt})
                worst = max(abs(r["err_R"]) for r in rows[-len(cases):])
                print(f"{v:15s} M={M} N={N:3d}: max |R err| {100 * worst:5.1f}%  "
                      f"({time.perf_counter() - t0:.0f}s)", flush=True)
    with open(args.out / f"{args.name}.csv", "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=list(rows[0]))
        w.writeheader()
        for r in rows:
            w.writerow({k: (f"{x:.7g}" if isinstance(x, float) else x) for k, x in r.items()})
    md = markdown(rows, args.n, args.m, args.variants, info)
    if args.scheme != "step":
        md = md.replace("of the sweep solver", f"of the sweep solver (scheme={args.scheme})", 1)
    (args.out / f"{args.name}.md").write_text(md)
    print()
    print(md)
    print(f"total {time.perf_counter() - t_all:.0f} s, warm solves "
          f"{sum(r['solve_s'] for r in rows):.2f} s")


if __name__ == "__main__":
    main()
