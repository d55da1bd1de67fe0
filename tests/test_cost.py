"""Know before you run (issue 22): the cost estimate, the memory guard, and the values no
machine or float type can hold."""

import json
import math
import os
import subprocess
import sys

import jax
import pytest

import difffog as df
from difffog import _cost
from difffog.cli import main


@pytest.mark.parametrize("name,N,M", [("fog-balls", 24, 2), ("slab", 16, 2),
                                      ("translucent-cube", 20, 3), ("cloud-plane", 15, 2)])
def test_lattice_shape_is_the_voxelizers_without_voxelizing(name, N, M):
    scene = df.load_scene(name)
    assert _cost.lattice_shape(scene, N, M + 1) == df.voxelize(scene, N, M, margin=M + 1).shape


def test_estimate_at_any_size_never_voxelizes(monkeypatch):
    """N = 1024, M = 5: the estimate comes from the settings alone (voxelizing would take
    minutes), and it scales as the arrays do: ×8 nodes per doubling of N."""
    import difffog.geometry._lattice as lat

    monkeypatch.setattr(lat, "voxelize", lambda *a, **k: pytest.fail("voxelized"))
    scene = df.load_scene("fog-balls")
    big = df.estimate(scene, "sweep", resolution=1024, M=5)
    assert big.shape == (1028, 1028, 1028)  # two vacuum nodes each side
    half = df.estimate(scene, "sweep", resolution=512, M=5)
    ratio = big.memory["Krylov vectors"] / half.memory["Krylov vectors"]
    assert ratio == pytest.approx((1028 / 516) ** 3, rel=1e-9)
    assert big.peak_bytes > 100 * 2**30  # far beyond any workstation
    assert big.seconds_per_iteration > 100 * half.seconds_per_iteration / 8 / 20


def test_estimate_matches_a_measured_render(tmp_path):
    """A fresh process renders the furnace at N = 16, M = 3: the estimate it recorded before
    building anything is within 30% of its measured peak resident memory (bench_cost.py
    measures fog-balls over N and M).  The peak of the same program varies from run to run
    (575-680 MB measured before stop 55 on two machines, 590 since the light solve became
    one sweep program, the estimate 601: the compiler's threads and their allocator arenas,
    fewer when the machine is busy), so the process runs twice and the larger peak
    is the measurement."""
    peaks = [_measured_render(tmp_path / f"o{k}") for k in range(2)]
    est, measured = peaks[0][0], max(p for _, p in peaks)
    assert est == pytest.approx(measured, rel=0.3), peaks


def _measured_render(out):
    """(estimated, measured) peak MB of ``difffog render furnace`` in a fresh process."""
    # a clean environment: other tests leave XLA_FLAGS asking for several host devices, each
    # with its own buffers (1.34 GB peak instead of 0.75 in the suite)
    env = {k: v for k, v in os.environ.items() if not k.startswith(("XLA_", "JAX_"))}
    # and it compiles, as the estimate assumes: a program loaded from the session's compilation
    # cache (another test may have compiled the same one) skips the compiler's own memory
    # (560 MB peak instead of 600-645)
    env["DIFFFOG_CACHE_DIR"] = "off"
    subprocess.run([sys.executable, "-m", "difffog", "render", "furnace", "-N", "16", "-M",
                    "3", "--iterations", "2", "--supersample", "1", "--out", str(out), "-q"],
                   check=True, env=env)
    rep = json.loads((out / "report.json").read_text())
    assert rep["estimate"]["lattice_shape"] == rep["settings"]["lattice_shape"]
    return rep["estimate"]["peak_mb"], rep["peak_memory_mb"]


def _fake_memory(monkeypatch, gib):
    monkeypatch.setattr(_cost, "available_bytes", lambda backend=None: (int(gib * 2**30), "RAM"))


def test_guard_refuses_warns_and_can_be_forced(monkeypatch):
    scene = df.load_scene("fog-balls")
    est = df.estimate(scene, "sweep", resolution=32, M=2)
    need = est.peak_bytes / 2**30
    _fake_memory(monkeypatch, need / 2)  # half of what it needs
    with pytest.raises(df.ResourceError, match=r"needs ~.* at its peak .* is .*lower"):
        df.forward_model(scene, "sweep", accuracy="draft")
    assert "needs ~" in _cost.check_fits(est, force=True)  # forced: said, not refused
    _fake_memory(monkeypatch, need * 1.5)  # fits, but above half: a warning text
    assert "needs ~" in _cost.check_fits(est)
    _fake_memory(monkeypatch, need * 4)
    assert _cost.check_fits(est) is None


def test_oversized_renders_exit_1_with_one_line_and_write_nothing(tmp_path, capsys):
    for argv in (["-N", "1024", "-M", "5"], ["-N", "8", "-M", "80"]):
        out = tmp_path / "out"
        assert main(["render", "fog-balls", *argv, "--out", str(out)]) == 1
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and err[0].startswith("difffog: error: ") and "GiB" in err[0]
        assert "--force" in err[0] and not out.exists()


def test_info_prints_the_estimate_without_voxelizing_a_huge_lattice(capsys, monkeypatch):
    import difffog.cli._info as info

    monkeypatch.setattr(info, "voxelize", lambda *a, **k: pytest.fail("voxelized"))
    assert main(["info", "fog-balls", "-N", "1024", "-M", "5"]) == 0
    out = capsys.readouterr().out
    assert "1028x1028x1028 nodes" in out and "not voxelized" in out
    assert "GiB at the peak" in out and "per light iteration" in out


@pytest.mark.parametrize("override,field", [("fog.scattering=1e300", "scattering"),
                                            ("sun.irradiance=2e15", "irradiance"),
                                            ("sky.radiance=-1e16", "radiance")])
def test_numbers_float32_cannot_carry_are_refused(override, field):
    with pytest.raises(df.SceneError, match=rf"{field}.*beyond ±1e\+15.*float32"):
        df.load_scene("fog-balls", [override])


def test_numbers_up_to_the_limit_still_load():
    scene = df.load_scene("fog-balls", ["fog.scattering=1e6", "sun.irradiance=1e15"])
    assert scene.fog.scattering == 1e6 and scene.sun.irradiance == 1e15


def test_a_non_finite_result_names_the_inputs_that_led_there():
    """A valid input can still overflow float32 in combination: the message names the largest
    inputs rather than blaming the solver."""
    import equinox as eqx
    import jax.numpy as jnp

    from difffog.forward._model import largest_inputs

    p = df.Params.from_scene(df.load_scene("fog-balls"), jnp.float32)
    p = eqx.tree_at(lambda q: q.sun_irradiance, p, jnp.asarray(3e37, jnp.float32))
    text = largest_inputs(p)
    assert text.startswith("sun.irradiance = 3e+37, fog.scattering = 2")


def test_estimate_follows_the_scheme_the_solver_will_run(monkeypatch):
    """scheme="auto" runs the linear-source scheme where a lattice step is optically thick: the
    estimate charges its measured cost there (time ×LINEAR_COST of XLA's step loop, three slope
    channels) and nothing in thin fog; the native CPU sweep is charged its own rates where it
    will run (the step scheme's, and its general form's per update for the linear scheme)."""
    from difffog._cost import CPU_NATIVE_GENERAL_S_PER_UPDATE, LINEAR_COST
    from difffog.forward.sweep import _native
    from difffog.study._semi_infinite import thick_cube

    thick = thick_cube(1000.0)
    native_auto = df.estimate(thick, "sweep", resolution=32, M=2)
    native = df.estimate(thick, "sweep", resolution=32, M=2, scheme="step")
    will_be_native = _native.expected() and native.backend == "cpu"
    if will_be_native:  # 6 faces × 25 directions per node, the general form's rate
        n = math.prod(native_auto.shape)
        assert native_auto.seconds_per_iteration == pytest.approx(
            6 * 25 * n * CPU_NATIVE_GENERAL_S_PER_UPDATE, rel=1e-9)
        # the sub-stepped scheme's native kernel: per node, direction and sub-step (M = 2)
        from difffog._cost import CPU_NATIVE_SUBSTEP_S_PER_UPDATE

        sub_n = df.estimate(thick, "sweep", resolution=32, M=2, scheme="substep")
        assert sub_n.seconds_per_iteration == pytest.approx(
            6 * 25 * math.prod(sub_n.shape) * 2 * CPU_NATIVE_SUBSTEP_S_PER_UPDATE, rel=1e-9)
    monkeypatch.setattr(_native, "expected", lambda: False)  # the XLA loop's figures below
    auto = df.estimate(thick, "sweep", resolution=32, M=2)
    step = df.estimate(thick, "sweep", resolution=32, M=2, scheme="step")
    assert (native.seconds_per_iteration < step.seconds_per_iteration) == will_be_native
    assert auto.seconds_per_iteration == pytest.approx(step.seconds_per_iteration * LINEAR_COST,
                                                       rel=1e-9)
    assert auto.peak_bytes > step.peak_bytes
    thin = thick_cube(0.5)  # a step of 0.03 mean free paths
    assert (df.estimate(thin, "sweep", resolution=32, M=2).seconds_per_iteration
            == df.estimate(thin, "sweep", resolution=32, M=2, scheme="step").seconds_per_iteration)
    # the opt-in sub-stepped scheme: its measured cost per program (the CPU's loop here), more
    # temporaries, and a linearised sweep that keeps more per node and direction
    from difffog._cost import SUBSTEP_COST_BATCHED, SUBSTEP_COST_LOOP

    sub = df.estimate(thick, "sweep", resolution=32, M=2, scheme="substep", kernel="loop")
    assert sub.seconds_per_iteration == pytest.approx(step.seconds_per_iteration
                                                      * SUBSTEP_COST_LOOP, rel=1e-9)
    assert sub.peak_bytes > step.peak_bytes
    # and its host set-up: the per-node weight scale, per crossing and per NumPy call
    from difffog._cost import SETUP_S_PER_SUBSTEP_CALL, SETUP_S_PER_SUBSTEP_CROSSING

    n, D = float(math.prod(sub.shape)), 25
    assert sub.setup_s - step.setup_s == pytest.approx(
        D * (SETUP_S_PER_SUBSTEP_CROSSING * n
             + SETUP_S_PER_SUBSTEP_CALL * 6 * -(-max(sub.shape) // 2)), rel=1e-9)
    kw = dict(resolution=32, M=2, kernel="batched", gradient=True, sweep_residuals="keep")
    sub_b = df.estimate(thick, "sweep", scheme="substep", **kw)
    step_b = df.estimate(thick, "sweep", scheme="step", **kw)
    assert sub_b.seconds_per_iteration == pytest.approx(step_b.seconds_per_iteration
                                                        * SUBSTEP_COST_BATCHED, rel=1e-9)
    assert sub_b.memory["linearised sweeps"] > 1.5 * step_b.memory["linearised sweeps"]


def test_a_device_mesh_on_a_cpu_is_estimated_with_a_copy_per_host_device(monkeypatch):
    """On a CPU the host devices share the cores: a mesh of faces alone runs the native kernel
    per face (measured: CPU_MESH_COST times one device's iteration; no surface records, which
    only one device's world-frame sweep reads), a mesh that splits the plane XLA's loop; and
    every host device keeps its own copy of the light's fields and GMRES's vectors in the one
    machine's memory (fog-balls, 2 host devices against one, stop 74: +449 MB at N = 64, M =
    3, +953 MB at N = 96, M = 3).  On a GPU each device has its own memory, which the
    estimate is compared with: nothing is added there."""
    from difffog.forward.sweep import _native

    scene = df.load_scene("fog-balls")
    kw = dict(resolution=64, M=3, backend="cpu")
    one = _cost.estimate_sweep(scene, **kw)
    two = _cost.estimate_sweep(scene, devices=2, **kw)
    assert two.memory["other devices' copies"] == (one.memory["light solve"]
                                                   + one.memory["Krylov vectors"])
    assert "surface records" not in two.memory and "other devices' copies" not in one.memory
    four = _cost.estimate_sweep(scene, devices=4, mesh=(2, 2, 1), **kw)
    assert four.memory["other devices' copies"] == 3 * two.memory["other devices' copies"]
    gpu = _cost.estimate_sweep(scene, resolution=64, M=3, backend="gpu", devices=2)
    assert "other devices' copies" not in gpu.memory
    if _native.expected():
        assert two.seconds_per_iteration == pytest.approx(
            one.seconds_per_iteration * _cost.CPU_MESH_COST, rel=1e-12)
    monkeypatch.setattr(_native, "expected", lambda: False)  # XLA's loop on one device
    xla = _cost.estimate_sweep(scene, **kw)
    split = _cost.estimate_sweep(scene, devices=2, mesh=(1, 2, 1), **kw)
    monkeypatch.undo()
    assert _cost.estimate_sweep(scene, devices=2, mesh=(1, 2, 1), **kw).seconds_per_iteration \
        == split.seconds_per_iteration == xla.seconds_per_iteration


def test_a_device_mesh_on_a_cpu_warns_that_one_device_is_faster():
    """devices > 1 on a CPU whose native kernel would run: a DeviceWarning that names what it
    costs and what to do (the CLI prints it as one line); the mesh's geometry has no surface
    records (its sweeps are XLA's, which do not read them)."""
    from difffog.forward.sweep import _native

    if not _native.expected() or jax.default_backend() != "cpu":
        pytest.skip("the native kernel would not run here: a mesh costs nothing extra")
    scene = df.load_scene("fog-balls", ["shape.walls.thickness=0.1"])
    lat = df.voxelize(scene, 24, 2)  # (faces large enough for the blocked sweep)
    with pytest.warns(df.DeviceWarning, match="leave devices at 1 on a CPU"):
        geom = df.SweepSolver(M=2, devices=2).prepare(scene, lat)
    assert geom.records is None
    assert df.SweepSolver(M=2).prepare(scene, lat).records is not None


def test_a_gradient_estimate_counts_the_linearised_sweeps():
    """A reverse-mode gradient's adjoint solve keeps the linearised Jacobi step's residuals
    (stop 41: cloud-plane's fit at N = 48, which then took that route, peaked at 20.8 GB where
    the estimate said 1.9 GiB): per node and direction, more with the linear scheme and per
    moment."""
    from difffog._cost import (LINEARISED_BYTES_LINEAR, LINEARISED_BYTES_STEP,
                               LINEARISED_PER_MOMENT)
    from difffog.study._semi_infinite import thick_cube

    scene = thick_cube(1000.0)
    kw = dict(resolution=32, M=2, sweep_residuals="keep")
    plain = df.estimate(scene, "sweep", scheme="step", **kw)
    grad = df.estimate(scene, "sweep", scheme="step", gradient=True, **kw)
    lin = df.estimate(scene, "sweep", scheme="linear", gradient=True, **kw)
    n = math.prod(grad.shape)
    assert "linearised sweeps" not in plain.memory
    assert grad.memory["linearised sweeps"] == int(n * 25 * LINEARISED_BYTES_STEP)
    assert lin.memory["linearised sweeps"] == int(n * 25 * LINEARISED_BYTES_LINEAR)
    assert grad.peak_bytes - plain.peak_bytes >= grad.memory["linearised sweeps"]
    cloud = df.load_scene("cloud-plane")
    l0 = df.estimate(cloud, "sweep", resolution=24, M=3, phase_order=0, scheme="linear",
                     gradient=True, sweep_residuals="keep")
    l3 = df.estimate(cloud, "sweep", resolution=24, M=3, phase_order=3, scheme="linear",
                     gradient=True, sweep_residuals="keep")
    assert (l3.memory["linearised sweeps"] / l0.memory["linearised sweeps"]
            == pytest.approx(1 + 15 * LINEARISED_PER_MOMENT, rel=1e-6))
    # recomputing each slab step keeps ~4x less; "auto" recomputes above 1 GiB of kept ones
    from difffog._cost import RECOMPUTED_BYTES_STEP
    from difffog.forward.sweep._solver import RECOMPUTE_ABOVE_BYTES

    re = df.estimate(scene, "sweep", resolution=32, M=2, scheme="step", gradient=True,
                     sweep_residuals="recompute")
    assert re.memory["linearised sweeps"] == int(n * 25 * RECOMPUTED_BYTES_STEP)
    for N in (16, 32):
        keep, auto = (df.estimate(scene, "sweep", resolution=N, M=2, scheme="step",
                                  gradient=True, sweep_residuals=r) for r in ("keep", "auto"))
        big = keep.memory["linearised sweeps"] > RECOMPUTE_ABOVE_BYTES
        assert big == (N == 32)
        assert auto.memory["linearised sweeps"] < keep.memory["linearised sweeps"] or not big
        assert auto.memory["linearised sweeps"] == keep.memory["linearised sweeps"] or big


def test_a_fit_jacobian_estimate_counts_one_matrix_free_tangent_solve_per_unknown():
    """A fit's Jacobian (forward mode, products matrix-free since stop 42) keeps one GMRES's
    Krylov vectors per unknown and no linearised sweeps; ``make_model`` guards with its
    unknowns."""
    from difffog._cost import TANGENT_BYTES_PER_STATE
    from difffog.fit._driver import make_model

    cloud = df.load_scene("cloud-plane")
    kw = dict(resolution=24, M=3, phase_order=3)
    plain = df.estimate(cloud, "sweep", **kw)
    one, three = (df.estimate(cloud, "sweep", tangent_solves=p, **kw) for p in (1, 3))
    state = math.prod(one.shape) * (2 + 15)  # Λ, 15 moments, E (cloud-plane has a ground)
    assert one.memory["tangent solves"] == TANGENT_BYTES_PER_STATE * state
    assert three.memory["tangent solves"] == 3 * one.memory["tangent solves"]
    assert "linearised sweeps" not in three.memory and "adjoint" not in three.memory
    # each tangent's start and result: three state vectors, and the light state the
    # optimizer carries (since stop 61)
    assert three.memory["tangents' starts"] == (3 * 3 + 1) * state * 4
    assert (three.peak_bytes - plain.peak_bytes
            == three.memory["tangent solves"] + three.memory["cameras' columns"]
            + three.memory["tangents' starts"])
    # the cameras' columns by forward mode (since stop 60), one per unknown, no reverse pass
    assert three.memory["cameras' columns"] == 3 * one.memory["cameras' columns"] > 0
    assert "cameras' VJP" not in three.memory
    # the fit's guard estimates with its unknowns' tangent solves
    import difffog._cost as cost

    seen = []

    class Stop(Exception):
        pass

    def record(est, **kw):
        seen.append(est)
        raise Stop  # before the model is built

    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(cost, "check_fits", record)
        with pytest.raises(Stop):
            make_model(cloud, "sweep", cameras=["top"], resolution=24, downsample=8,
                       model_settings={"M": 3, "phase_order": 3}, unknowns=3)
    assert seen[0].memory["tangent solves"] == three.memory["tangent solves"]
    assert "linearised sweeps" not in seen[0].memory
