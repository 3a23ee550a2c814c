"""Seed-paired comparison of training runs (perception/seed_pairs.py, ``robotdemo compare``)."""

import json

import numpy as np
import pytest
from scipy import stats

from perception.dataset import write_dataset
from perception.seed_pairs import compare_arms, load_arm_runs, parse_pair, seed_paired_difference
from perception.train import TrainConfig, train_command
from robotdemo.cli import main
from tests.test_cli import _one_line_error
from tests.test_dataset import make_material_strokes

MANIFEST = "ab" * 32


def _write_run(root, arm, seed, val, test, fold=0, task="ssmc", manifest=MANIFEST, sub="", sensor_use=None):
    folder = root / arm / sub / f"seed{seed}_fold{fold}"
    folder.mkdir(parents=True)
    record = {"task": task, "model": "x", "seed": seed, "fold": fold, "best_val_accuracy": val,
              "test_accuracy": test, "best_epoch": 3, "data_manifest_sha256": manifest}
    if sensor_use is not None:
        record["val_sensor_use"] = sensor_use
    (folder / "metrics.json").write_text(json.dumps(record))
    return folder


def test_hand_example_pairs_by_seed_and_fold_and_counts_wins(tmp_path):
    a = {(0, 0): (0.80, 0.70), (1, 0): (0.90, 0.72), (2, 0): (0.85, 0.75), (3, 0): (0.50, 0.50)}
    b = {(0, 0): (0.75, 0.71), (1, 0): (0.80, 0.70), (2, 0): (0.85, 0.70)}  # seed 3 has no partner
    for (seed, fold), (val, test) in a.items():
        _write_run(tmp_path, "a", seed, val, test, fold)
    for (seed, fold), (val, test) in b.items():
        _write_run(tmp_path, "b", seed, val, test, fold)
    runs = load_arm_runs(tmp_path)
    d = seed_paired_difference(runs, "a", "b", "val")
    expected = np.array([5.0, 10.0, 0.0])
    assert d.n_pairs == 3 and d.differences_points == pytest.approx(tuple(expected))
    assert d.mean_points == pytest.approx(5.0)
    assert (d.won, d.lost, d.tied) == (2, 0, 1)
    ref = stats.ttest_rel([0.80, 0.90, 0.85], [0.75, 0.80, 0.85])
    assert d.p_value == pytest.approx(ref.pvalue)
    half = stats.t.ppf(0.975, 2) * expected.std(ddof=1) / np.sqrt(3)
    assert d.ci95_points == pytest.approx((5.0 - half, 5.0 + half))
    t = seed_paired_difference(runs, "a", "b", "test")
    assert t.mean_points == pytest.approx((-1.0 + 2.0 + 5.0) / 3) and (t.won, t.lost) == (2, 1)


def test_a_clearly_better_recipe_is_told_apart_and_a_copy_is_not(tmp_path):
    rng = np.random.default_rng(0)
    for seed in range(10):
        base = rng.uniform(0.6, 0.8)
        _write_run(tmp_path, "base", seed, base, base)
        _write_run(tmp_path, "better", seed, base + 0.05 + rng.normal(0, 0.01), base + 0.05)
        _write_run(tmp_path, "copy", seed, base, base)
    runs = load_arm_runs(tmp_path)
    better = seed_paired_difference(runs, "better", "base", "val")
    assert better.p_value < 1e-6 and better.ci95_points[0] > 3.0 and better.won == 10
    same = seed_paired_difference(runs, "copy", "base", "val")
    assert same.mean_points == 0.0 and same.p_value == 1.0 and same.tied == 10
    shifted = seed_paired_difference(runs, "better", "base", "test")  # every pair exactly +5: no spread
    assert shifted.mean_points == pytest.approx(5.0) and shifted.ci95_points == pytest.approx((5.0, 5.0))


def test_runs_at_any_depth_under_an_arm_are_found(tmp_path):
    _write_run(tmp_path, "a", 0, 0.5, 0.5, sub="x/y")
    _write_run(tmp_path, "a", 1, 0.5, 0.5)
    assert sorted(load_arm_runs(tmp_path)["a"]) == [(0, 0), (1, 0)]


@pytest.mark.parametrize("setup, call, message", [
    (lambda r: None, lambda r: load_arm_runs(r / "missing"), "does not exist"),
    (lambda r: r.mkdir(exist_ok=True), lambda r: load_arm_runs(r), "holds no ARM/.../metrics.json"),
    (lambda r: (_write_run(r, "a", 0, 0.5, 0.5) / "metrics.json").write_text("{"), lambda r: load_arm_runs(r),
     "not valid JSON"),
    (lambda r: (_write_run(r, "a", 0, 0.5, 0.5) / "metrics.json").write_text('{"seed": 0}'),
     lambda r: load_arm_runs(r), "not a robotdemo train metrics.json (missing task"),
    (lambda r: _write_run(r, "a", 0, float("nan"), 0.5), lambda r: load_arm_runs(r),
     "best_val_accuracy must be an accuracy in [0, 1], got nan"),
    (lambda r: (_write_run(r, "a", 0, 0.5, 0.5, sub="p"), _write_run(r, "a", 0, 0.6, 0.5, sub="q")),
     lambda r: load_arm_runs(r), "arm 'a' has two runs of seed 0 fold 0"),
    (lambda r: (_write_run(r, "a", 0, 0.5, 0.5), _write_run(r, "a", 1, 0.5, 0.5)),
     lambda r: seed_paired_difference(load_arm_runs(r), "a", "b", "val"), "no arm 'b' in the runs folder (arms: a)"),
    (lambda r: (_write_run(r, "a", 0, 0.5, 0.5), _write_run(r, "b", 0, 0.5, 0.5)),
     lambda r: seed_paired_difference(load_arm_runs(r), "a", "b", "val"), "share 1 (seed, fold) run(s)"),
    (lambda r: (_write_run(r, "a", 0, 0.5, 0.5), _write_run(r, "a", 1, 0.5, 0.5),
                _write_run(r, "b", 0, 0.5, 0.5), _write_run(r, "b", 1, 0.5, 0.5, manifest="cd" * 32)),
     lambda r: seed_paired_difference(load_arm_runs(r), "a", "b", "val"), "of different data sets or tasks"),
    (lambda r: None, lambda r: parse_pair("a:b:c"), "a pair must be ARM:AGAINST"),
])
def test_bad_runs_folders_are_refused_with_a_message_naming_the_problem(tmp_path, setup, call, message):
    root = tmp_path / "runs"
    root.mkdir()
    setup(root)
    with pytest.raises(ValueError, match=None) as info:
        call(root)
    assert message in str(info.value)


def test_compare_cli_pairs_real_training_runs_and_writes_json_and_png(tmp_path, capsys):
    recs = make_material_strokes(2, n_categories=2, n_instances=2, n_objects=2, n_strokes=3, duration_s=0.2)
    write_dataset(tmp_path / "ds", recs, env="clean", seed=2)
    for model in ("mtcnn", "lstm"):
        for seed in (0, 1):
            train_command(tmp_path / "ds", tmp_path / "runs" / model / f"s{seed}",
                          TrainConfig(model=model, epochs=1, batch_size=4, seed=seed, device="cpu"),
                          command="robotdemo train", progress=False)
    out_json, out_png = tmp_path / "cmp.json", tmp_path / "cmp.png"
    code = main(["compare", str(tmp_path / "runs"), "--pair", "mtcnn:lstm", "--json", str(out_json),
                 "--png", str(out_png)])
    assert code == 0
    printed = capsys.readouterr().out
    assert "mtcnn - lstm (2 pairs): val" in printed and "lstm: 2 runs" in printed
    result = json.loads(out_json.read_text())
    assert result["pairs"][0]["test"]["n_pairs"] == 2
    assert result == json.loads(json.dumps(compare_arms(tmp_path / "runs", [("mtcnn", "lstm")])))
    assert out_png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_compare_cli_errors_are_one_line(tmp_path, capsys):
    _one_line_error(capsys, main(["compare", str(tmp_path / "nothing")]), "does not exist or is not a folder")
    _write_run(tmp_path, "a", 0, 0.5, 0.5)
    _one_line_error(capsys, main(["compare", str(tmp_path), "--pair", "a"]), "a pair must be ARM:AGAINST")
    _one_line_error(capsys, main(["compare", str(tmp_path), "--json", str(tmp_path)]), "is a folder")


def _use(dropped: dict[str, float]) -> dict[str, dict]:
    return {m: {"n_strokes": 20, "mean_alpha": 0.0 if dropped.get(m, 0.0) == 1.0 else 0.3,
                "dropped_share": dropped.get(m, 0.0)} for m in ("sound", "normal", "friction", "accel")}


def test_the_runs_in_which_the_gate_shut_a_sensor_out_are_counted_per_arm(tmp_path, capsys):
    _write_run(tmp_path, "stems", 0, 0.43, 0.40, sensor_use=_use({"normal": 1.0, "friction": 0.9}))
    _write_run(tmp_path, "stems", 1, 0.60, 0.58, sensor_use=_use({"normal": 0.5}))  # half is not shut out
    _write_run(tmp_path, "stems", 2, 0.59, 0.57, sensor_use=_use({"accel": 0.2}))
    _write_run(tmp_path, "stems", 3, 0.58, 0.55)  # predates val_sensor_use: not counted either way
    for seed in range(4):
        _write_run(tmp_path, "old", seed, 0.55, 0.52)
    result = compare_arms(tmp_path, [("stems", "old")])
    stems = result["arms"]["stems"]
    assert stems["sensor_use_recorded"] == 3
    assert stems["sensor_shut_out"] == [{"seed": 0, "fold": 0, "sensors": ["normal", "friction"]}]
    assert result["arms"]["old"]["sensor_use_recorded"] == 0 and result["arms"]["old"]["sensor_shut_out"] == []
    assert main(["compare", str(tmp_path), "--pair", "stems:old"]) == 0
    lines = capsys.readouterr().out.splitlines()
    assert lines[1].endswith("a sensor shut out by the gate in 1 of 3 runs (seed 0 fold 0: normal+friction)")
    assert lines[0].startswith("old: 4 runs") and "shut out" not in lines[0]


def test_a_malformed_sensor_use_is_refused_in_one_line(tmp_path, capsys):
    _write_run(tmp_path, "a", 0, 0.5, 0.5, sensor_use={"normal": {"dropped_share": 1.0}})
    _write_run(tmp_path, "b", 0, 0.5, 0.5, sensor_use=[1, 2])
    with pytest.raises(ValueError) as info:
        load_arm_runs(tmp_path)
    assert "malformed val_sensor_use" in str(info.value) and "metrics.json" in str(info.value)
    _one_line_error(capsys, main(["compare", str(tmp_path)]), "malformed val_sensor_use")
