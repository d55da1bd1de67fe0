"""The speed-accuracy study (`difffog bench`) and the accuracy presets."""

import csv
import dataclasses
import json
import warnings

import numpy as np
import pytest

import difffog as df
from difffog.cli import main
from difffog.cli._main import build_parser, model_settings
from difffog.forward._registry import LEVELS, SOLVERS, forward_model, preset
from difffog.study import _bench


def test_presets_order_cost_and_reject_unknown_names():
    for solver in SOLVERS:
        res = [preset(solver, lv)["resolution"] for lv in LEVELS]
        assert res == sorted(res) and res[0] < res[-1], (solver, res)
    assert preset("sweep", "draft")["M"] <= preset("sweep", "high")["M"]
    p = preset("sweep")
    p["resolution"] = 1  # a copy: the table is not changed
    assert SOLVERS["sweep"].presets["default"]["resolution"] != 1
    with pytest.raises(df.DifffogError, match="draft, default, high"):
        preset("sweep", "fast")
    with pytest.raises(df.DifffogError, match="sweep or splat"):
        preset("montecarlo")
    # a setting of the other solver is refused also on top of a preset
    with pytest.raises(df.DifffogError, match="sheets is not a setting of the sweep solver"):
        forward_model(df.load_scene("furnace"), accuracy="draft", sheets=3)


def _settings(argv, solver="sweep"):
    args = build_parser().parse_args(argv)
    return model_settings(args, solver, accuracy=args.accuracy)


def test_cli_accuracy_fills_only_what_is_not_given():
    assert _settings(["render", "--accuracy", "draft"]) == dict(resolution=32, M=2, tol=1e-3)
    assert _settings(["render", "--accuracy", "high", "-N", "40", "--tol", "1e-6"]) == dict(
        resolution=40, M=SOLVERS["sweep"].presets["high"]["M"], tol=1e-6)
    s = _settings(["render", "--solver", "splat", "--accuracy", "high"], "splat")
    assert s == dict(SOLVERS["splat"].presets["high"]) and s["sheets"] is None
    # an exact iteration count wins over the preset's tolerance: K iterations, tol 0
    s = _settings(["render", "--iterations", "5"])
    assert s["max_iterations"] == 5 and s["tol"] == 0.0
    # an iteration cap keeps the tolerance (the preset's or --tol)
    s = _settings(["render", "--max-iterations", "7"])
    assert s["max_iterations"] == 7 and s["tol"] == preset("sweep")["tol"]
    s = _settings(["render", "--max-iterations", "7", "--tol", "1e-6"])
    assert (s["max_iterations"], s["tol"]) == (7, 1e-6)


def test_mitsuba_rows_sum_time_and_average_error_over_cameras(tmp_path):
    rows = [("a", "top", 4, 1.0, 0.5), ("a", "side", 4, 2.0, 0.3), ("a", "top", 16, 4.0, 0.2),
            ("a", "side", 16, 8.0, 0.1), ("b", "top", 4, 9.0, 0.9)]
    with (tmp_path / "convergence.csv").open("w", newline="") as f:
        w = csv.writer(f)
        w.writerow(["scene", "camera", "spp", "wall_s", "rel_rmse_corr"])
        w.writerows(rows)
    out = _bench.mitsuba_rows(tmp_path, ["a"])
    assert [(r["spp"], r["time_s"], round(r["error"], 12)) for r in out] == [(4, 3.0, 0.4),
                                                                             (16, 12.0, 0.15)]


def test_scene_errors_remove_reference_noise(tmp_path):
    rng = np.random.default_rng(0)
    ref = 1.0 + rng.random((8, 8))
    (tmp_path / "s").mkdir()
    np.save(tmp_path / "s" / "top.npy", ref)
    (tmp_path / "s" / "top_stats.json").write_text(json.dumps({"ref_noise_rmse": 0.0}))
    err, bias, cams = _bench.scene_errors({"top": 1.1 * ref, "nocam": ref}, tmp_path, "s")
    assert cams == ["top"]
    assert bias == pytest.approx(0.1)
    assert err == pytest.approx(0.1 * np.sqrt(np.mean(ref**2)) / ref.mean())
    (tmp_path / "s" / "top_stats.json").write_text(json.dumps({"ref_noise_rmse": 10.0}))
    err, _, _ = _bench.scene_errors({"top": 1.1 * ref}, tmp_path, "s")
    assert err == 0.0  # the difference is below the reference's own noise


def test_bench_errors_are_one_line(tmp_path, capsys):
    assert main(["bench", "--quick", "--references", str(tmp_path / "none"),
                 "--out", str(tmp_path / "o")]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("difffog: error:") and "--references" in err and "\n" not in err
    (tmp_path / "refs").mkdir()
    assert main(["bench", "--quick", "--scenes", "slab", "--references", str(tmp_path / "refs"),
                 "--out", str(tmp_path / "o")]) == 2
    assert "no reference images for slab" in capsys.readouterr().err
    assert not (tmp_path / "o").exists()


STUDY_SETTINGS = {"splat": dict(resolution=12, sheets=None),
                  "sweep": dict(resolution=12, M=2, tol=1e-3)}


# slow (both): ~30 s for the splat, 4× that for the sweep; the default suite keeps the bench
# command's own tests
@pytest.mark.slow
@pytest.mark.parametrize("solver", ["splat", "sweep"])
def test_bench_study_rows_match_an_independent_render(solver, tmp_path, monkeypatch):
    """A one-setting study on fog-balls against the shipped references: the CSV's error is the
    error of the same render computed here, Mitsuba's curve is included, and the Pareto plot
    is written.  (The study is the same for both solvers; the sweep compiles 4× longer.)"""
    from difffog.study import references

    setting = STUDY_SETTINGS[solver]
    monkeypatch.setitem(SOLVERS, solver, dataclasses.replace(SOLVERS[solver], quick=(setting,)))
    res = _bench.run_bench(scenes=["fog-balls"], solvers=[solver], out=tmp_path / "b",
                           quick=True)  # references=None: the shipped ones
    with res.csv_path.open() as f:
        rows = list(csv.DictReader(f))
    ours = [r for r in rows if r["solver"] == solver]
    assert len(ours) == 1 and any(r["solver"].startswith("mitsuba") for r in rows)
    assert ours[0]["setting"] == _bench.setting_label(setting)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # the walls are thinner than a voxel at N = 12
        r = forward_model(df.load_scene("fog-balls"), solver, accuracy=None, **setting)
    err, bias, _ = _bench.scene_errors(r(r.params()), references.references_dir(), "fog-balls")
    assert float(ours[0]["error"]) == pytest.approx(err, rel=1e-3)
    assert float(ours[0]["bias"]) == pytest.approx(bias, rel=1e-3, abs=1e-6)
    assert float(ours[0]["time_s"]) > 0 and float(ours[0]["xla_mib"]) > 0
    assert int(float(ours[0]["iterations"])) >= 1
    assert res.plot_path.stat().st_size > 10_000


def test_mitsuba_time_at_equal_error_interpolates_its_curve():
    """Mitsuba's time to an error: log-log between its measured points, t ∝ error⁻² beyond."""
    rows = [dict(solver="mitsuba3 (references' run)", scene="s", time_s=t, error=e)
            for t, e in ((1.0, 0.4), (4.0, 0.2), (16.0, 0.1))]
    assert _bench.mitsuba_time_at(rows, "s", 0.2) == pytest.approx(4.0)
    assert _bench.mitsuba_time_at(rows, "s", 0.4 / np.sqrt(2)) == pytest.approx(2.0)
    assert _bench.mitsuba_time_at(rows, "s", 0.05) == pytest.approx(64.0)   # extrapolated
    assert np.isnan(_bench.mitsuba_time_at(rows, "other", 0.1))


def test_summary_has_presets_and_equal_error_tables(tmp_path):
    rows = [dict(solver="sweep", scene="s", setting=_bench.setting_label(preset("sweep", lv)),
                 time_s=t, compile_s=2.0, setup_s=1.0, xla_mib=10.0, iterations=5, error=e,
                 bias=0.0) for lv, t, e in (("draft", 1.0, 0.2), ("default", 4.0, 0.1))]
    rows += [dict(solver="mitsuba3 (references' run)", scene="s", setting="4 spp", spp=4,
                  time_s=t, error=e) for t, e in ((2.0, 0.2), (8.0, 0.1))]
    machine = {"start": _bench.run_machine()}
    start = machine["start"]
    assert start["copy_all"] > 0 and start["copy_1"] > 0 and start["cores"] >= 1
    machine["end"] = dict(start, copy_1=1.5, copy_all=2.5, load="9.00 / 9.00 / 9.00")
    md = _bench.summary_markdown(rows, machine)
    assert md.startswith("# difffog bench\n")
    assert (f"{start['copy_1']:.1f} GB/s on one thread, {start['copy_all']:.1f} GB/s on "
            f"{start['cores']} at the start; 1.5 / 2.5 GB/s at the end") in md
    assert "9.00 / 9.00 / 9.00 at the end" in md
    assert "| sweep | draft | N32 M2 tol0.001 | 1.00 | 2.0 | 20.0 | 1 |" in md
    assert "| sweep | s | N64 M3 tol0.0001 | 10.0 | 4.00 | 7.0 | 8.00 | 2.0× |" in md
    p = tmp_path / "bench.csv"
    with p.open("w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=_bench.FIELDS)
        w.writeheader()
        for r in rows:
            w.writerow({k: r.get(k, "") for k in _bench.FIELDS})
    back = _bench.read_rows(p)
    assert back[0]["time_s"] == 1.0 and np.isnan(back[2]["compile_s"])
