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
