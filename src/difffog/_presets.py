"""Accuracy presets: what ``--accuracy draft|default|high`` (and ``accuracy=``) means for
each solver.  Chosen from the speed–accuracy study (``difffog bench``; figures in the README's
"Speed and accuracy" section and ``benchmarks/results/bench/``), not guessed:

* sweep: the lattice resolution N and direction half-width M set the model error; the
  iteration tolerance only needs to sit well below it (1e-3 changes images by < 0.1%).
  draft = N 32, M 2 (0.7 s warm, 16% mean error against Mitsuba over the four benchmark
  scenes); default = N 64, M 3 (2.3 s, 11%); high = N 96, M 4 (18 s, 9%).
* splat: the resolution of the splatted voxels and the sheet count.  Its error against the
  references hardly moves with either (23-25% averaged over the four scenes: the light model
  dominates), so the presets trade detail for time: draft = N 32 (0.10 s), default = N 64
  with 34 sheets (0.11 s, the lowest error measured, 21.9%; one sheet per voxel was 23.2% in
  0.24 s), high = N 128 with a sheet per voxel (1.1 s: sharper shadows and edges, not a lower
  error).  Measured by ``difffog bench`` (``benchmarks/results/bench/bench.md``, load ≈ 3).
"""

from __future__ import annotations

from ._errors import DifffogError

LEVELS = ("draft", "default", "high")

PRESETS: dict[str, dict[str, dict]] = {
    "sweep": {
        "draft": dict(resolution=32, M=2, tol=1e-3),
        "default": dict(resolution=64, M=3, tol=1e-4),
        "high": dict(resolution=96, M=4, tol=1e-4),
    },
    "splat": {
        "draft": dict(resolution=32, sheets=None),
        "default": dict(resolution=64, sheets=34),
        "high": dict(resolution=128, sheets=None),
    },
}


def preset(solver: str, accuracy: str = "default") -> dict:
    """The settings of ``solver`` ("sweep" or "splat") at ``accuracy`` (a copy)."""
    if solver not in PRESETS:
        raise DifffogError(f"unknown solver {solver!r}: choose {' or '.join(PRESETS)}")
    if accuracy not in LEVELS:
        raise DifffogError(f"unknown accuracy {accuracy!r}: choose {', '.join(LEVELS)}")
    return dict(PRESETS[solver][accuracy])


def forward_model(scene, *, solver: str = "sweep", accuracy: str = "default",
                  cameras: list[str] | None = None, **overrides):
    """A forward model (``Renderer`` for the sweep, ``SplatRenderer`` for the splat) at an
    accuracy preset; keyword arguments override single settings (e.g. ``resolution=48``)."""
    s = preset(solver, accuracy)
    unknown = set(overrides) - set(s) - {"supersample", "max_iterations", "progress"}
    if unknown:
        raise DifffogError(f"forward_model: unknown setting(s) {', '.join(sorted(unknown))} for "
                           f"the {solver}; it takes {', '.join(sorted(s))}")
    s.update(overrides)
    if solver == "sweep":
        from ._render import Renderer
        from ._solver import SweepSolver

        kw = {k: s[k] for k in ("max_iterations", "progress") if k in s}
        return Renderer(scene, resolution=s["resolution"], cameras=cameras,
                        supersample=s.get("supersample", 2),
                        solver=SweepSolver(M=s["M"], tol=s["tol"], **kw))
    from ._splat import SplatRenderer

    return SplatRenderer(scene, resolution=s["resolution"], sheets=s["sheets"], cameras=cameras,
                         supersample=s.get("supersample", 1))
