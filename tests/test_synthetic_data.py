"""data_synthetic/: the committed targets agree with their truth.json, and make.py never leaves a
scene half-replaced (new images under an old truth.json entry, or a partial folder)."""

import importlib.util
import json
from pathlib import Path

import numpy as np
import pytest

DATA = Path(__file__).resolve().parents[1] / "data_synthetic"


def _make():
    spec = importlib.util.spec_from_file_location("difffog_data_make", DATA / "make.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def test_the_committed_targets_are_what_truth_json_says():
    """Every set's images have truth.json's shape and mean, its noisy copies differ from them by
    about the recorded σ, and they are finer than the model a fit at `difffog fit`'s defaults
    corrects to (N = 64, M = 4)."""
    make = _make()
    truth = json.loads((DATA / "truth.json").read_text())
    assert sorted(truth) == sorted(make.SETS)
    for name, entry in truth.items():
        r = entry["render"]
        assert r["resolution"] > 64 and r["directions"] > 4, (name, r)
        assert [s["params"] for s in entry["sets"]] == make.SETS[name]
        for k, s in enumerate(entry["sets"]):
            for cam, info in s["images"].items():
                img = np.load(DATA / name / f"set{k}" / f"{cam}.npy")
                assert list(img.shape) == info["shape"], (name, k, cam)
                assert img.mean() == pytest.approx(info["mean"], rel=1e-5), (name, k, cam)
                for level in make.NOISE:
                    noisy = np.load(DATA / name / f"set{k}" / f"{cam}_{level}.npy")
                    sd = float(np.std(noisy.astype(np.float64) - img))
                    assert sd == pytest.approx(info[level]["sigma"], rel=0.05), (name, k, level)


def _old_scene(out: Path) -> None:
    (out / "fog-balls" / "set0").mkdir(parents=True)
    (out / "fog-balls" / "set0" / "top.npy").write_bytes(b"old")
    (out / "truth.json").write_text(json.dumps({"fog-balls": {"render": "old"}}))


def test_make_replaces_a_scene_and_its_truth_together(tmp_path):
    make = _make()
    _old_scene(tmp_path)
    partial = tmp_path / ".fog-balls.partial"
    (partial / "set0").mkdir(parents=True)
    (partial / "set0" / "oblique.npy").write_bytes(b"new")
    truth = json.loads((tmp_path / "truth.json").read_text())
    make.replace_scene("fog-balls", {"render": "new"}, partial, tmp_path, truth)
    assert [p.name for p in (tmp_path / "fog-balls" / "set0").iterdir()] == ["oblique.npy"]
    assert json.loads((tmp_path / "truth.json").read_text()) == {"fog-balls": {"render": "new"}}
    assert sorted(p.name for p in tmp_path.iterdir()) == ["fog-balls", "truth.json"]


def test_make_stopped_part_way_leaves_the_old_targets(tmp_path, monkeypatch):
    make = _make()
    _old_scene(tmp_path)

    def fails_after_one_set(name, root, **kw):
        (root / "set0").mkdir(parents=True)
        (root / "set0" / "top.npy").write_bytes(b"new")
        raise KeyboardInterrupt

    monkeypatch.setattr(make, "make_scene", fails_after_one_set)
    with pytest.raises(KeyboardInterrupt):
        make.main(["--scene", "fog-balls", "--out", str(tmp_path)])
    assert (tmp_path / "fog-balls" / "set0" / "top.npy").read_bytes() == b"old"
    assert json.loads((tmp_path / "truth.json").read_text()) == {"fog-balls": {"render": "old"}}
    assert sorted(p.name for p in tmp_path.iterdir()) == ["fog-balls", "truth.json"]
