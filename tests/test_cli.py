"""The command line: outputs on disk, exit codes and one-line errors."""

import gc
import json
import math
import re
import subprocess
import sys

import jax
import numpy as np
import pytest

from difffog.cli import main


def test_info_summarizes_scene(capsys):
    frozen = gc.get_freeze_count()
    assert main(["info", "fog-balls", "-N", "24", "-M", "2"]) == 0
    assert gc.get_freeze_count() == frozen  # only the program itself freezes its imports
    out = capsys.readouterr().out
    # the lattice carries two vacuum nodes around open sides (VACUUM_MARGIN)
    assert "24x24x24 nodes" not in out and "28x28x28 nodes" in out
    for needle in ("free", "surface", "solid", "opt.depth", "sun", "camera     top",
                   "anisotropic phase: no", "sun: yes"):
        assert needle in out
    if jax.default_backend() == "cpu":  # which program sweeps the step scheme, and why
        from difffog.forward.sweep import _native

        assert (("sweep kernel: loop (native C++)" in out) == _native.available())
        assert "loop (native C++)" in out or "loop (XLA loop: " in out


def test_info_names_the_phase_order_of_a_forward_scattering_fog(capsys):
    assert main(["info", "cloud-plane", "-N", "16", "-M", "2", "--phase-order", "2"]) == 0
    out = capsys.readouterr().out
    assert "(L+1)² = 9 angular moments" in out and "g^(L+1) = 0.614" in out


def test_info_names_the_once_scattered_sweep(capsys):
    """--once-M: info says what the extra sweep costs (the lattice keeps its two vacuum
    nodes); an isotropic fog has nothing to refine (no line)."""
    assert main(["info", "cloud-plane", "-N", "16", "-M", "2", "--once-M", "5"]) == 0
    out = capsys.readouterr().out
    assert "20x20x20 nodes" in out and "2 vacuum nodes" in out
    assert "once-scattered light on M = 5 (121 directions per face" in out
    assert main(["info", "fog-balls", "-N", "24", "-M", "2", "--once-M", "5"]) == 0
    out = capsys.readouterr().out
    assert "28x28x28 nodes" in out and "once-scattered" not in out


def test_info_periodic_slab_has_no_lateral_margin(capsys):
    assert main(["info", "slab", "-N", "16", "-M", "2"]) == 0
    assert "16x16x20 nodes" in capsys.readouterr().out


@pytest.mark.parametrize(
    "argv,needle",
    [
        (["info", "no-such-scene"], "no built-in scene of that name"),
        (["info", "fog-balls", "--set", "fog.scater=1"], "Did you mean 'fog.scattering'"),
        (["info", "fog-balls", "--set", "fog.scattering=-1"], "fog.scattering"),
        (["render", "fog-balls", "--camera", "nope", "--out", "OUT"], "has no camera 'nope'"),
        (["render", "fog-balls", "-N", "0", "--out", "OUT"], "--resolution must be a positive"),
        (["render", "fog-balls", "--tol", "-1", "--out", "OUT"], "--tol must be a positive"),
        (["render", "cloud-plane", "--set", "sun.angular_radius_deg=2", "--out", "OUT"],
         "treats the sun as a point"),
        (["render", "cloud-plane", "--phase-order", "-1", "--out", "OUT"], "phase_order"),
        (["render", "cloud-plane", "--solver", "splat", "--phase-order", "2", "--out", "OUT"],
         "--phase-order does not apply to --solver splat"),
        (["render", "cloud-plane", "--once-M", "0", "--out", "OUT"],
         "--once-M must be a positive integer"),
        (["render", "cloud-plane", "--solver", "splat", "--once-M", "6", "--out", "OUT"],
         "--once-M does not apply to --solver splat"),
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
    assert rep["result"] == "successful"
    assert set(rep["timings_s"]) >= {"voxelize_s", "light_s", "images_s", "light_compile_s"}
    assert rep["peak_memory_mb"] > 0
    assert not list(tmp_path.glob(".difffog-*"))  # the staging folder is gone
    assert rep["machine"]["backend"] == jax.default_backend() and rep["machine"]["devices"] >= 1
    assert rep["settings"]["solver_options"]["kernel"] in ("loop", "batched")


@pytest.mark.slow  # 20-27 s of two subprocess renders (the suite's 12-minute budget); the
# cache's switch is checked by test_import_turns_the_cache_on_unless_told_not_to
def test_a_second_render_loads_its_programs_from_the_cache(tmp_path):
    """The command line keeps compiled programs in DIFFFOG_CACHE_DIR: a second identical render
    in a new process compiles nothing new (every program a cache hit)."""
    import os

    def render(cache, out):
        env = dict(os.environ, DIFFFOG_CACHE_DIR=str(cache))
        r = subprocess.run([sys.executable, "-m", "difffog", "render", "furnace", "-N", "8", "-M",
                            "1", "--iterations", "2", "--supersample", "1", "-q", "--out",
                            str(tmp_path / out)], env=env, capture_output=True, text=True,
                           timeout=300)
        assert r.returncode == 0, r.stderr[-2000:]

    cache = tmp_path / "xla"
    render(cache, "a")
    first = {p.name: p.stat().st_mtime_ns for p in cache.iterdir()}
    assert first  # at least the light solve
    render(cache, "b")
    # the same entries, none rewritten: a recompiled program would have been written again
    assert {p.name: p.stat().st_mtime_ns for p in cache.iterdir()} == first


def test_import_turns_the_cache_on_unless_told_not_to(tmp_path):
    import os

    code = "import difffog, jax; print(jax.config.jax_compilation_cache_dir)"
    env = {k: v for k, v in os.environ.items() if k != "DIFFFOG_CACHE_DIR"}
    for extra, expected in (({"XDG_CACHE_HOME": str(tmp_path)}, str(tmp_path / "difffog" / "xla")),
                            ({"DIFFFOG_CACHE_DIR": "off"}, "None")):
        r = subprocess.run([sys.executable, "-c", code], env={**env, **extra}, capture_output=True,
                           text=True, timeout=120)
        assert r.returncode == 0 and r.stdout.strip() == expected, (r.stdout, r.stderr[-500:])


def test_cache_folder_setting(monkeypatch, tmp_path):
    from difffog._cache import default_cache_dir

    for off in ("off", "0", ""):
        monkeypatch.setenv("DIFFFOG_CACHE_DIR", off)
        assert default_cache_dir() is None
    monkeypatch.setenv("DIFFFOG_CACHE_DIR", str(tmp_path / "c"))
    assert default_cache_dir() == tmp_path / "c"
    monkeypatch.delenv("DIFFFOG_CACHE_DIR")
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path))
    assert default_cache_dir() == tmp_path / "difffog" / "xla"


def test_a_model_built_near_the_mapping_limit_drops_compiled_programs(monkeypatch):
    """A process near Linux's limit on memory mappings (each compiled XLA program holds ~1,100)
    drops JAX's compiled programs before the next model is built, with a MemoryWarning that
    says what happened and how to raise the limit; below it, nothing is dropped."""
    import jax.numpy as jnp

    import difffog as df
    from difffog import _cache

    real = _cache.memory_maps()
    if real is None:
        pytest.skip("no /proc/self/maps here")
    f = jax.jit(lambda x: x + 1.0)
    f(jnp.ones(3))
    assert f._cache_size() == 1
    scene = df.load_scene("furnace")
    monkeypatch.setattr(_cache, "memory_maps", lambda: (int(0.5 * real[1]), real[1]))
    df.forward_model(scene, "sweep", accuracy="draft")
    assert f._cache_size() == 1  # half the limit: kept
    monkeypatch.setattr(_cache, "memory_maps", lambda: (int(0.9 * real[1]), real[1]))
    with pytest.warns(df.MemoryWarning, match="memory mappings.*sysctl vm.max_map_count"):
        df.forward_model(scene, "sweep", accuracy="draft")
    assert f._cache_size() == 0  # dropped


# slow: the default suite's 12-minute budget on 2 cores (stop 56)
@pytest.mark.slow
def test_render_fixed_iterations_and_override(tmp_path):
    out = tmp_path / "o"
    args = ["render", "furnace", "-N", "12", "-M", "2", "--iterations", "3", "-q",
            "--set", "shape.walls.albedo=0.5", "--set", "fog.scattering=0", "--supersample", "1"]
    assert main(args + ["--method", "jacobi", "--out", str(out)]) == 0
    rep = json.loads((out / "report.json").read_text())
    assert rep["iterations"] == 3
    assert rep["overrides"] == ["shape.walls.albedo=0.5", "fog.scattering=0"]
    assert rep["settings"]["solver_options"]["method"] == "jacobi"
    assert any("volume" in line for line in rep["settings"]["terms"])
    # an empty furnace of albedo 0.5 after 3 Jacobi iterations: B = 1 + 0.5·(1 + 0.5·(1 + 0.5))
    assert float(np.load(out / "inside.npy").mean()) == pytest.approx(1.875, rel=0.02)
    # GMRES (the default) has the exact 1/(1 - 0.5) = 2 after the same 3 applications
    assert main(args + ["--out", str(tmp_path / "g")]) == 0
    assert float(np.load(tmp_path / "g" / "inside.npy").mean()) == pytest.approx(2.0, rel=1e-3)


def test_unconverged_render_exits_1_with_one_line_and_writes_its_report(tmp_path, capsys):
    """An optically thick fog with a small iteration cap: the light solve stops before --tol.
    The images and report.json are still written (naming the result), one line on stderr says
    what happened (the result, its estimated error and iterations), and the exit status is 1."""
    out = tmp_path / "thick"
    argv = ["render", "fog-balls", "--set", "fog.scattering=60", "--set", "fog.absorption=0.001",
            "--set", "shape.walls.thickness=0.1", "-N", "10", "-M", "2", "--tol", "1e-8",
            "--max-iterations", "3", "--supersample", "1", "--camera", "top", "-q",
            "--out", str(out)]
    assert main(argv) == 1
    captured = capsys.readouterr()
    err = captured.err.strip().splitlines()
    # one line warns that the steps are optically thick (ζ = 60 at N = 10), one says the error
    assert len(err) == 2, err
    assert re.search(r"^difffog: warning: one lattice step is optically thick .* "
                     r"resolution >= \d+", err[0]), err[0]
    assert re.search(r"^difffog: error: render: max_iterations_reached \(estimated error "
                     r"[0-9.e+-]+ after 3 iterations\)", err[1]), err[1]
    assert "--max-iterations" in err[1]  # what to do about it
    assert sorted(p.name for p in out.iterdir()) == ["report.json", "top.npy", "top.png"]
    rep = json.loads((out / "report.json").read_text())
    assert rep["result"] == "max_iterations_reached"
    assert rep["iterations"] == 3 and rep["error_estimate"] > 1e-8
    assert rep["settings"]["solver_options"]["max_iterations"] == 3
    assert rep["settings"]["solver_options"]["tol"] == 1e-8
    assert np.isfinite(np.load(out / "top.npy")).all()


@pytest.mark.filterwarnings("default::UserWarning")  # as outside pytest: shown, not raised
def test_every_warning_of_difffog_is_one_line(capsys):
    """A shape thinner than a voxel (fog-balls' balls at N = 8) is said in one line like the
    rest, not as Python's "file:line: UserWarning" and the source line after it (``info``
    voxelizes as ``render`` does)."""
    assert main(["info", "fog-balls", "-N", "8"]) == 0
    err = capsys.readouterr().err.strip().splitlines()
    assert err and all(line.startswith("difffog: warning: ") for line in err), err
    assert any("less than one voxel" in line and "use resolution >= " in line for line in err)


def test_max_iterations_and_iterations_are_exclusive(tmp_path, capsys):
    assert main(["render", "furnace", "--iterations", "3", "--max-iterations", "5",
                 "--out", str(tmp_path / "o")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "--max-iterations" in err[0] and "--iterations" in err[0]
    assert not (tmp_path / "o").exists()


def test_the_command_line_imports_only_what_it_uses():
    # SciPy's optimizers (a density fit), trimesh (the splat's shapes) and matplotlib (plots)
    # cost a command ~0.7 s to import; a render of spheres needs none of them
    code = ("import sys, difffog.cli; from difffog.cli._main import main; "
            "assert main(['info', 'fog-balls', '-N', '8', '-M', '1']) == 0; "
            "print(sorted(m for m in ('scipy.optimize', 'trimesh', 'matplotlib') "
            "if m in sys.modules))")
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stderr
    assert r.stdout.strip().splitlines()[-1] == "[]"


def test_console_script_entry_point():
    r = subprocess.run([sys.executable, "-m", "difffog", "info", "slab", "-N", "8", "-M", "1"],
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
    assert rep["settings"]["solver"] == "splat"
    assert rep["settings"]["passes"]["top"]["sheets"] == 10
    # a single pass per camera: one "iteration", no remaining error to estimate
    assert rep["iterations"] == 1 and rep["error_estimate"] == 0.0
    assert rep["result"] == "successful" and rep["settings"]["supersample"] == 1
    # the lit ground in the top-left corner: ρ/π·(E·cos 40° + π·sky), no fog above it
    assert float(img[0, 0]) == pytest.approx(0.6 / np.pi * (3.0 * np.cos(np.radians(40.0))
                                                             + np.pi * 0.2), rel=1e-3)


@pytest.mark.parametrize(
    "argv,needle",
    [
        (["render", "furnace", "--solver", "splat", "--out", "OUT"], "no [sun]"),
        (["render", "fog-balls", "--sheets", "8", "--out", "OUT"],
         "--sheets does not apply to --solver sweep"),
        (["render", "fog-balls", "--solver", "splat", "--directions", "2", "--out", "OUT"],
         "--directions does not apply to --solver splat"),
        (["render", "fog-balls", "--solver", "splat", "--max-iterations", "5", "--out", "OUT"],
         "--max-iterations does not apply to --solver splat"),
        (["render", "fog-balls", "--solver", "splat", "--sheets", "0", "--out", "OUT"],
         "--sheets must be a positive"),
    ],
)
def test_splat_errors_are_one_line(argv, needle, capsys, tmp_path):
    argv = [str(tmp_path / "o") if a == "OUT" else a for a in argv]
    assert main(argv) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("difffog: error:") and needle in err[0], err
    assert not (tmp_path / "o").exists()


# ------------------------------------------------------------------ difffog fit
FIT_SMALL = ["fog-balls", "--set", "shape.walls.thickness=0.1", "-N", "12", "-M", "2",
             "--downsample", "8"]


@pytest.fixture(scope="module")
def fit_targets(tmp_path_factory):
    """Targets of the small fog-balls (ζ = 2, γ = 0.5) rendered by the fit's own model."""
    from difffog import load_scene
    from difffog.fit._driver import make_model

    scene = load_scene("fog-balls", ["shape.walls.thickness=0.1"])
    fwd = make_model(scene, "sweep", cameras=["top", "oblique"], resolution=12, downsample=8,
                     model_settings={"M": 2})
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
            "--solver", "sweep", "--optimizer", "lm", "--out", str(out)]
    assert main(argv) == 0
    files = sorted(p.name for p in out.iterdir())
    assert files == sorted(["fit.json", "convergence.png"] + [
        f"{c}_{k}" for c in ("top", "oblique")
        for k in ("fit.npy", "target.npy", "residual.npy", "fit.png")])
    rep = json.loads((out / "fit.json").read_text())
    # the targets are the N = 12 model's own: its fit finds them
    assert rep["fitted"]["fog.scattering"] == pytest.approx(2.0, rel=1e-3)
    assert rep["fitted"]["fog.absorption"] == pytest.approx(0.5, rel=1e-3)
    assert set(rep["stderr"]) == {"fog.scattering", "fog.absorption"}
    # --model-error refine (the default): the estimate is that fit corrected to N = 24, and
    # the model's own error is the correction (first order, doubled lattice)
    # (with one more direction, M = 3; and the checks of a lattice between, N = 18, and of
    # the direction set, M = 3 at N = 12)
    assert [(lv["resolution"], lv.get("M")) for lv in rep["ladder"]] == [
        (12, None), (24, 3), (18, None), (12, 3)]
    assert rep["estimates"] == rep["ladder"][1]["estimates"]
    for path in ("fog.scattering", "fog.absorption"):
        shift = abs(rep["estimates"][path] - rep["fitted"][path])
        parts = rep["model_error_parts"][path]
        assert parts["lattice"] == pytest.approx(shift) and shift > 0
        assert rep["model_error"][path] == pytest.approx(math.sqrt(sum(
            v * v for v in parts.values())))
        assert rep["uncertainty"][path] >= max(rep["stderr"][path], rep["model_error"][path])
        assert parts["brightness"] > 0  # --model-floor auto: the sweep's 0.5%
    assert rep["model_floor"] == 0.005
    # the fit's own images: the residual is what the fit's tolerances leave, far inside what
    # the floor alone explains, and no misfit part
    for cam in ("top", "oblique"):
        assert rep["goodness_of_fit"][cam]["ratio"] < 0.5, rep["goodness_of_fit"]
    assert not any("misfit" in rep["model_error_parts"][p] for p in rep["paths"])
    assert len(rep["correlation"]) == 2 and rep["converged"]
    assert rep["settings"]["forward"] == "sweep" and rep["settings"]["optimizer"] == "lm"
    assert rep["settings"]["model"]["resolution"] == 12
    assert rep["settings"]["model"]["solver_options"]["M"] == 2
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


@pytest.mark.parametrize("extra, needle", [
    (["--unknown", "fog.density", "--unknown", "fog.scattering"], "is fitted alone"),
    (["--unknown", "fog.density", "--prior", "l2=1"], "--prior l2=1: use KIND=WEIGHT"),
    (["--unknown", "fog.density", "--prior", "tv=-1"], "must be >= 0"),
    (["--unknown", "fog.density", "--prior", "tv=balance"], "tv has no balancing share"),
    (["--unknown", "fog.density", "--resume"], "no checkpoint"),
    (["--unknown", "fog.density", "--phase-order", "2"],
     "--phase-order does not apply to --unknown fog.density"),
    (["--unknown", "fog.density", "--first-collision", "deposit"],
     "--first-collision does not apply to --unknown fog.density"),
    (["--unknown", "fog.density", "--devices", "2"],
     "--devices does not apply to --unknown fog.density"),
])
def test_density_fit_errors_are_one_line_and_exit_2(extra, needle, tmp_path, capsys):
    np.save(tmp_path / "T.npy", np.ones((64, 64), np.float32))
    argv = ["fit", "cloud-tomo-start", "--target", f"top={tmp_path / 'T.npy'}", *extra,
            "--out", str(tmp_path / "o")]
    assert main(argv) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("difffog: error:") and needle in err[0], err
    assert not (tmp_path / "o").exists()


def test_density_fit_takes_the_model_flags(tmp_path, capsys, monkeypatch):
    """--scheme and --once-M reach the density fit's models (not ignored): what fit_density
    is called with (stopped there with a one-line error that names it)."""
    import importlib

    from difffog import DifffogError

    density = importlib.import_module("difffog.fit._density")  # (difffog.fit is the function)

    def stop(*a, **kw):
        raise DifffogError(f"settings={kw.get('settings')}")

    monkeypatch.setattr(density, "fit_density", stop)
    np.save(tmp_path / "T.npy", np.ones((64, 64), np.float32))
    argv = ["fit", "cloud-tomo-start", "--target", f"top={tmp_path / 'T.npy'}", "--unknown",
            "fog.density", "--scheme", "step", "--once-M", "4", "--out", str(tmp_path / "o")]
    assert main(argv) == 2
    assert "settings={'scheme': 'step', 'once_M': 4}" in capsys.readouterr().err


@pytest.mark.parametrize("quiet", [False, True])
def test_a_fit_the_model_does_not_explain_is_said_and_written(tmp_path, capsys, monkeypatch,
                                                              quiet):
    """A misfit (test_fit's analytic Toy fit to a target with a blob it has no term for, in
    place of the sweep's fit) reaches the user: in the summary, or with -q as one stderr line
    (the summary that lists the fit's warnings is not printed then), and in fit.json with the
    goodness of fit; the fit converged, so the exit status is 0."""
    from difffog.fit import _driver

    import test_fit as T

    _, wrong = T.misfit_targets()
    real = _driver.fit

    def toy_fit(scene, targets, unknowns, **kw):
        return real(T.Toy().scene, wrong, T.MISFIT_START, forward=T.LatticeToy(10),
                    model_error="refine")

    monkeypatch.setattr(_driver, "fit", toy_fit)
    np.save(tmp_path / "T.npy", np.ones((16, 16), np.float32))
    out = tmp_path / "o"
    argv = ["fit", *FIT_SMALL, "--target", f"top={tmp_path / 'T.npy'}", "--unknown",
            "fog.scattering", "--out", str(out)] + (["-q"] if quiet else [])
    assert main(argv) == 0
    cap = capsys.readouterr()
    said = "the model does not explain the images: residual RMS top"
    err = [line for line in cap.err.splitlines() if said in line]
    if quiet:
        assert len(err) == 1 and err[0].startswith("difffog: warning: "), cap.err
        assert cap.out == ""
    else:
        assert not err and f"warning: {said}" in cap.out and "(misfit)" in cap.out
    rep = json.loads((out / "fit.json").read_text())
    assert rep["goodness_of_fit"]["top"]["ratio"] > 2
    assert any(said in w for w in rep["warnings"])
    assert all(rep["model_error_parts"][p]["misfit"] > 0 for p in T.MISFIT_TRUTH)


@pytest.mark.parametrize("extra,needle", [
    (["--target", "top=MISSING.npy", "--unknown", "fog.scattering"], "no such file"),
    (["--target", "side=T.npy", "--unknown", "fog.scattering"], "has no camera 'side'"),
    (["--target", "top=T.npy", "--unknown", "fog.scatter"], "Did you mean 'fog.scattering'"),
    (["--target", "top=T.npy"], "at least one --unknown"),
    (["--target", "top=BAD.npy", "--unknown", "fog.scattering"], "the image is 128x100 pixels "
     "(width x height) but camera 'top' is 128x128, rendered at 16x16 with downsample 8"),
    (["--target", "top=photo.bmp", "--unknown", "fog.scattering"],
     "unknown image format '.bmp'; supported: .npy"),
    (["--target", "top=T.npy", "--unknown", "camera.top.exposur"], "Did you mean "
     "'camera.top.exposure'?"),
    (["--target", "top=T.npy", "--unknown", "fog.scattering=abc"], "not a number"),
    (["--target", "top=T.npy", "--unknown", "fog.scattering", "--resume"], "no checkpoint"),
    (["--target", "top=T.npy", "--unknown", "fog.scattering", "--model-error", "finer"],
     "--model-error finer: use refine, none or a finer resolution"),
    (["--target", "top=T.npy", "--unknown", "fog.scattering", "--refine-steps", "0"],
     "--refine-steps 0: give the most renders of the finer model"),
    (["--target", "top=T.npy", "--unknown", "fog.scattering", "--model-floor", "5%x"],
     "--model-floor 5%x: use auto or a relative brightness in [0, 1)"),
    (["--target", "top=T.npy", "--unknown", "fog.scattering", "--bounds",
      "fog.scattering=3,9"], "outside"),
    (["--target", "top=T.npy", "--unknown", "fog.scattering", "--edge-weight", "2"],
     "edge_weight must be a number in [0, 1]"),
    (["--target", "top=T.npy", "--unknown", "sun.zenith_deg", "--bounds",
      "sun.zenith_deg=0,120"], "bounds [0.0, 120.0] must satisfy 0.0 <= lower < upper <= 90.0"),
    # FIT_SMALL gives -M, a setting the splat does not take
    (["--target", "top=T.npy", "--unknown", "fog.scattering", "--solver", "splat"],
     "--directions does not apply to --solver splat"),
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


def test_fit_parser_takes_the_solver_and_the_optimizer():
    """`difffog fit --solver NAME --optimizer NAME`: the forward model's settings come from the
    solver's fit defaults (no --accuracy) and only the flags given."""
    from difffog.cli._main import build_parser, model_settings

    args = build_parser().parse_args(["fit", *FIT_SMALL, "--solver", "sweep",
                                      "--optimizer", "gauss-newton"])
    assert (args.solver, args.optimizer, args.accuracy, args.devices, args.edge_weight) == (
        "sweep", "gauss-newton", None, None, 1.0)
    assert model_settings(args, args.solver, accuracy=args.accuracy) == {"resolution": 12,
                                                                        "M": 2}
    args = build_parser().parse_args(["fit", "--solver", "splat", "--optimizer", "bfgs", "-N",
                                      "16"])
    assert model_settings(args, "splat", accuracy=None) == {"resolution": 16}
    for argv in (["fit", "--optimizer", "adam"], ["fit", "--solver", "montecarlo"]):
        with pytest.raises(SystemExit):
            build_parser().parse_args(argv)
