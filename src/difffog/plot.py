"""Plots for notebooks, benchmarks and the command line (matplotlib).

Every function returns a :class:`matplotlib.figure.Figure` (or draws into the ``ax=`` /
``axes=`` it is given and returns their figure), labels its axes with units, and never touches
pyplot's global figure list: new figures are :class:`PlotFigure` (a ``Figure`` that Jupyter
shows as PNG), so nothing is left open and nothing is shown twice in a notebook (a returned
figure displays itself; ``display(fig)`` in a loop; ``fig.savefig`` writes it).  ``import difffog`` does not import matplotlib; ``import difffog.plot`` does.

Units.  Images are linear radiance.  A scene file gives ``sun.irradiance`` and
``sky.radiance`` without units; in SI (irradiance in W m⁻²) image radiance is in
W m⁻² sr⁻¹, which is what the labels say (:data:`RADIANCE_UNIT`; pass ``unit=`` to change it).
Lengths are in scene units.

Tone map.  :func:`tonemap` is the command line's: divide by the 99.5th percentile of the
pixels (one shared scale for all images given together), clip to [0, 1], gamma 1/2.2.
:func:`image_grid` shows linear images through the same map (a power norm), so its colour
bar reads in radiance.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence

import matplotlib
import numpy as np
from matplotlib import colors as mcolors
from matplotlib.figure import Figure
from matplotlib.patches import Patch
from matplotlib.ticker import PercentFormatter

from ._errors import DifffogError
from ._image import GAMMA, PERCENTILE, exposure, image_errors, tonemap

__all__ = [
    "RADIANCE_UNIT",
    "PlotFigure",
    "convergence",
    "error_map",
    "exposure",
    "image_errors",
    "image_grid",
    "lattice_slices",
    "pareto",
    "pareto_front",
    "tonemap",
]

RADIANCE_UNIT = "W m⁻² sr⁻¹"

# FREE / SURFACE / SOLID (the values of Lattice.node_type)
_NODE_COLOURS = ("#f2f2f2", "#e6862e", "#3b3b3b")
_NODE_NAMES = ("FREE", "SURFACE", "SOLID")

_AXIS_NAMES = "xyz"

# axis labels (with units) of the columns `pareto` knows; others are labelled by their name
_LABELS = {
    "time_s": "time (s)",
    "solve_s": "solve time (s)",
    "render_s": "render time (s)",
    "wall_s": "wall time (s)",
    "error": "relative error",
    "rel_rmse": "relative RMSE",
    "rel_rmse_corr": "relative RMSE (reference noise removed)",
    "rel_rmse_s3": "relative RMSE (3×3 smoothed)",
    "iterations": "Jacobi iterations",
    "memory_mb": "memory (MiB)",
    "spp": "samples per pixel",
}


class PlotFigure(Figure):
    """A matplotlib Figure that Jupyter displays by itself (as PNG) without pyplot: the
    figures of this module are never registered with pyplot, so nothing is left open and a
    figure returned by a cell is shown exactly once."""

    def _repr_png_(self) -> bytes:
        import io

        buf = io.BytesIO()
        self.savefig(buf, format="png", dpi=90, bbox_inches="tight")
        return buf.getvalue()


def _new_figure(nrows: int, ncols: int, size: tuple[float, float], layout: str = "constrained",
                **kw):
    # "compressed" is matplotlib's layout for grids of fixed-aspect images
    fig = PlotFigure(figsize=(size[0] * ncols, size[1] * nrows), layout=layout)
    axes = fig.subplots(nrows, ncols, squeeze=False, **kw)
    return fig, axes


def _panels(n: int, ncols: int | None, panel_size, axes, caller: str, what: str):
    """(figure, flat list of axes, columns) for ``n`` panels: a new grid of ``ncols`` columns
    (default 4, at most n), or the ``axes`` given (ncols defaults to their count)."""
    if axes is None:
        ncols = min(n, ncols or 4)
        fig, grid = _new_figure(-(-n // ncols), ncols, panel_size, layout="compressed")
        return fig, list(grid.ravel()), ncols
    flat = list(np.ravel(axes))
    if len(flat) < n:
        raise DifffogError(f"difffog.plot.{caller}: {n} {what} but {len(flat)} axes given")
    return flat[0].figure, flat, ncols or len(flat)


def _pixel_labels(ax, bottom: bool = True, left: bool = True):
    if bottom:
        ax.set_xlabel("column (pixels)")
    if left:
        ax.set_ylabel("row (pixels)")


def image_grid(images: Mapping[str, np.ndarray], *, ncols: int | None = None,
               scale: float | None = None, percentile: float = PERCENTILE,
               gamma: float = GAMMA, unit: str = RADIANCE_UNIT, colorbar: bool = True,
               axes=None, panel_size: tuple[float, float] = (3.2, 3.0),
               suptitle: str | None = None) -> Figure:
    """Linear radiance images side by side under one shared tone map, titled by their keys.

    images: ``{title: (H, W) array}`` (a renderer's output works as it is).  The tone map is
    :func:`tonemap`'s (``scale`` default: the ``percentile`` of all images' pixels together),
    drawn as a power norm so that the colour bar reads in radiance (``unit``).  ``axes``: a
    sequence of at least ``len(images)`` Axes to draw into instead of a new figure (for
    example a column of a larger figure); unused ones are hidden.
    """
    if not isinstance(images, Mapping) or not images:
        raise DifffogError("difffog.plot.image_grid: pass a non-empty dict {title: image}")
    arrays = {k: np.asarray(v, dtype=np.float64) for k, v in images.items()}
    for k, a in arrays.items():
        if a.ndim != 2:
            raise DifffogError(f"difffog.plot.image_grid: image {k!r} has shape {a.shape}; "
                               "pass 2-D (H, W) radiance images")
    if scale is None:
        scale = exposure(arrays, percentile)
    n = len(arrays)
    fig, flat, ncols = _panels(n, ncols, panel_size, axes, "image_grid", "images")
    norm = mcolors.PowerNorm(gamma=1.0 / gamma, vmin=0.0, vmax=float(scale), clip=True)
    im = None
    for i, (title, a) in enumerate(arrays.items()):
        ax = flat[i]
        # matplotlib's default interpolation: anti-aliased where a panel shows fewer screen
        # pixels than the image has
        im = ax.imshow(np.nan_to_num(a, nan=0.0), cmap="gray", norm=norm)
        ax.set_title(str(title), fontsize=9)
        _pixel_labels(ax, bottom=True, left=(i % ncols == 0))
    for ax in flat[n:]:
        ax.set_visible(False)
    if colorbar and im is not None:
        # ticks evenly spaced in grey level, labelled in radiance
        ticks = float(scale) * np.linspace(0.0, 1.0, 5) ** gamma
        cb = fig.colorbar(im, ax=flat[:n], shrink=0.85, ticks=ticks, format="%.3g",
                          label=f"radiance ({unit})")
        cb.ax.set_title(f"γ {gamma:g}", fontsize=8)
    if suptitle:
        fig.suptitle(suptitle)
    return fig


# --- errors against a reference ---------------------------------------------------------------

def error_map(image, reference, *, noise: float | None = None, relative: bool = True,
              min_reference: float | None = None, vmax: float | None = None,
              unit: str = RADIANCE_UNIT, title: str | None = None, ax=None) -> Figure:
    """Signed error of ``image`` against ``reference`` on a diverging colour map.

    relative=True: (image − reference) / reference, shown in % where the reference exceeds
    ``min_reference`` (default 1% of its mean; darker pixels are masked, grey); False: image −
    reference in radiance (``unit``).  The colour scale is symmetric, ±``vmax`` (default the
    99.5th percentile of |error|).  The title gives the relative RMSE (RMSE / mean reference)
    and the bias; with ``noise`` (the reference's per-pixel noise RMSE) also the RMSE with that
    noise removed in quadrature (:func:`image_errors`).
    """
    img = np.asarray(image, dtype=np.float64)
    ref = np.asarray(reference, dtype=np.float64)
    stats = image_errors(img, ref, noise)
    if relative:
        floor = 0.01 * float(ref.mean()) if min_reference is None else float(min_reference)
        ok = ref > floor
        err = np.where(ok, (img - ref) / np.where(ok, ref, 1.0), np.nan)
    else:
        err = img - ref
    finite = np.abs(err[np.isfinite(err)])
    if vmax is None:
        vmax = float(np.percentile(finite, 99.5)) if finite.size else 0.0
    vmax = vmax if vmax > 0 else (1e-3 if relative else 1e-6)
    if ax is None:
        fig, grid = _new_figure(1, 1, (4.6, 3.6))
        ax = grid[0, 0]
    fig = ax.figure
    cmap = matplotlib.colormaps["RdBu_r"].with_extremes(bad="#9a9a9a")
    im = ax.imshow(np.ma.masked_invalid(err), cmap=cmap, vmin=-vmax, vmax=vmax,
                   interpolation="nearest")
    # arrow ends on the colour bar where the colour scale clips larger errors
    extend = "both" if finite.size and finite.max() > vmax else "neither"
    if relative:
        cb = fig.colorbar(im, ax=ax, shrink=0.9, format=PercentFormatter(xmax=1.0, decimals=None),
                          label="(image − reference) / reference (%)", extend=extend)
    else:
        cb = fig.colorbar(im, ax=ax, shrink=0.9, label=f"image − reference ({unit})",
                          extend=extend)
    cb.ax.tick_params(labelsize=8)
    _pixel_labels(ax)
    line = f"rel. RMSE {100 * stats['rel_rmse']:.1f}%"
    if "rel_rmse_corr" in stats:
        line = (f"rel. RMSE {100 * stats['rel_rmse_corr']:.1f}% (reference noise "
                f"{100 * stats['ref_noise_rel']:.1f}% removed)")
    line += f"\nbias of the mean {100 * stats['bias']:+.1f}%"
    ax.set_title(f"{title}\n{line}" if title else line, fontsize=9)
    return fig


# --- the lattice ------------------------------------------------------------------------------

def _axis_index(axis) -> int:
    if isinstance(axis, str) and axis in _AXIS_NAMES:
        return _AXIS_NAMES.index(axis)
    if isinstance(axis, (int, np.integer)) and 0 <= int(axis) < 3:
        return int(axis)
    raise DifffogError(f"difffog.plot.lattice_slices: axis must be 'x', 'y', 'z' or 0, 1, 2, "
                       f"got {axis!r}")


def lattice_slices(lattice, field="node_type", *, axis="z", index=None, label: str | None = None,
                   cmap: str | None = None, log: bool = False, scene=None, ncols: int = 4,
                   axes=None, panel_size: tuple[float, float] = (3.4, 3.0)) -> Figure:
    """Slices of a lattice field perpendicular to ``axis`` at node ``index`` (an int, a list of
    ints for several panels, or None for the middle plane), in world coordinates (scene units).

    field: ``"node_type"`` (FREE / SURFACE / SOLID, with a legend), ``"material"`` (the shape
    of SOLID and SURFACE nodes; names from ``scene`` if given), ``"density"`` (fog density
    multiplier), ``"sdf"`` (signed distance, scene units), ``"normal"`` (SURFACE normals as
    RGB = (n + 1)/2 plus arrows of their in-plane part), or any (nx, ny, nz) array on this
    lattice, e.g. a :class:`~difffog.LightField`'s ``fluence`` or ``sun_fluence``, with
    ``label`` naming it and its unit (``log=True`` for a log colour scale).
    """
    a = _axis_index(axis)
    shape = tuple(lattice.shape)
    name = field if isinstance(field, str) else None
    known = ("node_type", "material", "density", "sdf", "normal")
    if name is not None:
        if name not in known:
            raise DifffogError(f"difffog.plot.lattice_slices: unknown field {name!r}; use one of "
                               f"{', '.join(known)} or pass an (nx, ny, nz) array")
        data = np.asarray(getattr(lattice, name))
    else:
        data = np.asarray(field)
        if data.shape != shape:
            raise DifffogError(f"difffog.plot.lattice_slices: the field has shape {data.shape}, "
                               f"the lattice {shape}; pass a field of this lattice (a model's "
                               "light field goes with model.lattice)")
    if index is None:
        indices = [shape[a] // 2]
    elif isinstance(index, (int, np.integer)):
        indices = [int(index)]
    else:
        indices = [int(i) for i in index]
    for i in indices:
        if not 0 <= i < shape[a]:
            raise DifffogError(f"difffog.plot.lattice_slices: index {i} is outside the lattice "
                               f"(0 .. {shape[a] - 1} along {_AXIS_NAMES[a]})")
    # the two in-plane axes, shown as (horizontal, vertical)
    u, v = [b for b in range(3) if b != a]
    origin = np.asarray(lattice.origin, dtype=np.float64)
    h = float(lattice.h)
    extent = (origin[u], origin[u] + h * shape[u], origin[v], origin[v] + h * shape[v])

    n = len(indices)
    # with axes given, their count is the row length (as image_grid with ncols=None)
    fig, flat, ncols = _panels(n, ncols if axes is None else None, panel_size, axes,
                               "lattice_slices", "slices")
    for ax in flat[n:]:
        ax.set_visible(False)

    def plane(arr, i):  # (n_v, n_u): rows along the vertical in-plane axis
        return np.take(arr, i, axis=a).T

    mappable, cb_label, handles = None, None, None
    if name == "node_type":
        cm = mcolors.ListedColormap(_NODE_COLOURS)
        kw = {"cmap": cm, "vmin": -0.5, "vmax": 2.5}
        handles = [Patch(facecolor=c, edgecolor="k", label=f"{lbl} ({k})")
                   for lbl, c, k in zip(_NODE_NAMES, _NODE_COLOURS,
                                        [int((data == t).sum()) for t in range(3)])]
    elif name == "material":
        ids = sorted(int(x) for x in np.unique(data) if x >= 0)
        base = matplotlib.colormaps["tab10"]
        palette = ["#f2f2f2"] + [base(i % 10) for i in range(max(ids, default=-1) + 1)]
        cm = mcolors.ListedColormap(palette)
        kw = {"cmap": cm, "vmin": -1.5, "vmax": len(palette) - 1.5}
        shapes = getattr(scene, "shapes", None)

        def shape_name(i):
            if shapes is not None and i < len(shapes):
                return shapes[i].name or f"shape {i}"
            return f"shape {i}"

        handles = [Patch(facecolor="#f2f2f2", edgecolor="k", label="FREE (no shape)")]
        handles += [Patch(facecolor=palette[i + 1], edgecolor="k", label=shape_name(i))
                    for i in ids]
    elif name == "normal":
        kw = {}
        cb_label = None
    else:
        if name == "density":
            cb_label = "fog density multiplier (dimensionless)"
            kw = {"cmap": cmap or "viridis", "vmin": 0.0}
        elif name == "sdf":
            lim = float(np.max(np.abs(data))) or 1.0
            cb_label = "signed distance to the geometry (scene units)"
            kw = {"cmap": cmap or "RdBu_r", "vmin": -lim, "vmax": lim}
        else:
            cb_label = label or "value"
            finite = data[np.isfinite(data)]
            if log:
                pos = finite[finite > 0]
                lo = float(pos.min()) if pos.size else 1e-6
                hi = float(pos.max()) if pos.size else 1.0
                kw = {"cmap": cmap or "magma",
                      "norm": mcolors.LogNorm(vmin=lo, vmax=max(hi, lo * 10))}
            else:
                kw = {"cmap": cmap or "magma",
                      "vmin": float(finite.min()) if finite.size else 0.0,
                      "vmax": float(finite.max()) if finite.size else 1.0}

    title = {"node_type": "node type"}.get(name, name)
    for k, i in enumerate(indices):
        ax = flat[k]
        if name == "normal":
            nrm = np.moveaxis(np.take(data, i, axis=a), 0, 1)  # (nv, nu, 3)
            mag = np.linalg.norm(nrm, axis=-1)
            rgb = np.where(mag[..., None] > 0, 0.5 * (nrm + 1.0), 0.95)
            ax.imshow(rgb, origin="lower", extent=extent, interpolation="nearest")
            vv, uu = np.nonzero(mag > 0)
            step = max(1, math.ceil(math.sqrt(len(vv) / 300))) if len(vv) else 1
            sel = slice(None, None, step)
            ax.quiver(origin[u] + (uu[sel] + 0.5) * h, origin[v] + (vv[sel] + 0.5) * h,
                      nrm[vv, uu, u][sel], nrm[vv, uu, v][sel], angles="xy", color="k",
                      width=0.004, scale=1.2 / h, scale_units="xy")
        else:
            mappable = ax.imshow(plane(data, i), origin="lower", extent=extent,
                                 interpolation="nearest", **kw)
        pos = origin[a] + (i + 0.5) * h
        where = f"{_AXIS_NAMES[a]} = {pos:.3g} (node {i})"
        ax.set_title(f"{title}, {where}" if title else where, fontsize=9)
        ax.set_xlabel(f"{_AXIS_NAMES[u]} (scene units)")
        if k % ncols == 0:
            ax.set_ylabel(f"{_AXIS_NAMES[v]} (scene units)")
        ax.set_aspect("equal")
    if handles is not None:
        flat[n - 1].legend(handles=handles, loc="upper left", bbox_to_anchor=(1.02, 1.0),
                           fontsize=8, title=("node type (nodes in lattice)" if name == "node_type"
                                              else "shape"), title_fontsize=8)
    elif name == "normal":
        fig.supxlabel("SURFACE normals n: colour RGB = (n + 1) / 2,\narrows = in-plane part of n",
                      fontsize=8)
    elif mappable is not None:
        fig.colorbar(mappable, ax=flat[:n], shrink=0.85, label=cb_label)
    return fig


# --- iteration and cost -----------------------------------------------------------------------

def _history(h) -> np.ndarray:
    res = getattr(h, "residuals", None)
    if res is not None:  # a LightField: its residuals up to the iterations run
        k = int(np.asarray(h.iterations))
        return np.asarray(res, dtype=np.float64)[:k]
    arr = np.asarray(h, dtype=np.float64).ravel()
    return arr[np.isfinite(arr)]


def convergence(history, *, tol: float | None = None, label: str | None = None,
                ylabel: str | None = None, xlabel: str = "application of K (six face sweeps)",
                ax=None) -> Figure:
    """Residual history on a log scale against the applications of the light operator K.

    The solver's ``residuals`` are, per application of K, GMRES's relative residual (the
    default method) or Jacobi's relative change (``method="jacobi"``); ``ylabel`` defaults to
    saying so.

    history: a :class:`~difffog.LightField` (its ``residuals`` up to ``iterations``), a 1-D
    array (NaNs past the end are dropped), or a dict ``{label: either}`` for several curves.
    tol: drawn as a horizontal line (the solver's stopping tolerance on the estimated error).
    """
    curves = dict(history) if isinstance(history, Mapping) else {label: history}
    if ax is None:
        fig, grid = _new_figure(1, 1, (5.0, 3.4))
        ax = grid[0, 0]
    fig = ax.figure
    for lbl, h in curves.items():
        y = _history(h)
        y = np.where(y > 0, y, np.nan)
        ax.semilogy(np.arange(1, len(y) + 1), y, marker="." if len(y) < 60 else None,
                    label=None if lbl is None else str(lbl))
    if tol is not None:
        ax.axhline(tol, color="k", ls=":", lw=1, label=f"tolerance {tol:g}")
    ax.set_xlabel(xlabel)
    ax.set_ylabel(ylabel or "relative residual (GMRES) / change (Jacobi)")
    ax.grid(True, which="both", alpha=0.3)
    if any(lbl is not None for lbl in curves) or tol is not None:
        ax.legend(fontsize=8)
    return fig


def pareto_front(points) -> np.ndarray:
    """Indices of the non-dominated points of ``points`` ((n, 2): cost, error; lower is better),
    sorted by cost: no other point is at most as costly and at most as wrong, and better in
    one."""
    p = np.asarray(points, dtype=np.float64).reshape(-1, 2)
    order = np.lexsort((p[:, 1], p[:, 0]))
    front, best = [], np.inf
    for i in order:
        if p[i, 1] < best:
            front.append(int(i))
            best = p[i, 1]
    return np.asarray(front, dtype=int)


def pareto(rows: Sequence[Mapping] | Mapping[str, Sequence], *, x: str = "time_s",
           y: str = "error", group: str | None = "solver", annotate: str | None = None,
           front: bool = True, xlabel: str | None = None, ylabel: str | None = None,
           ax=None) -> Figure:
    """Cost against error, log-log, one labelled curve per ``group`` (e.g. per solver).

    rows: a list of dicts (rows of a benchmark CSV; numbers may be strings) or a dict of
    columns.  Each group's points are joined in order of ``x``; ``annotate`` names a column
    whose value is written beside each point (e.g. ``"N"``); ``front=True`` also draws the
    Pareto front over all groups (the settings that no other one beats in both time and
    error).  Axis labels come from the column names (``time_s`` → "time (s)", ...) unless given.
    """
    if isinstance(rows, Mapping):
        keys = list(rows)
        rows = [dict(zip(keys, vals)) for vals in zip(*(rows[k] for k in keys))]
    rows = list(rows)
    if not rows:
        raise DifffogError("difffog.plot.pareto: no rows to plot")
    for col in (x, y) + ((group,) if group else ()):
        if col not in rows[0]:
            raise DifffogError(f"difffog.plot.pareto: rows have no column {col!r}; they have "
                               f"{', '.join(map(str, rows[0]))}")
    groups: dict[str, list[Mapping]] = {}
    for r in rows:
        groups.setdefault(str(r[group]) if group else "", []).append(r)
    if ax is None:
        fig, grid = _new_figure(1, 1, (5.4, 3.8))
        ax = grid[0, 0]
    fig = ax.figure
    all_pts = []
    for name, rs in groups.items():
        pts = np.array([[float(r[x]), float(r[y])] for r in rs])
        order = np.argsort(pts[:, 0], kind="stable")
        ax.loglog(pts[order, 0], pts[order, 1], marker="o", ms=4, label=name or None)
        if annotate:
            for j in order:
                ax.annotate(str(rs[j][annotate]), pts[j], textcoords="offset points",
                            xytext=(4, 3), fontsize=7)
        all_pts.append(pts)
    pts = np.concatenate(all_pts)
    if front and len(pts) > 1:
        idx = pareto_front(pts)
        ax.step(pts[idx, 0], pts[idx, 1], where="post", color="k", ls="--", lw=1,
                label="Pareto front")
    ax.set_xlabel(xlabel or _LABELS.get(x, x))
    ax.set_ylabel(ylabel or _LABELS.get(y, y))
    ax.grid(True, which="both", alpha=0.3)
    if len(groups) > 1 or (group and next(iter(groups))) or front:
        ax.legend(fontsize=8, title=group if group else None, title_fontsize=8)
    return fig
