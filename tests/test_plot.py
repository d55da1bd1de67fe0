"""difffog.plot: shared tone map, error maps, lattice slices, convergence and Pareto plots.

Every figure is also drawn (saved to memory): with ``filterwarnings = error`` a layout or
colour-map warning fails the test.
"""

import io
import subprocess
import sys
from types import SimpleNamespace

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
import pytest  # noqa: E402
from matplotlib.figure import Figure  # noqa: E402

from difffog import DifffogError, _image, load_scene, plot, voxelize  # noqa: E402
from difffog._output import save_image  # noqa: E402
from difffog.geometry._lattice import FREE, SOLID, SURFACE  # noqa: E402


@pytest.fixture(autouse=True)
def no_open_figures():
    before = plt.get_fignums()
    yield
    assert plt.get_fignums() == before, "difffog.plot left a pyplot figure open"


def _draw(fig):
    assert isinstance(fig, Figure)
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=40)
    assert buf.getvalue()[:4] == b"\x89PNG"


def _images():
    rng = np.random.default_rng(0)
    bright = rng.uniform(0.0, 4.0, (12, 16))
    dim = rng.uniform(0.0, 0.5, (10, 10))
    return {"bright": bright, "dim": dim}


@pytest.fixture(scope="module")
def lattice():
    # fog-balls with walls thick enough for N = 12 (no thin-wall warning)
    scene = load_scene("fog-balls", ["shape.walls.thickness=0.1"])
    return scene, voxelize(scene, 12, 2, margin=3)


def test_import_difffog_does_not_import_matplotlib():
    code = ("import sys, difffog; assert 'matplotlib' not in sys.modules; "
            "difffog.plot.tonemap; assert 'matplotlib' in sys.modules")
    subprocess.run([sys.executable, "-c", code], check=True)


# --- tone map ---------------------------------------------------------------------------------

def _cli_tonemap(img):
    """The command line's PNG tone map as 0.1 wrote it: 99.5th percentile, clip, gamma 2.2."""
    scale = float(np.percentile(img, 99.5)) or 1.0
    x = np.clip(img / scale, 0.0, 1.0) ** (1 / 2.2)
    return (x * 255 + 0.5).astype(np.uint8)


def test_tonemap_of_one_image_is_the_command_lines(tmp_path):
    from skimage import io as skio

    img = _images()["bright"].astype(np.float32)
    out, scale = plot.tonemap(img)
    assert out.dtype == np.uint8
    np.testing.assert_array_equal(out, _cli_tonemap(img))
    assert scale == pytest.approx(np.percentile(img, 99.5))
    # the PNG the command line writes (render, fit) is this tone map
    save_image(tmp_path, "x", img)
    np.testing.assert_array_equal(skio.imread(tmp_path / "x.png"), out)
    np.testing.assert_array_equal(np.load(tmp_path / "x.npy"), img)
    # difffog.plot re-exports the NumPy-only image functions
    assert plot.tonemap is _image.tonemap and plot.image_errors is _image.image_errors
    assert plot.exposure is _image.exposure


def test_tonemap_shares_one_scale_across_images():
    images = _images()
    out, scale = plot.tonemap(images, dtype="float")
    pooled = np.concatenate([a.ravel() for a in images.values()])
    assert scale == pytest.approx(np.percentile(pooled, 99.5))
    for k, a in images.items():
        np.testing.assert_allclose(out[k], np.clip(a / scale, 0, 1) ** (1 / 2.2))
    # the dim image stays dim under the shared exposure (its own would make it white)
    assert out["dim"].max() < 0.6 and out["bright"].max() == 1.0
    # lists keep their order and structure
    lst, s2 = plot.tonemap(list(images.values()), dtype="float")
    assert s2 == scale and np.array_equal(lst[1], out["dim"])


def test_tonemap_edge_cases():
    black, s = plot.tonemap(np.zeros((3, 3)))
    assert s == 1.0 and black.max() == 0
    img = np.array([[np.nan, 1.0], [2.0, np.inf]])
    out, s = plot.tonemap(img, scale=2.0, dtype="float")
    np.testing.assert_allclose(out, [[0.0, 0.5 ** (1 / 2.2)], [1.0, 1.0]])
    with pytest.raises(DifffogError, match="^tonemap: dtype must be 'uint8' or 'float'"):
        plot.tonemap(img, dtype="uint16")
    with pytest.raises(DifffogError, match="^tonemap: scale must be a positive"):
        plot.tonemap(img, scale=0.0)
    with pytest.raises(DifffogError, match=r"^percentile must be in \(0, 100\]"):
        plot.tonemap(img, percentile=0.0)
    with pytest.raises(DifffogError, match="^no images given"):
        plot.tonemap([])


# --- image grid -------------------------------------------------------------------------------

def test_image_grid_uses_one_tone_map_and_labels_everything():
    images = _images()
    fig = plot.image_grid(images)
    _draw(fig)
    axes = [ax for ax in fig.axes if ax.images]
    assert [ax.get_title() for ax in axes] == ["bright", "dim"]
    scale = plot.exposure(images)
    for ax, (k, a) in zip(axes, images.items()):
        im = ax.images[0]
        assert im.norm.vmin == 0.0 and im.norm.vmax == pytest.approx(scale)
        assert im.norm.gamma == pytest.approx(1 / 2.2)
        np.testing.assert_array_equal(im.get_array(), a)
        assert ax.get_xlabel() == "column (pixels)"
    assert axes[0].get_ylabel() == "row (pixels)"
    colorbars = [ax for ax in fig.axes if not ax.images]
    assert len(colorbars) == 1 and plot.RADIANCE_UNIT in colorbars[0].get_ylabel()
    # Jupyter shows it without pyplot
    assert isinstance(fig, plot.PlotFigure) and fig._repr_png_()[:4] == b"\x89PNG"
    # the grey level shown is the tone map's
    out, _ = plot.tonemap(images, dtype="float")
    np.testing.assert_allclose(axes[1].images[0].norm(images["dim"]), out["dim"], atol=1e-12)


def test_image_grid_draws_into_given_axes_and_checks_input():
    fig = Figure()
    axes = fig.subplots(2, 2).ravel()
    got = plot.image_grid(_images(), axes=axes, scale=2.0, colorbar=False)
    assert got is fig
    assert axes[0].images[0].norm.vmax == 2.0 and not axes[2].get_visible()
    _draw(fig)
    with pytest.raises(DifffogError, match="2 images but 1 axes"):
        plot.image_grid(_images(), axes=[axes[0]])
    with pytest.raises(DifffogError, match="2-D"):
        plot.image_grid({"cube": np.zeros((2, 2, 2))})
    with pytest.raises(DifffogError, match="non-empty dict"):
        plot.image_grid({})


# --- error map --------------------------------------------------------------------------------

def test_error_map_shows_signed_relative_error_where_the_reference_is_bright():
    rng = np.random.default_rng(1)
    ref = rng.uniform(0.5, 2.0, (8, 9))
    ref[0, :3] = 0.0  # dark pixels: masked, not divided by
    img = ref * (1 + rng.normal(0, 0.1, ref.shape)) + 0.01
    fig = plot.error_map(img, ref, noise=0.02, title="case")
    _draw(fig)
    ax = fig.axes[0]
    data = ax.images[0].get_array()
    ok = ref > 0.01 * ref.mean()
    assert not ok[0, :3].any() and data.mask[0, :3].all()
    np.testing.assert_allclose(data[ok], (img[ok] - ref[ok]) / ref[ok])
    lo, hi = ax.images[0].get_clim()
    assert lo == -hi and hi > 0 and ax.images[0].get_cmap().name.startswith("RdBu")
    cbar = fig.axes[1]
    assert "(image − reference) / reference (%)" == cbar.get_ylabel()
    # the scale is the 99.5th percentile of |error|: the largest errors are clipped, and
    # the colour bar says so; a wide enough scale clips nothing
    assert np.nanmax(np.abs(data.filled(np.nan))) > hi
    assert ax.images[0].colorbar.extend == "both"
    wide = plot.error_map(img, ref, vmax=10.0)
    assert wide.axes[0].images[0].colorbar.extend == "neither"
    stats = plot.image_errors(img, ref, noise=0.02)
    rmse = np.sqrt(np.mean((img - ref) ** 2))
    assert stats["rel_rmse"] == pytest.approx(rmse / ref.mean())
    assert stats["rel_rmse_corr"] == pytest.approx(np.sqrt(rmse**2 - 0.02**2) / ref.mean())
    assert stats["bias"] == pytest.approx(img.mean() / ref.mean() - 1)
    title = ax.get_title()
    assert title.startswith("case") and f"rel. RMSE {100 * stats['rel_rmse_corr']:.1f}%" in title
    assert f"{100 * stats['bias']:+.1f}%" in title
    assert ax.get_xlabel() == "column (pixels)" and ax.get_ylabel() == "row (pixels)"


def test_error_map_absolute_and_bad_input():
    ref = np.full((4, 4), 2.0)
    img = ref + np.arange(16).reshape(4, 4) / 16
    fig = Figure()
    ax = fig.subplots()
    assert plot.error_map(img, ref, relative=False, ax=ax) is fig
    np.testing.assert_allclose(ax.images[0].get_array(), img - ref)
    assert fig.axes[1].get_ylabel() == f"image − reference ({plot.RADIANCE_UNIT})"
    _draw(fig)
    with pytest.raises(DifffogError, match="differ in shape"):
        plot.error_map(img, np.ones((3, 3)))
    with pytest.raises(DifffogError, match="mean radiance is not positive"):
        plot.error_map(img, np.zeros((4, 4)))
    # image_errors (difffog._image) says what is wrong without a "difffog.plot:" prefix
    with pytest.raises(DifffogError,
                       match=r"^image \(4, 4\) and reference \(3, 3\) differ in shape"):
        _image.image_errors(img, np.ones((3, 3)))
    with pytest.raises(DifffogError, match="^the reference's mean radiance is not positive"):
        _image.image_errors(img, np.zeros((4, 4)))


# --- lattice slices ---------------------------------------------------------------------------

def test_lattice_slices_node_types_with_legend_and_world_axes(lattice):
    _, lat = lattice
    k = lat.shape[2] // 2
    fig = plot.lattice_slices(lat, "node_type", axis="z", index=[k, k + 2])
    _draw(fig)
    panels = [ax for ax in fig.axes if ax.images]
    assert len(panels) == 2
    np.testing.assert_array_equal(panels[0].images[0].get_array(), lat.node_type[:, :, k].T)
    np.testing.assert_array_equal(panels[1].images[0].get_array(), lat.node_type[:, :, k + 2].T)
    x0, x1, y0, y1 = panels[0].images[0].get_extent()
    assert (x0, y0) == pytest.approx((lat.origin[0], lat.origin[1]))
    assert (x1, y1) == pytest.approx((lat.origin[0] + lat.h * lat.shape[0],
                                      lat.origin[1] + lat.h * lat.shape[1]))
    assert panels[0].get_xlabel() == "x (scene units)"
    assert panels[0].get_ylabel() == "y (scene units)"
    z = lat.origin[2] + (k + 0.5) * lat.h
    assert panels[0].get_title() == f"node type, z = {z:.3g} (node {k})"
    labels = [t.get_text() for t in panels[-1].get_legend().get_texts()]
    counts = lat.counts()
    assert labels == [f"FREE ({counts['free']})", f"SURFACE ({counts['surface']})",
                      f"SOLID ({counts['solid']})"]
    assert (FREE, SURFACE, SOLID) == (0, 1, 2)  # the colour map's order


def test_lattice_slices_other_fields(lattice):
    scene, lat = lattice
    fig = plot.lattice_slices(lat, "density", axis="x")
    _draw(fig)
    assert fig.axes[-1].get_ylabel() == "fog density multiplier (dimensionless)"
    np.testing.assert_array_equal(fig.axes[0].images[0].get_array(),
                                  lat.density[lat.shape[0] // 2].T)
    assert (fig.axes[0].get_xlabel(), fig.axes[0].get_ylabel()) == ("y (scene units)",
                                                                     "z (scene units)")
    fig = plot.lattice_slices(lat, "material", axis="y", scene=scene)
    _draw(fig)
    labels = [t.get_text() for t in fig.axes[0].get_legend().get_texts()]
    assert labels[0] == "FREE (no shape)" and set(labels[1:]) <= {s.name for s in scene.shapes}
    fig = plot.lattice_slices(lat, "normal", axis="z")
    _draw(fig)
    assert len(fig.axes[0].collections) == 1  # the arrows
    field = np.arange(np.prod(lat.shape), dtype=float).reshape(lat.shape) + 1
    fig = plot.lattice_slices(lat, field, axis="y", index=3, label="fluence (W m⁻²)", log=True)
    _draw(fig)
    np.testing.assert_array_equal(fig.axes[0].images[0].get_array(), field[:, 3, :].T)
    assert fig.axes[-1].get_ylabel() == "fluence (W m⁻²)"


def test_lattice_slices_reject_bad_requests(lattice):
    _, lat = lattice
    with pytest.raises(DifffogError, match="unknown field 'colour'"):
        plot.lattice_slices(lat, "colour")
    with pytest.raises(DifffogError, match="axis must be"):
        plot.lattice_slices(lat, axis="w")
    with pytest.raises(DifffogError, match="outside the lattice"):
        plot.lattice_slices(lat, index=lat.shape[2])
    with pytest.raises(DifffogError, match="model.lattice"):
        plot.lattice_slices(lat, np.zeros((2, 2, 2)))


# --- convergence and Pareto -------------------------------------------------------------------

def test_convergence_plots_the_residuals_run_on_a_log_axis():
    res = np.array([1.0, 0.3, 0.1, 0.03, np.nan, np.nan])
    light = SimpleNamespace(residuals=res, iterations=np.int32(4))
    fig = plot.convergence({"light field": light, "array": res[:3]}, tol=1e-2)
    _draw(fig)
    ax = fig.axes[0]
    assert ax.get_yscale() == "log"
    (l0, l1, tol) = ax.get_lines()
    np.testing.assert_array_equal(l0.get_xdata(), [1, 2, 3, 4])
    np.testing.assert_array_equal(l0.get_ydata(), res[:4])
    np.testing.assert_array_equal(l1.get_ydata(), res[:3])
    assert tol.get_ydata()[0] == 1e-2
    assert ax.get_xlabel() == "application of K (six face sweeps)"
    assert "GMRES" in ax.get_ylabel() and "Jacobi" in ax.get_ylabel()
    assert [t.get_text() for t in ax.get_legend().get_texts()] == ["light field", "array",
                                                                   "tolerance 0.01"]


def test_pareto_front_and_plot():
    pts = np.array([[1.0, 0.5], [2.0, 0.2], [3.0, 0.3], [4.0, 0.05], [0.5, 0.9], [2.0, 0.25]])
    np.testing.assert_array_equal(plot.pareto_front(pts), [4, 0, 1, 3])
    rows = [{"solver": "sweep", "time_s": str(t), "error": str(e), "N": n}  # as read from a CSV
            for (t, e), n in zip(pts[:4], (16, 32, 48, 64))]
    rows += [{"solver": "mitsuba", "time_s": t, "error": e, "N": n}
             for (t, e), n in zip(pts[4:], (4, 16))]
    fig = plot.pareto(rows, annotate="N")
    _draw(fig)
    ax = fig.axes[0]
    assert ax.get_xscale() == "log" and ax.get_yscale() == "log"
    assert ax.get_xlabel() == "time (s)" and ax.get_ylabel() == "relative error"
    legend = [t.get_text() for t in ax.get_legend().get_texts()]
    assert legend == ["sweep", "mitsuba", "Pareto front"]
    sweep = ax.get_lines()[0]
    np.testing.assert_array_equal(sweep.get_xdata(), [1.0, 2.0, 3.0, 4.0])  # joined by time
    np.testing.assert_array_equal(sweep.get_ydata(), [0.5, 0.2, 0.3, 0.05])
    assert sorted(t.get_text() for t in ax.texts) == sorted(["16", "32", "48", "64", "4", "16"])
    front = ax.get_lines()[2]
    np.testing.assert_array_equal(front.get_xdata(), [0.5, 1.0, 2.0, 4.0])
    # a dict of columns works too, and names its axes from unknown columns as they are
    fig = plot.pareto({"cost": [1, 2], "err": [0.2, 0.1]}, x="cost", y="err", group=None,
                      front=False)
    _draw(fig)
    assert fig.axes[0].get_xlabel() == "cost" and fig.axes[0].get_legend() is None
    with pytest.raises(DifffogError, match="no column 'error'"):
        plot.pareto([{"time_s": 1.0}])
