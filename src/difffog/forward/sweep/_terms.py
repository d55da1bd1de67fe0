"""The terms: which terms of the light problem a scene needs, decided once on the host.

``choose_terms(scene, lattice)`` inspects the scene (and its lattice) and says what the solver builds:

- fog → volume attenuation in the sweeps; fog that scatters (ζ > 0) → the in-scatter source and
  the Λ accumulation.  No fog: the sweeps only carry radiance between surfaces.
- fog confined to a sub-box (``fog.region``, a density grid with empty borders) → the volume
  work of each sweep is restricted to the slabs that hold fog; outside them rays just move.
- surfaces → radiosity, irradiance accumulation, blocked segments.
- sun → the first-collision sun pass (shadow buffer); sky → the first-collision sky pass (or
  sky radiance entering through the lattice's boundary, for periodic domains).
- nothing scatters or reflects (no fog scattering, every albedo 0) → one pass, no iteration.
- isotropic fog → scalar Λ only; Henyey–Greenstein fog → Λ and (L+1)² − 1 angular moments
  (δ-M, ``SweepSolver.phase_order`` L; L = 0: δ-isotropic, Λ only) for the multiple scattering,
  the exact phase for the sun's first collision and its single scattering at the camera.
- meshes → voxelized on the host; none → no mesh rasterization at all.

A term is dropped when the scene has no such object (no ``[fog]``, no shapes, no ``[sun]``, no
``[sky]``) or when its parameter is exactly 0 in the scene (ζ = 0: no Λ; every albedo and ζ 0:
one pass).  Such a parameter then cannot change inside the solve: setting it non-zero later is
an error (``check_params``), and its gradient is not computed.  ``terms="all"`` keeps every
term (what a fit that starts a parameter from 0 needs; also the benchmarks' baseline).

The terms also record enclosed cavities (non-solid regions that light cannot leave): if every
surface around one reflects everything, its fog (if any) does not absorb and something in it
emits, the light problem has no steady state, and solving is refused with a SolverError.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np
from scipy import ndimage

from ..._errors import SolverError

TERMS = ("auto", "all")


@dataclass(frozen=True)
class Terms:
    fog: bool  # volume attenuation (σ_t > 0 somewhere)
    volume_source: bool  # fog scattering: in-scatter source and Λ accumulation
    surfaces: bool
    sun: bool  # first-collision sun pass
    sky: str  # "none" | "first-collision" | "lattice"
    meshes: bool
    phase: str  # "isotropic" | "henyey-greenstein"
    iterate: bool  # False: nothing scatters or reflects → one pass
    fog_slabs: tuple[tuple[int, int], ...] | None  # per axis [lo, hi) node range holding fog
    cavities: tuple[tuple[int, ...], ...]  # shapes around each enclosed cavity
    cavity_fog: tuple[bool, ...]  # whether each cavity holds fog
    terms: str = "auto"

    def as_dict(self) -> dict:
        return asdict(self)

    def lines(self, shape: tuple[int, int, int] | None = None) -> list[str]:
        """Human-readable terms, one term per line (``difffog info``, the render report)."""
        yn = lambda b: "yes" if b else "no"  # noqa: E731
        out = [f"terms      {self.terms}"]
        if not self.fog:
            out.append("volume     no fog: no attenuation, no in-scatter source, no Λ")
        else:
            src = "in-scatter source + Λ" if self.volume_source else "attenuation only (ζ = 0: no Λ)"
            box = ""
            if self.fog_slabs is not None and shape is not None:
                frac = np.prod([(hi - lo) / n for (lo, hi), n in zip(self.fog_slabs, shape)])
                box = ("; volume work restricted to nodes " + " × ".join(
                    f"[{lo}, {hi})" for lo, hi in self.fog_slabs) + f" ({100 * frac:.0f}% of the lattice)")
            out.append(f"volume     {src}{box}")
            ph = ("scalar Λ (isotropic)" if self.phase == "isotropic" else
                  "Henyey–Greenstein: Λ + δ-M angular moments (phase_order), the sun's first "
                  "collision and single scattering with the exact phase")
            out.append(f"phase      {ph}")
        out.append(f"surfaces   {yn(self.surfaces)}" + ("" if self.surfaces else ": no radiosity terms"))
        out.append(f"sun pass   {yn(self.sun)}")
        out.append(f"sky pass   {self.sky}")
        out.append(f"meshes     {yn(self.meshes)}" + ("" if self.meshes else ": no mesh rasterization"))
        out.append("iteration  " + ("multiple scattering: iterate to the tolerance" if self.iterate
                                    else "nothing scatters or reflects: one pass"))
        if self.cavities:
            out.append(f"cavities   {len(self.cavities)} enclosed (light cannot leave them)")
        return out


def _fog_slabs(density: np.ndarray) -> tuple[tuple[int, int], ...] | None:
    """[lo, hi) per axis of the nodes with fog, or None if that is the whole lattice."""
    nz = np.argwhere(density > 0)
    if nz.size == 0:
        return None
    lo, hi = nz.min(0), nz.max(0) + 1
    if np.all(lo == 0) and np.all(hi == np.array(density.shape)):
        return None
    return tuple((int(a), int(b)) for a, b in zip(lo, hi))


def _cavities(lattice) -> tuple[list[tuple[int, ...]], list[bool]]:
    """Non-SOLID regions not connected to the open boundary, and the shapes around each."""
    nt = np.asarray(lattice.node_type)
    fluid = nt != 2
    labels, n = ndimage.label(fluid, structure=np.ones((3, 3, 3)))
    if n == 0:
        return [], []
    periodic = lattice.boundary == "periodic-xy"
    border = np.zeros(nt.shape, bool)
    for a in range(3):
        if periodic and a < 2:
            continue
        idx = [slice(None)] * 3
        idx[a] = 0
        border[tuple(idx)] = True
        idx[a] = -1
        border[tuple(idx)] = True
    if periodic:  # components touching across the wrap are one region
        for a in range(2):
            lo = np.take(labels, 0, axis=a)
            hi = np.take(labels, -1, axis=a)
            both = (lo > 0) & (hi > 0)
            for x, y in set(zip(lo[both].tolist(), hi[both].tolist())):
                if x != y:
                    labels[labels == y] = x
    escaping = set(np.unique(labels[border & fluid]).tolist())
    mat = np.asarray(lattice.material)
    dens = np.asarray(lattice.density)
    shapes, fog = [], []
    for lab in np.unique(labels[fluid]).tolist():
        if lab in escaping:
            continue
        region = labels == lab
        around = nt == 1
        ms = np.unique(mat[region & around])
        shapes.append(tuple(int(m) for m in ms if m >= 0))
        fog.append(bool(np.any(dens[region] > 0)))
    return shapes, fog


def choose_terms(scene, lattice=None, *, terms: str = "auto") -> Terms:
    """The terms this scene needs (see the module docstring); ``lattice`` adds the fog's node
    range and the enclosed cavities."""
    if terms not in TERMS:
        raise SolverError(f"terms must be one of {', '.join(TERMS)}, got {terms!r}")
    full = terms == "all"
    f = scene.fog
    fog = full or (f is not None and f.scattering + f.absorption > 0)
    volume_source = full or (f is not None and f.scattering > 0)
    surfaces = bool(scene.shapes)
    reflect = surfaces and (full or any(s.albedo > 0 for s in scene.shapes))
    periodic = scene.domain.boundary == "periodic-xy"
    sky = "none" if (scene.sky is None and not full) else ("lattice" if periodic else "first-collision")
    slabs, cav, cav_fog = None, (), ()
    if lattice is not None:
        if fog and not full:
            slabs = _fog_slabs(np.asarray(lattice.density))
        c, cf = _cavities(lattice)
        cav, cav_fog = tuple(c), tuple(cf)
    return Terms(
        fog=fog,
        volume_source=volume_source,
        surfaces=surfaces,
        sun=scene.sun is not None,
        sky=sky,
        meshes=scene.has_meshes,
        phase=f.phase if f is not None else "isotropic",
        iterate=bool(volume_source or reflect),
        fog_slabs=slabs,
        cavities=cav,
        cavity_fog=cav_fog,
        terms=terms,
    )


def check_terms(p: Terms, params) -> None:
    """Host-side check of concrete parameters against the terms: a SolverError if they need a
    term the terms dropped, or if an enclosed cavity has no steady state.  (Traced parameters
    are skipped here; the solver checks them at run time.)"""
    import dataclasses

    import jax

    if any(isinstance(x, jax.core.Tracer) for x in jax.tree.leaves(params)):
        return
    msg = terms_violation(p, {f.name: np.asarray(getattr(params, f.name))
                             for f in dataclasses.fields(params)})
    if msg:
        raise SolverError(msg)


def terms_violation(p: Terms, v: dict, xp=np):
    """The reason these parameter values do not fit the terms, or None.  With ``xp=jax.numpy``
    returns a list of (traced bool, message, result code) triples instead: the light solve's
    result code where the bool holds (``RESULTS.terms_dropped`` or ``no_steady_state``)."""
    from ..._results import RESULTS

    conds = []
    rebuild = ("; build the solver with terms='all' (SweepSolver(terms='all')) to keep every "
               "term, or set it non-zero in the scene")
    if not p.volume_source:
        conds.append((xp.any(v["scattering"] != 0),
                      "fog.scattering is non-zero but the terms dropped fog scattering (the scene "
                      "has none)" + rebuild, RESULTS.terms_dropped))
    if not p.fog:
        conds.append((xp.any(v["absorption"] != 0) | xp.any(v["scattering"] != 0),
                      "the fog coefficients are non-zero but the terms dropped the fog (the scene "
                      "has none)" + rebuild, RESULTS.terms_dropped))
    if p.sky == "none":
        conds.append((xp.any(v["sky_radiance"] != 0),
                      "sky.radiance is non-zero but the scene has no [sky] table" + rebuild,
                      RESULTS.terms_dropped))
    if not p.iterate:
        conds.append((xp.any(v["albedo"] != 0),
                      "a surface albedo is non-zero but the terms dropped reflection (every albedo "
                      "is 0 in the scene)" + rebuild, RESULTS.terms_dropped))
    for shapes, has_fog in zip(p.cavities, p.cavity_fog):
        if not shapes:
            continue
        idx = np.array(shapes)
        conservative = xp.all(v["albedo"][idx] >= 1.0)
        if has_fog:
            conservative = conservative & (v["absorption"] <= 0)
        emitting = xp.any(v["emission"][idx] > 0)
        conds.append((conservative & emitting,
                      "no steady state: an enclosed region whose surfaces reflect everything "
                      "(albedo 1)" + (" and whose fog does not absorb" if has_fog else "")
                      + " contains emission, so its light grows without bound; lower an albedo "
                      "below 1, add fog absorption, or open the enclosure",
                      RESULTS.no_steady_state))
    if xp is np:
        return next((m for c, m, _ in conds if bool(c)), None)
    return conds
