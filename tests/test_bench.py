"""The speed-accuracy study (`difffog bench`) and the accuracy presets."""

import csv
import json
import warnings

import numpy as np
import pytest

import difffog as df
from difffog import _bench
from difffog._cli import _apply_accuracy, build_parser, main
from difffog._presets import LEVELS, PRESETS, forward_model, preset


def test_presets_order_cost_and_reject_unknown_names():
    for solver in PRESETS:
        res = [preset(solver, lv)["resolution"] for lv in LEVELS]
        assert res == sorted(res) and res[0] < res[-1], (solver, res)
    assert preset("sweep", "draft")["M"] <= preset("sweep", "high")["M"]
    p = preset("sweep")
    p["resolution"] = 1  # a copy: the table is not changed
    assert PRESETS["sweep"]["default"]["resolution"] != 1
    with pytest.raises(df.DifffogError, match="draft, default, high"):
        preset("sweep", "fast")
    with pytest.raises(df.DifffogError, match="sweep or splat"):
        preset("montecarlo")
    with pytest.raises(df.DifffogError, match="unknown setting"):
        forward_model(df.load_scene("furnace"), accuracy="draft", sheets=3)


def test_cli_accuracy_fills_only_what_is_not_given():
    args = build_parser().parse_args(["render", "--accuracy", "draft"])
    _apply_accuracy(args, "sweep")
    assert (args.resolution, args.directions, args.tol) == (32, 2, 1e-3)
    args = build_parser().parse_args(["render", "--accuracy", "high", "-N", "40", "--tol", "1e-6"])
    _apply_accuracy(args, "sweep")
    assert (args.resolution, args.directions, args.tol) == (40, PRESETS["sweep"]["high"]["M"],
                                                            1e-6)
    args = build_parser().parse_args(["render", "--solver", "splat", "--accuracy", "high"])
    _apply_accuracy(args, "splat")
    assert args.resolution == PRESETS["splat"]["high"]["resolution"] and args.sheets is None
    args = build_parser().parse_args(["render", "--iterations", "5"])
    _apply_accuracy(args, "sweep")
    assert args.tol is None and args.iterations == 5  # exact iteration count wins


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


def test_bench_study_rows_match_an_independent_render(tmp_path, monkeypatch):
    """A one-setting study on fog-balls: the CSV's error is the error of the same render
    computed here, Mitsuba's curve is included, and the Pareto plot is written."""
    refs = _bench.default_references()
    if refs is None:
        pytest.skip("no ../shared/references")
    setting = dict(resolution=12, M=2, tol=1e-3)
    monkeypatch.setitem(_bench.QUICK, "sweep", [setting])
    res = _bench.run_bench(scenes=["fog-balls"], solvers=["sweep"], out=tmp_path / "b",
                           references=refs, quick=True)
    with res.csv_path.open() as f:
        rows = list(csv.DictReader(f))
    ours = [r for r in rows if r["solver"] == "sweep"]
    assert len(ours) == 1 and any(r["solver"].startswith("mitsuba") for r in rows)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # the walls are thinner than a voxel at N = 12
        r = _bench.build("sweep", df.load_scene("fog-balls"), setting)
    err, bias, _ = _bench.scene_errors(r(r.params()), refs, "fog-balls")
    assert float(ours[0]["error"]) == pytest.approx(err, rel=1e-3)
    assert float(ours[0]["time_s"]) > 0 and float(ours[0]["xla_mib"]) > 0
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
    from difffog._presets import PRESETS

    rows = [dict(solver="sweep", scene="s", setting=_bench.setting_label("sweep", PRESETS["sweep"][lv]),
                 time_s=t, compile_s=2.0, setup_s=1.0, xla_mib=10.0, iterations=5, error=e,
                 bias=0.0) for lv, t, e in (("draft", 1.0, 0.2), ("default", 4.0, 0.1))]
    rows += [dict(solver="mitsuba3 (references' run)", scene="s", setting="4 spp", spp=4,
                  time_s=t, error=e) for t, e in ((2.0, 0.2), (8.0, 0.1))]
    md = _bench.summary_markdown(rows)
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
