"""The command line: outputs on disk, exit codes and one-line errors."""

import json
import subprocess
import sys

import numpy as np
import pytest

from difffog._cli import main


def test_info_summarizes_scene(capsys):
    assert main(["info", "fog-balls", "-N", "24", "-M", "2"]) == 0
    out = capsys.readouterr().out
    assert "24x24x24 nodes" not in out  # the lattice carries the vacuum margin around open sides
    assert "30x30x30 nodes" in out
    for needle in ("free", "surface", "solid", "opt.depth", "sun", "camera     top",
                   "anisotropic phase: no", "sun: yes"):
        assert needle in out


def test_info_periodic_slab_has_no_lateral_margin(capsys):
    assert main(["info", "slab", "-N", "16", "-M", "2"]) == 0
    assert "16x16x22 nodes" in capsys.readouterr().out


@pytest.mark.parametrize(
    "argv,needle",
    [
        (["info", "no-such-scene"], "no built-in scene of that name"),
        (["info", "fog-balls", "--set", "fog.scater=1"], "Did you mean 'fog.scattering'"),
        (["info", "fog-balls", "--set", "fog.scattering=-1"], "fog.scattering"),
        (["render", "fog-balls", "--camera", "nope", "--out", "OUT"], "has no camera 'nope'"),
        (["render", "fog-balls", "-N", "0", "--out", "OUT"], "--resolution must be a positive"),
        (["render", "fog-balls", "--tol", "-1", "--out", "OUT"], "--tol must be a positive"),
    ],
)
def test_errors_are_one_line_and_exit_2(argv, needle, capsys, tmp_path):
    argv = [str(tmp_path / "o") if a == "OUT" else a for a in argv]
    assert main(argv) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("difffog: error:") and needle in err[0]
    assert not (tmp_path / "o").exists()  # nothing half-written


def test_render_writes_images_and_report(tmp_path, capsys):
    out = tmp_path / "furnace"
    assert main(["render", "furnace", "-N", "12", "-M", "2", "--tol", "1e-5", "--out", str(out),
                 "--supersample", "1"]) == 0
    files = sorted(p.name for p in out.iterdir())
    assert files == ["inside.npy", "inside.png", "report.json"]
    img = np.load(out / "inside.npy")
    assert img.dtype == np.float32 and img.shape == (64, 64)  # (height, width)
    np.testing.assert_allclose(img, 10.0, rtol=0.02)  # exact answer of the furnace: 1/(1-0.9)
    rep = json.loads((out / "report.json").read_text())
    assert rep["settings"]["resolution"] == 12 and rep["settings"]["solver_options"]["M"] == 2
    assert rep["iterations"] == len(rep["residuals"]) > 10
    assert rep["error_estimate"] < 1e-5
    assert set(rep["timings_s"]) >= {"voxelize_s", "solve_s", "render_s", "solve_compile_s"}
    assert rep["peak_memory_mb"] > 0
    assert not list(tmp_path.glob(".difffog-*"))  # the staging folder is gone


def test_render_fixed_iterations_and_override(tmp_path):
    out = tmp_path / "o"
    args = ["render", "furnace", "-N", "12", "-M", "2", "--iterations", "3", "-q",
            "--set", "shape.walls.albedo=0.5", "--set", "fog.scattering=0", "--supersample", "1"]
    assert main(args + ["--method", "jacobi", "--out", str(out)]) == 0
    rep = json.loads((out / "report.json").read_text())
    assert rep["iterations"] == 3
    assert rep["overrides"] == ["shape.walls.albedo=0.5", "fog.scattering=0"]
    assert rep["settings"]["solver_options"]["method"] == "jacobi"
    assert any("volume" in line for line in rep["settings"]["plan"])
    # an empty furnace of albedo 0.5 after 3 Jacobi iterations: B = 1 + 0.5·(1 + 0.5·(1 + 0.5))
    assert float(np.load(out / "inside.npy").mean()) == pytest.approx(1.875, rel=0.02)
    # GMRES (the default) has the exact 1/(1 - 0.5) = 2 after the same 3 applications
    assert main(args + ["--out", str(tmp_path / "g")]) == 0
    assert float(np.load(tmp_path / "g" / "inside.npy").mean()) == pytest.approx(2.0, rel=1e-3)


def test_console_script_entry_point():
    r = subprocess.run([sys.executable, "-m", "difffog._cli", "info", "slab", "-N", "8", "-M", "1"],
                       capture_output=True, text=True, timeout=120)
    assert r.returncode == 0 and "slab" in r.stdout


def test_render_with_the_splat_solver(tmp_path):
    out = tmp_path / "splat"
    assert main(["render", "translucent-cube", "--solver", "splat", "-N", "12", "--sheets", "10",
                 "--camera", "top", "-q", "--out", str(out)]) == 0
    assert sorted(p.name for p in out.iterdir()) == ["report.json", "top.npy", "top.png"]
    img = np.load(out / "top.npy")
    assert img.dtype == np.float32 and img.shape == (128, 128) and np.isfinite(img).all()
    rep = json.loads((out / "report.json").read_text())
    assert rep["settings"]["solver"] == "splat" and rep["passes"]["top"]["sheets"] == 10
    assert "iterations" not in rep and rep["settings"]["supersample"] == 1
    # the lit ground in the top-left corner: ρ/π·(E·cos 40° + π·sky), no fog above it
    assert float(img[0, 0]) == pytest.approx(0.6 / np.pi * (3.0 * np.cos(np.radians(40.0))
                                                             + np.pi * 0.2), rel=1e-3)


@pytest.mark.parametrize(
    "argv,needle",
    [
        (["render", "furnace", "--solver", "splat", "--out", "OUT"], "no [sun]"),
        (["render", "fog-balls", "--sheets", "8", "--out", "OUT"], "--sheets applies to"),
        (["render", "fog-balls", "--solver", "splat", "--sheets", "0", "--out", "OUT"],
         "--sheets must be a positive"),
    ],
)
def test_splat_errors_are_one_line(argv, needle, capsys, tmp_path):
    argv = [str(tmp_path / "o") if a == "OUT" else a for a in argv]
    assert main(argv) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and needle in err[0]


# ------------------------------------------------------------------ difffog fit
FIT_SMALL = ["fog-balls", "--set", "shape.walls.thickness=0.1", "-N", "12", "-M", "2",
             "--downsample", "8"]


@pytest.fixture(scope="module")
def fit_targets(tmp_path_factory):
    """Targets of the small fog-balls (ζ = 2, γ = 0.5) rendered by the fit's own model."""
    from difffog import load_scene
    from difffog._fit import make_forward

    scene = load_scene("fog-balls", ["shape.walls.thickness=0.1"])
    fwd = make_forward(scene, "sweep", cameras=["top", "oblique"], resolution=12,
                       directions=2, downsample=8)
    d = tmp_path_factory.mktemp("targets")
    for k, v in fwd(fwd.params()).items():
        np.save(d / f"{k}.npy", np.asarray(v))
    return d


@pytest.mark.slow  # a whole fit through the CLI; test_fit.py covers the fit itself
def test_fit_writes_estimates_plots_and_residuals(fit_targets, tmp_path, capsys):
    out = tmp_path / "fit"
    argv = ["fit", *FIT_SMALL, "--target", f"top={fit_targets / 'top.npy'}",
            "--target", f"oblique={fit_targets / 'oblique.npy'}",
            "--unknown", "fog.scattering=1.2", "--unknown", "fog.absorption=0.8",
            "--out", str(out)]
    assert main(argv) == 0
    files = sorted(p.name for p in out.iterdir())
    assert files == sorted(["fit.json", "convergence.png"] + [
        f"{c}_{k}" for c in ("top", "oblique")
        for k in ("fit.npy", "target.npy", "residual.npy", "fit.png")])
    rep = json.loads((out / "fit.json").read_text())
    assert rep["estimates"]["fog.scattering"] == pytest.approx(2.0, rel=1e-3)
    assert rep["estimates"]["fog.absorption"] == pytest.approx(0.5, rel=1e-3)
    assert set(rep["stderr"]) == {"fog.scattering", "fog.absorption"}
    assert len(rep["correlation"]) == 2 and rep["converged"]
    assert len(rep["history"]) == rep["iterations"] >= 2
    fitted, target = np.load(out / "top_fit.npy"), np.load(out / "top_target.npy")
    np.testing.assert_allclose(np.load(out / "top_residual.npy"), fitted - target, atol=1e-7)
    assert not (tmp_path / ".fit.fit-checkpoint.npz").exists()  # removed after success
    assert "fog.scattering" in capsys.readouterr().out


@pytest.mark.slow
def test_fit_resume_continues_a_stopped_fit(fit_targets, tmp_path):
    out = tmp_path / "fit"
    argv = ["fit", *FIT_SMALL, "--target", f"top={fit_targets / 'top.npy'}",
            "--unknown", "fog.scattering=1.2", "--unknown", "fog.absorption=0.8",
            "--out", str(out), "-q"]
    assert main(argv) == 0
    whole = json.loads((out / "fit.json").read_text())
    out2 = tmp_path / "fit2"
    argv2 = [a if a != str(out) else str(out2) for a in argv]
    assert main(argv2 + ["--max-steps", "2"]) == 1  # stopped early: exit 1, checkpoint kept
    assert (tmp_path / ".fit2.fit-checkpoint.npz").exists()
    assert main(argv2 + ["--resume"]) == 0
    resumed = json.loads((out2 / "fit.json").read_text())
    assert resumed["estimates"] == whole["estimates"]
    assert [h["values"] for h in resumed["history"]] == [h["values"] for h in whole["history"]]


@pytest.mark.parametrize("extra,needle", [
    (["--target", "top=MISSING.npy", "--unknown", "fog.scattering"], "no such file"),
    (["--target", "side=T.npy", "--unknown", "fog.scattering"], "has no camera 'side'"),
    (["--target", "top=T.npy", "--unknown", "fog.scatter"], "Did you mean 'fog.scattering'"),
    (["--target", "top=T.npy"], "at least one --unknown"),
    (["--target", "top=BAD.npy", "--unknown", "fog.scattering"], "expected (height, width)"),
    (["--target", "top=T.npy", "--unknown", "fog.scattering=abc"], "not a number"),
    (["--target", "top=T.npy", "--unknown", "fog.scattering", "--resume"], "no checkpoint"),
    (["--target", "top=T.npy", "--unknown", "fog.scattering", "--bounds",
      "fog.scattering=3,9"], "outside"),
])
def test_fit_errors_are_one_line_and_exit_2(extra, needle, tmp_path, capsys):
    np.save(tmp_path / "T.npy", np.ones((128, 128), np.float32))
    np.save(tmp_path / "BAD.npy", np.ones((100, 128), np.float32))
    extra = [a.replace("T.npy", str(tmp_path / "T.npy")).replace(
        "BAD.npy", str(tmp_path / "BAD.npy")).replace("MISSING.npy", str(tmp_path / "M.npy"))
        for a in extra]
    argv = ["fit", *FIT_SMALL, *extra, "--out", str(tmp_path / "o")]
    assert main(argv) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("difffog: error:") and needle in err[0], err
    assert not (tmp_path / "o").exists()
