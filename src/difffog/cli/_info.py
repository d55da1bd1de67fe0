"""``difffog info``: a readable summary of a scene, its lattice and the physics it needs."""

from __future__ import annotations

import time

from ..forward.sweep._terms import choose_terms
from ..geometry._lattice import VACUUM_MARGIN, voxelize
from ..scene._description import Scene
from ._main import add_scene_args


def physics_needed(scene: Scene) -> dict[str, bool]:
    """Which terms a solver must model for this scene (the basis of the sweep's terms)."""
    return {
        "fog": scene.has_fog,
        "anisotropic phase": scene.anisotropic,
        "surfaces": bool(scene.shapes),
        "meshes": scene.has_meshes,
        "sun": scene.sun is not None and scene.sun.irradiance > 0,
        "sky": scene.sky is not None and scene.sky.radiance > 0,
        "emission": any(s.emission > 0 for s in scene.shapes),
        "periodic boundary": scene.domain.boundary == "periodic-xy",
    }


#: ``difffog info`` voxelizes (node counts, optical depths, terms) only up to this many nodes
#: (~5 s on this project's CPU); beyond, it prints the estimate and says what it skipped
INFO_VOXELIZE_MAX_NODES = 20_000_000


def scene_info(scene: Scene, *, resolution: int = 64, M: int = 3, phase_order="auto",
               once_M: int | None = None) -> str:
    from .._cost import machine_line
    from ..forward.sweep._kernel import kernel_for
    from ..forward._registry import model_estimate
    from ..forward.sweep._solver import SweepSolver

    d = scene.domain
    est = model_estimate(scene, "sweep", resolution=resolution, M=M, phase_order=phase_order,
                         once_M=once_M)
    shell = SweepSolver(M=M, phase_order=phase_order, once_M=once_M).lattice_M(scene)
    big = est.nodes > INFO_VOXELIZE_MAX_NODES
    fmt = lambda v: "[" + ", ".join(f"{x:g}" for x in v) + "]"  # noqa: E731
    lines = [f"scene      {scene.title}" + (f"  ({scene.source})" if scene.source else "")]
    lines.append(f"domain     {fmt(d.min)} .. {fmt(d.max)}  boundary: {d.boundary}")
    h = max(b - a for a, b in zip(d.min, d.max)) / resolution
    sx, sy, sz = est.shape
    lat = None
    if not big:
        t = time.perf_counter()
        lat = voxelize(scene, resolution, shell, margin=VACUUM_MARGIN)
        tv = time.perf_counter() - t
    done = (f"voxelized in {tv:.2f} s" if lat is not None else
            f"not voxelized: {est.nodes:.3g} nodes (set-up ~{est.setup_text()})")
    lines.append(
        f"lattice    {sx}x{sy}x{sz} nodes, voxel {h:.4g}, M = {M} ({(2 * M + 1) ** 2} directions "
        f"per face; {VACUUM_MARGIN} vacuum nodes around open sides), {done}"
    )
    if est.once_s:
        lines.append(f"once       the sun's once-scattered light on M = {shell} "
                     f"({(2 * shell + 1) ** 2} directions per face, sub-stepped): one more "
                     f"sweep per light solve, ~{est.once_s:.2g} s (--once-M)")
    kernel = kernel_for(est.backend)
    if kernel == "loop":  # on a CPU: the sweep native or XLA's (and why)
        from ..forward.sweep import _native

        kernel += " (" + ("native C++)" if _native.available() else _native.status() + ")")
    lines.append(f"backend    {machine_line()}; sweep kernel: {kernel}")
    lines += ["cost       (sweep, estimated from the settings: difffog.estimate)"]
    lines += ["  " + ln for ln in est.lines()]
    if lat is not None:
        c = lat.counts()
        total = sum(c.values())
        lines.append(
            "nodes      "
            + ", ".join(f"{k} {v} ({100 * v / total:.1f}%)" for k, v in c.items())
        )
    if scene.fog is not None:
        f = scene.fog
        ph = f.phase + (f" g={f.g:g}" if f.phase == "henyey-greenstein" else "")
        extra = []
        if f.density_path:
            extra.append(f"density {f.density_path} {tuple(f.density.shape)}")
        if f.region:
            extra.append(f"region {fmt(f.region[0])} .. {fmt(f.region[1])}")
        lines.append(
            f"fog        ζ = {f.scattering:g}, γ = {f.absorption:g} per unit, albedo "
            f"{f.single_scattering_albedo:.4g}, {ph}" + ("; " + "; ".join(extra) if extra else "")
        )
        zeta_lattice = f.scattering
        if f.phase == "henyey-greenstein" and f.g:
            from ..forward.sweep._harmonics import delta_m
            from ..forward.sweep._solver import SweepSolver

            L = SweepSolver(phase_order=phase_order).resolved_phase_order(scene)
            fpeak = delta_m(f.g, L)[0]
            zeta_lattice = f.scattering * (1.0 - fpeak)
            lines.append(
                f"phase      the sweep carries (L+1)² = {(L + 1) ** 2} angular moments per fog "
                f"node (δ-M order L = {L}, --phase-order); the forward "
                f"peak g^(L+1) = {fpeak:.3g} of the scattering passes on unscattered")
        if lat is not None:
            tau = lat.optical_depth_range(f.scattering, f.absorption)
            lines.append(
                "opt.depth  across the domain: "
                + ", ".join(f"{a}: {lo:.3g}..{hi:.3g}" for a, (lo, hi) in tau.items())
            )
            seg = lat.max_segment_optical_depth(zeta_lattice, f.absorption)
            warn = "  (> 0.3: accuracy suffers, raise --resolution)" if seg > 0.3 else ""
            lines.append(f"segment    max optical depth of one lattice step σ_t·h·M = "
                         f"{seg:.3g}{warn}")
            from .._cost import _linear
            from ..forward.sweep._solver import LINEAR_FOG_SIZE, LINEAR_STEP_DEPTH

            lin = _linear(scene, resolution, M, phase_order, "auto")
            why = (f"a step is thicker than {LINEAR_STEP_DEPTH:g} mean free path, or the fog is "
                   f"{LINEAR_FOG_SIZE:g} or more across" if lin else
                   f"no step is thicker than {LINEAR_STEP_DEPTH:g} mean free path and the fog is "
                   f"under {LINEAR_FOG_SIZE:g} across")
            lines.append("transport  " + ("linear source along each lattice segment" if lin
                                          else "constant source per node")
                         + f" ({why}; --scheme overrides)")
    else:
        lines.append("fog        none")
    if scene.sun is not None:
        s = scene.sun
        lines.append(
            f"sun        irradiance {s.irradiance:g}, zenith {s.zenith_deg:g}°, azimuth "
            f"{s.azimuth_deg:g}°" + (f", radius {s.angular_radius_deg:g}°" if s.angular_radius_deg else "")
        )
    if scene.sky is not None:
        lines.append(f"sky        radiance {scene.sky.radiance:g}")
    for s in scene.shapes:
        lines.append(f"shape      {s.name}: {s.kind}, albedo {s.albedo:g}"
                     + (f", emission {s.emission:g}" if s.emission else ""))
    for cam in scene.cameras:
        what = f"fov {cam.fov_deg:g}°" if cam.kind == "perspective" else f"extent {fmt(cam.extent)}"
        lines.append(f"camera     {cam.name}: {cam.kind} {cam.width}x{cam.height}, {what}")
    needs = physics_needed(scene)
    lines.append("needs      " + ", ".join(f"{k}: {'yes' if v else 'no'}" for k, v in needs.items()))
    if lat is None:
        lines.append(f"skipped    node counts, optical depths and the sweep's terms (they need "
                     f"the lattice voxelized: {est.nodes:.3g} nodes > "
                     f"{INFO_VOXELIZE_MAX_NODES:.3g}; ask for a lower --resolution)")
        return "\n".join(lines)
    lines.append("terms      (what the sweep solver builds; SweepSolver(terms='all') keeps every "
                 "term)")
    lines += ["  " + ln for ln in choose_terms(scene, lat).lines(lat.shape)]
    return "\n".join(lines)


def add_parser(sub) -> None:
    p = sub.add_parser("info", help="summarize a scene: domain, lattice, node counts, physics")
    add_scene_args(p)
    p.set_defaults(func=run)


def run(args) -> int:
    from ..forward._registry import preset
    from ..scene._toml import load_scene

    s = preset("sweep", args.accuracy)
    scene = load_scene(args.scene, args.overrides)
    print(scene_info(scene, resolution=args.resolution or s["resolution"],
                     M=args.directions or s["M"],
                     phase_order="auto" if args.phase_order is None else args.phase_order,
                     once_M=args.once_M))
    return 0
