"""Evaluation protocol (perception.evaluate): metrics and the quick end-to-end report."""

from __future__ import annotations

import dataclasses
import json
import shutil
from pathlib import Path

import numpy as np
import pytest
import torch

from perception.checkpoint import load_checkpoint
from perception.dataset import write_dataset
from perception.evaluate import _category_recall, evaluate, g_mean, quick_config
from perception.report import PAPER, write_report
from tests.test_dataset import make_material_strokes


def test_g_mean_hand_example():
    y_true = [0, 0, 1, 1, 2, 2]
    y_pred = [0, 1, 1, 1, 2, 0]  # recalls 0.5, 1.0, 0.5
    assert g_mean(y_true, y_pred) == pytest.approx(0.25 ** (1 / 3))
    assert g_mean(y_true, y_true) == pytest.approx(1.0)
    assert g_mean(y_true, [0, 0, 0, 0, 2, 2]) == 0.0  # class 1 never recalled
    # a class absent from y_true has no recall and is skipped
    assert g_mean([0, 0, 1, 1], [0, 2, 1, 1], labels=range(3)) == pytest.approx(0.5 ** 0.5)


def test_failed_runs_are_those_whose_training_never_reached_twice_chance():
    from perception.evaluate import _failed_runs

    def run(model, curve, n_classes=7, seed=0):
        return {"model": model, "task": "ssmc", "split": f"seed{seed}", "seed": seed, "corruption_ratio": 1.0,
                "corruption_std": 3.0, "accuracy": 0.135, "checkpoint": f"runs/{model}/seed{seed}/checkpoint",
                "train_accuracy_curve": curve, "_names": tuple(range(n_classes))}

    stuck = run("mtcnn", [0.142, 0.135, 0.143], seed=2)  # cross-entropy at ln 7: never above 1/7
    learned = run("mtcnn", [0.142, 0.30, 0.85], seed=0)
    barely = run("lstm", [0.10, 2 / 7])  # reaches twice chance: it learned something
    reference = {**run("reference", []), "train_accuracy_curve": None}
    failed = _failed_runs([learned, stuck, barely, reference])
    assert [(r["model"], r["seed"]) for r in failed] == [("mtcnn", 2)]
    assert failed[0]["max_train_accuracy"] == 0.143 and failed[0]["n_classes"] == 7
    assert failed[0]["checkpoint"] == "runs/mtcnn/seed2/checkpoint" and "_names" not in failed[0]
    assert _failed_runs([stuck], Path("runs"))[0]["checkpoint"] == "mtcnn/seed2/checkpoint"  # relative to out_dir
    assert _failed_runs([run("lstm", [0.09, 0.095], n_classes=42)]) == []  # 42 classes: twice chance is 4.8 %


def _write_toy_clean_and_fire(tmp_path):
    """Write a small clean and fire data set to ``tmp_path / "clean"`` and ``/ "fire"``; return the clean strokes."""
    clean = make_material_strokes(0, n_categories=3, n_instances=2, n_objects=2, n_strokes=3, duration_s=0.25)
    fire = make_material_strokes(1, n_categories=3, n_instances=2, n_objects=1, n_strokes=4, duration_s=0.25,
                                 env="fire")
    write_dataset(tmp_path / "clean", clean, env="clean", seed=0)
    write_dataset(tmp_path / "fire", fire, env="fire", seed=1)
    return clean


def test_quick_evaluation_writes_report(tmp_path):
    torch.set_num_threads(1)
    clean = _write_toy_clean_and_fire(tmp_path)
    out = tmp_path / "report"
    results = evaluate(tmp_path / "clean", out, quick=True, fire_dir=tmp_path / "fire", progress=False,
                       command="robotdemo evaluate --quick")

    for name in ("REPORT.md", "results.json", "robustness.png", "tsne.png", "training_curves.png",
                 "confusion_ssmc_touchformer.png",
                 "confusion_usmc_touchformer.png", "confusion_fine_touchformer.png"):
        assert (out / name).is_file() and (out / name).stat().st_size > 0, name
    saved = json.loads((out / "results.json").read_text())
    assert saved["provenance"]["data_manifest_sha256"] == results["provenance"]["data_manifest_sha256"]
    assert saved["provenance"]["command"] == "robotdemo evaluate --quick"
    for task in ("ssmc", "usmc", "fine"):
        for model in ("touchformer", "touchformer_soft", "lstm", "mtcnn", "reference"):
            acc = saved["table1"][task][model]["accuracy"]
            assert 0.0 <= acc["mean"] <= 1.0
        assert len(saved["table1"][task]["touchformer"]["runs"]) == (2 if task == "usmc" else 1)
    for task in ("ssmc", "usmc", "fine"):  # TouchFormer against every other model on the same test strokes
        assert set(saved["paired"][task]) == {"touchformer_soft", "lstm", "mtcnn", "reference"}
        table = saved["table1"][task]
        for model, c in saved["paired"][task].items():
            assert c["difference_points"] == pytest.approx(
                100 * (table["touchformer"]["accuracy"]["mean"] - table[model]["accuracy"]["mean"]))
            assert c["n_strokes"] == sum(r["n_test"] for r in table[model]["runs"])
            low, high = c["ci95_points"]
            assert low <= c["difference_points"] <= high and 0.0 <= c["mcnemar_p"] <= 1.0
    assert "### TouchFormer against each model on the same test strokes" in (out / "REPORT.md").read_text()
    assert "| TouchFormer - it [points] (95 % interval over the test strokes) |" in (out / "REPORT.md").read_text()
    categories = {r.category for r in clean}
    for task in ("ssmc", "usmc"):  # recall per category over the runs' test strokes pooled
        for model, recall in saved["category_recall"][task].items():
            assert set(recall) == categories and all(0.0 <= v <= 1.0 for v in recall.values())
    for model, recall in saved["category_recall"]["usmc"].items():
        # each toy USMC fold tests one instance of every category (6 strokes each): classes and folds are
        # equal in size, so the mean recall is the mean fold accuracy
        assert np.mean(list(recall.values())) == pytest.approx(saved["table1"]["usmc"][model]["accuracy"]["mean"])
    assert "### Recall per category" in (out / "REPORT.md").read_text()
    assert set(saved["missing_modality"]["touchformer"]) == {"sound", "normal", "friction", "accel", "none"}
    assert set(saved["ablation"]) == {"touchformer_fusion", "touchformer_mag", "touchformer", "touchformer_soft"}
    steps = [(c["baseline"], c["model"], c["task"]) for c in saved["ablation_paired"]]  # + MAG, then + CER
    order = (("touchformer_fusion", "touchformer_mag"), ("touchformer_mag", "touchformer"))
    assert steps == [(b, a, t) for b, a in order for t in ("ssmc", "usmc", "fine")]
    for c in saved["ablation_paired"]:
        after, before = saved["ablation"][c["model"]][c["task"]], saved["ablation"][c["baseline"]][c["task"]]
        assert c["difference_points"] == pytest.approx(100 * (after["mean"] - before["mean"]))
    assert "Each step against the one before it" in (out / "REPORT.md").read_text()
    weights = saved["modality_weights"]["usmc"]
    assert weights["touchformer_fusion"]["alpha_mean"] == pytest.approx([0.25] * 4, abs=1e-4)  # uniform
    assert weights["touchformer_fusion"]["gate_dropped_share"] == [0.0] * 4
    for model in ("touchformer", "touchformer_mag", "touchformer_soft"):
        assert sum(weights[model]["alpha_mean"]) == pytest.approx(1.0, abs=1e-3)  # every toy stroke has all four
        assert all(0.0 <= d <= 1.0 for d in weights[model]["gate_dropped_share"])
    assert weights["touchformer_soft"]["gate_dropped_share"] == [0.0] * 4  # no threshold: nothing dropped
    fit = saved["fitting"]["ssmc"]["touchformer"]
    assert 1 <= fit["best_epoch"]["mean"] <= 2 and 0.0 <= fit["final_train_accuracy"]["mean"] <= 1.0
    run = saved["table1"]["ssmc"]["touchformer"]["runs"][0]
    assert len(run["val_accuracy_curve"]) == 2
    assert max(run["val_accuracy_curve"]) == pytest.approx(run["best_val_accuracy"], abs=1e-4)
    levels = saved["robustness"]["levels"]
    assert [level["corruption_std"] for level in levels] == [1.0, 3.0] == saved["robustness"]["corruption_stds"]
    for level in levels:
        for model in ("touchformer", "lstm", "mtcnn", "touchformer_soft"):
            assert set(level["curves"][model]) == {"0.0", "0.5", "1.0"}
        # p = 0 is Table 1's SSMC run at every intensity (one seed in the quick run, so std 0)
        assert level["curves"]["touchformer"]["0.0"] == pytest.approx(
            saved["table1"]["ssmc"]["touchformer"]["accuracy"]["mean"])
        # one seed: no sample std (it used to print a misleading "± 0.00")
        assert all(v != v for v in level["curves_std"]["touchformer"].values())
        assert set(level["seed_wins"]) == {"0.0", "0.5", "1.0"} and set(level["seed_wins"].values()) <= {0, 1}
        for p, c in level["paired_best_baseline"].items():  # against the better of the LSTM and MTCNN at p
            assert c["baseline"] in ("lstm", "mtcnn") and c["model"] == "touchformer"
            best = max(level["curves"]["lstm"][p], level["curves"]["mtcnn"][p])
            assert level["curves"][c["baseline"]][p] == pytest.approx(best)
            assert c["difference_points"] == pytest.approx(100 * (level["curves"]["touchformer"][p] - best))
        assert set(level["paired_best_baseline"]) == {"0.0", "0.5", "1.0"}
        assert all(Path(c[0]).is_dir() for c in level["checkpoints"]["touchformer"].values())
    assert "(n=1)" in (out / "REPORT.md").read_text()  # one SSMC seed in the quick run: no std to print
    # each run's checkpoint names the data it trained on, and the report counts the commits that trained them
    fire_sha = saved["provenance"]["fire_manifest_sha256"]
    for seed_dir in (out / "runs" / "fire").iterdir():
        for run_dir in seed_dir.iterdir():
            meta = load_checkpoint(run_dir / "checkpoint").meta
            expected = saved["provenance"]["data_manifest_sha256"] if run_dir.name.startswith("clean_") else fire_sha
            assert meta["data_manifest_sha256"] == expected, run_dir
    commits = saved["provenance"]["run_commits"]
    assert commits and all(n > 0 for n in commits.values()) and "runs by the commit that trained them" in (
        out / "REPORT.md").read_text()
    assert saved["provenance"]["git_dirty"] in (True, False, None)
    assert "std 1 and 3;" in saved["deviations"]["robustness_noise"]
    single = saved["single_sensor"]["touchformer_soft"]
    assert set(single) == {"sound", "normal", "friction", "accel", "all"}
    np.testing.assert_equal(single["all"]["accuracy"], saved["table1"]["ssmc"]["touchformer_soft"]["accuracy"])
    for i, sensor in enumerate(("sound", "normal", "friction", "accel")):
        run = single[sensor]["runs"][0]
        assert load_checkpoint(run["checkpoint"]).feature_config.modalities == (sensor,)
        assert run["alpha_mean"][i] == pytest.approx(1.0)  # the only sensor it was given carries all the weight
        assert 0.0 <= single[sensor]["accuracy"]["mean"] <= 1.0
    assert "One sensor at a time" in (out / "REPORT.md").read_text()
    assert len(saved["fire"]["rows"]) == 3 * 2 + 2  # three per network, two for the reference
    assert {row["model"] for row in saved["fire"]["rows"]} == {"touchformer", "touchformer_soft", "reference"}
    assert all(0.0 <= row["accuracy"]["mean"] <= 1.0 for row in saved["fire"]["rows"])
    # the reference classifier is a sanity floor that the toy data lets it reach
    assert saved["table1"]["ssmc"]["reference"]["accuracy"]["mean"] > 0.6
    report = (out / "REPORT.md").read_text()
    assert str(PAPER["table1"]["ssmc"]["touchformer"][0]) in report and "Deviations" in report
    assert "Which sensors the models trusted" in report
    assert "| TouchFormer, MAG without threshold |" in report and "our variant, not the paper's" in report
    assert results["provenance"]["data_manifest_sha256"] in report
    # USMC test instances never appear in the training part of their fold
    for run in saved["table1"]["usmc"]["touchformer"]["runs"]:
        assert run["n_train"] + run["n_test"] == len(clean)
    assert isinstance(saved["failed_runs"], list) and "## Runs that never learned" in report
    probes = saved["probes"]
    assert set(probes) == {"ssmc", "usmc", "fine"} and (out / "probes.png").stat().st_size > 0
    for task in probes:
        for model in ("touchformer", "touchformer_soft", "lstm", "mtcnn"):
            assert set(probes[task][model]) == {"intact", "time_shuffled", "time_reversed", "desync", "swap"}
            np.testing.assert_equal(probes[task][model]["intact"], saved["table1"][task][model]["accuracy"])
            assert all(0.0 <= st["mean"] <= 1.0 for st in probes[task][model].values())
        assert set(probes[task]["reference"]) == {"intact", "swap"}  # statistics have no frame order
    assert "## What the networks use" in report and "| sensors shifted apart | sensors from other strokes |" in report
    for failed in saved["failed_runs"]:
        assert failed["max_train_accuracy"] < 2.0 / failed["n_classes"]
    assert np.isfinite(saved["seconds"])
    # the report is a function of results.json alone: written again from the saved file, it is the same text
    write_report(tmp_path / "again.md", saved)
    assert (tmp_path / "again.md").read_text() == report


def test_parallel_training_gives_the_sequential_results(tmp_path, monkeypatch):
    import perception.evaluate as evaluation

    torch.set_num_threads(1)
    _write_toy_clean_and_fire(tmp_path)
    config = dataclasses.replace(quick_config(), models=("touchformer", "lstm", "reference"), ablation=False,
                                 robustness_models=("lstm",), corruption_ratios=(0.0, 1.0), tsne=False,
                                 fire_models=("lstm",), single_sensor_models=("lstm",))
    pretrained: list[str] = []
    pretrain = evaluation._pretrain

    def spy(ctx, jobs, workers, **kwargs):
        pretrained.extend(str(job.run_dir(ctx).relative_to(ctx.out_dir / "runs")) for job in jobs)
        return pretrain(ctx, jobs, workers, **kwargs)

    monkeypatch.setattr(evaluation, "_pretrain", spy)
    runs = {}
    for workers in (1, 2):
        out = tmp_path / f"w{workers}"
        runs[workers] = evaluate(tmp_path / "clean", out, config=config, progress=False, workers=workers,
                                 fire_dir=tmp_path / "fire")
        assert (out / "REPORT.md").is_file()
    for task in ("ssmc", "usmc", "fine"):
        for model in ("touchformer", "lstm", "reference"):
            np.testing.assert_equal(runs[1]["table1"][task][model]["accuracy"],  # NaN std (one run) equals NaN
                                    runs[2]["table1"][task][model]["accuracy"], err_msg=f"{task} {model}")
    for one, two in zip(runs[1]["robustness"]["levels"], runs[2]["robustness"]["levels"]):
        np.testing.assert_equal({k: v for k, v in one.items() if k != "checkpoints"},  # run folders differ
                                {k: v for k, v in two.items() if k != "checkpoints"})
    single = {w: runs[w]["single_sensor"]["lstm"] for w in (1, 2)}
    for sensor in ("sound", "normal", "friction", "accel", "all"):
        np.testing.assert_equal(single[1][sensor]["accuracy"], single[2][sensor]["accuracy"])
    assert sum(name.startswith("single_sensor/lstm/") for name in pretrained) == 4
    # the workers trained the fire runs too, fine-tuning after the clean run it starts from
    fire_runs = [name for name in pretrained if name.startswith("fire/")]
    assert set(fire_runs) == {"fire/seed0/clean_lstm", "fire/seed0/scratch_lstm", "fire/seed0/finetuned_lstm"}
    assert fire_runs[-1] == "fire/seed0/finetuned_lstm"
    np.testing.assert_equal(runs[1]["fire"]["rows"], runs[2]["fire"]["rows"])
    assert len(runs[2]["fire"]["rows"]) == 3 + 2
    report = (tmp_path / "w2" / "REPORT.md").read_text()
    assert "Not run in this report (`--no-ablation`)" in report
    no_fire = dataclasses.replace(config, models=("reference",), robustness_models=())
    evaluate(tmp_path / "clean", tmp_path / "nofire", config=no_fire, progress=False)
    assert "no `--fire` data set given" in (tmp_path / "nofire" / "REPORT.md").read_text()


def _twin_recordings(n_per_class: int = 12):
    """A clean and a fire recording of the same strokes (same instance, object and stroke draw), the fire one in
    another order, as two ``robotdemo dataset`` runs with one seed give (the order here differs on purpose)."""
    clean = make_material_strokes(0, n_categories=3, n_instances=2, n_objects=2, n_strokes=n_per_class // 4,
                                  duration_s=0.05)
    clean = [dataclasses.replace(r, meta={**r.meta, "stroke_seed": 1000 + i}) for i, r in enumerate(clean)]
    order = np.random.default_rng(3).permutation(len(clean))
    fire = [dataclasses.replace(clean[i], meta={**clean[i].meta, "env": "fire"}) for i in order]
    return clean, fire


def test_clean_models_of_the_fire_shift_never_train_on_a_fire_test_strokes_clean_twin():
    from perception.dataset import ssmc_split
    from perception.evaluate import clean_training_part

    clean, fire = _twin_recordings()
    key = lambda r: (r.instance, r.meta["object_id"], r.meta["stroke_seed"])  # noqa: E731
    for seed in (0, 1, 2):
        fire_test = ssmc_split(fire, seed)[1]
        part = clean_training_part(clean, fire, fire_test, seed)
        assert set(part) <= set(ssmc_split(clean, seed)[0])  # within the clean SSMC training part
        assert not {key(clean[i]) for i in part} & {key(fire[i]) for i in fire_test}  # no twin of a test stroke
        assert len(part) < len(ssmc_split(clean, seed)[0])  # the shuffled order put some twins there
    # without stroke draws in the meta (e.g. converted recordings) it is the clean SSMC training part
    plain = [dataclasses.replace(r, meta={"env": "clean"}) for r in clean]
    np.testing.assert_array_equal(clean_training_part(plain, fire, ssmc_split(fire, 0)[1], 0),
                                  ssmc_split(plain, 0)[0])


def test_robustness_runs_are_scored_on_fire_strokes_whose_clean_twin_they_never_trained_on():
    from types import SimpleNamespace

    from perception.dataset import ssmc_split
    from perception.evaluate import _zero_shot_test

    clean, fire = _twin_recordings()
    key = lambda r: (r.instance, r.meta["object_id"], r.meta["stroke_seed"])  # noqa: E731
    for seed in (0, 1, 2):
        split, fire_test = ssmc_split(clean, seed), ssmc_split(fire, seed)[1]
        ctx = SimpleNamespace(data=SimpleNamespace(records=clean),
                              fire=SimpleNamespace(data=SimpleNamespace(records=fire), splits={seed: (None, fire_test)}))
        scored = _zero_shot_test(ctx, SimpleNamespace(split=split, seed=seed))
        seen = {key(clean[i]) for i in split[0]}
        assert set(scored) == {i for i in fire_test if key(fire[i]) not in seen}
        assert 0 < len(scored) < len(fire_test)  # the shuffled order put some twins in the clean training part


def test_a_fine_tuned_run_is_trained_again_when_the_checkpoint_it_starts_from_changes(tmp_path):
    from perception.train import StaleRunError, TrainConfig, train

    clean, _ = _twin_recordings(8)
    base = TrainConfig(model="lstm", epochs=1, batch_size=8, seed=0, model_overrides=(("hidden", 8),))
    parent = tmp_path / "parent"
    train(clean[:30], clean[30:40], base, parent, progress=False)
    tuned = dataclasses.replace(base, init_checkpoint=str(parent / "checkpoint"))
    train(clean[:30], clean[30:40], tuned, tmp_path / "tuned", progress=False)
    train(clean[:30], clean[30:40], tuned, tmp_path / "tuned", progress=False)  # same parent: resumed
    train(clean[10:40], clean[:10], base, tmp_path / "parent2", progress=False)
    shutil.rmtree(parent)
    shutil.copytree(tmp_path / "parent2", parent)  # the parent's folder now holds other weights
    with pytest.raises(StaleRunError, match="another config"):
        train(clean[:30], clean[30:40], tuned, tmp_path / "tuned", progress=False)


def test_fire_shift_and_robustness_repeat_every_run_per_seed(tmp_path):
    from perception.report import _pct

    torch.set_num_threads(1)
    _write_toy_clean_and_fire(tmp_path)
    config = dataclasses.replace(quick_config(), seeds=(0, 1), models=("reference",), ablation=False,
                                 missing_modality=False, robustness_models=("lstm",), corruption_ratios=(0.0, 1.0),
                                 tsne=False, fire_models=("lstm",), single_sensor_models=())
    out = tmp_path / "report"
    results = evaluate(tmp_path / "clean", out, config=config, progress=False, fire_dir=tmp_path / "fire")

    rows = {row["label"]: row for row in results["fire"]["rows"]}
    assert len(rows) == 3 + 2 and results["fire"]["split"] == "ssmc seeds 0, 1"
    for row in rows.values():
        assert [r["seed"] for r in row["runs"]] == [0, 1]
        accuracies = [r["accuracy"] for r in row["runs"]]
        assert row["accuracy"]["n"] == 2 and row["accuracy"]["mean"] == pytest.approx(np.mean(accuracies))
        assert row["accuracy"]["std"] == pytest.approx(np.std(accuracies, ddof=1))  # sample std
    for seed in (0, 1):  # each seed trains its own clean model and fine-tunes from that one
        for kind in ("clean", "finetuned", "scratch"):
            run_dir = out / "runs" / "fire" / f"seed{seed}" / f"{kind}_lstm"
            assert (run_dir / "checkpoint" / "model.safetensors").is_file()
        tuned = json.loads((out / "runs" / "fire" / f"seed{seed}" / "finetuned_lstm" / "checkpoint" /
                            "config.json").read_text())
        assert f"fire/seed{seed}/clean_lstm" in json.dumps(tuned)
    rob = results["robustness"]
    assert rob["seeds"] == [0, 1]
    for level in rob["levels"]:
        std = level["corruption_std"]
        for p in ("0.0", "1.0"):
            accuracies = level["per_seed"]["lstm"][p]
            assert len(accuracies) == 2
            assert level["curves"]["lstm"][p] == pytest.approx(np.mean(accuracies))
            assert level["curves_std"]["lstm"][p] == pytest.approx(np.std(accuracies, ddof=1))
            for seed in (0, 1):  # p = 0 is one run for every intensity; each intensity has its own noisy runs
                name = f"seed{seed}_p{p}" + ("" if p == "0.0" else f"_std{std:g}")
                run_dir = out / "runs" / "ssmc" / "lstm" / name
                assert (run_dir / "checkpoint" / "model.safetensors").is_file()
                if p != "0.0":
                    trained = json.loads((run_dir / "checkpoint" / "config.json").read_text())
                    assert trained["meta"]["train_config"]["corruption_std"] == std
    weak, strong = (level["per_seed"]["lstm"] for level in rob["levels"])
    assert weak["0.0"] == strong["0.0"] and weak["1.0"] != strong["1.0"]
    # every run of the curve scored zero-shot on the fire test strokes of its seed, without test noise
    from perception.dataset import load_dataset, ssmc_split
    from perception.features import feature_dims
    from perception.train import featurize_records, predict

    fire = load_dataset(tmp_path / "fire")
    on_fire = rob["fire_zero_shot"]
    assert [level["corruption_std"] for level in on_fire] == [level["corruption_std"] for level in rob["levels"]]
    for level in on_fire:
        std = level["corruption_std"]
        for p in ("0.0", "1.0"):
            for seed in (0, 1):
                name = f"seed{seed}_p{p}" + ("" if p == "0.0" else f"_std{std:g}")
                ckpt = load_checkpoint(out / "runs" / "ssmc" / "lstm" / name / "checkpoint")
                test = ssmc_split(fire.records, seed)[1]
                pred = predict(ckpt.model, featurize_records([fire.records[i] for i in test], ckpt.feature_config),
                               feature_dims(ckpt.feature_config), stats=ckpt.norm_stats).pred
                y = [ckpt.class_names.index(fire.records[i].category) for i in test]
                assert level["per_seed"]["lstm"][p][seed] == pytest.approx(np.mean(pred == np.array(y)))
                assert level["n_test"]["lstm"][p][seed] == len(test)
                assert level["stored_test_agreement"]["lstm"][p][seed] == 1.0  # the run's own checkpoint
        assert level["curves"]["lstm"]["1.0"] == pytest.approx(np.mean(level["per_seed"]["lstm"]["1.0"]))
        assert level["alpha_mean"] == {}  # the LSTM has no gate
    assert on_fire[0]["per_seed"]["lstm"]["0.0"] == on_fire[1]["per_seed"]["lstm"]["0.0"]  # one p = 0 run
    assert "robustness_fire.png" in results["figures"] and (out / "robustness_fire.png").stat().st_size > 0
    report = (out / "REPORT.md").read_text()
    assert "Mean ± std over the seeds (ssmc seeds 0, 1" in report
    assert report.count("| std over the seeds | p=0.0 | p=1.0 |") == 2
    assert "| noise std 1 | p=0.0 | p=1.0 |" in report and "| noise std 3 | p=0.0 | p=1.0 |" in report
    assert "### The robustness runs on fire strokes (zero-shot accuracy [%])" in report
    assert "| trained at noise std 3 | p=0.0 | p=1.0 |" in report
    assert f"| LSTM | {100 * on_fire[1]['curves']['lstm']['0.0']:.1f} ± " in report
    assert "as the run store holds on every stroke (6 checkpoints)" in report  # 2 seeds x (p = 0, 1 x 2 stds)
    assert f"| {_pct(rows['reference, fire only']['accuracy'])} |" in report


def test_inference_benchmark_reports_latency(tmp_path):
    from perception.bench_inference import run_inference_benchmark

    import threadpoolctl

    pools = [p["num_threads"] for p in threadpoolctl.threadpool_info()]
    result = run_inference_benchmark("mtcnn", n=5, batch=4, duration_s=0.3, seed=3)
    assert result["threads"] == 1 and result["model"] == "mtcnn" and result["seed"] == 3
    assert [p["num_threads"] for p in threadpoolctl.threadpool_info()] == pools  # BLAS pools restored
    b1 = result["batch1"]
    assert 0 < b1["median_ms"] <= b1["p95_ms"] and b1["featurize_median_ms"] > 0
    assert result["batch4"]["strokes_per_s"] > 0 and isinstance(result["meets_target"], bool)
    assert result["batch4"]["repeats"] >= 3  # a median, not one timing
    with pytest.raises(ValueError, match="neither a checkpoint folder nor a model name"):
        run_inference_benchmark("no-such-model", n=1)


def test_evaluate_cli_takes_the_noise_intensities_and_the_accelerometer_front_end(tmp_path, capsys):
    from robotdemo.cli import main

    torch.set_num_threads(1)
    _write_toy_clean_and_fire(tmp_path)
    args = ["evaluate", "--data", str(tmp_path / "clean"), "--quick", "--no-ablation", "--quiet", "--seeds", "0"]
    split = ["--accel-axes", "normal-tangential"]
    assert main([*args, *split, "--out", str(tmp_path / "report"), "--corruption-stds", "2",
                 "--no-single-sensor"]) == 0
    capsys.readouterr()
    saved = json.loads((tmp_path / "report" / "results.json").read_text())
    report = (tmp_path / "report" / "REPORT.md").read_text()
    assert "single_sensor" not in saved and not (tmp_path / "report" / "runs" / "single_sensor").exists()
    assert "Not run in this report (`--no-single-sensor`)" in report
    assert saved["robustness"]["corruption_stds"] == [2.0]
    assert [level["corruption_std"] for level in saved["robustness"]["levels"]] == [2.0]
    assert (tmp_path / "report" / "runs" / "ssmc" / "lstm" / "seed0_p0.5_std2").is_dir()
    # every network run, the robustness runs too, was trained on the split accelerometer front end, and the
    # report says so among its deviations
    for run in ("ssmc/touchformer/seed0_p0.0", "usmc/mtcnn/seed0_fold0_p0.0", "ssmc/lstm/seed0_p0.5_std2"):
        ckpt = load_checkpoint(tmp_path / "report" / "runs" / run / "checkpoint")
        assert ckpt.feature_config.accel.channel_groups == ((2,), (0, 1)), run
    assert saved["deviations"]["accel_front_end"].startswith("every network's accelerometer front end keeps channel "
                                                             "groups [[2], [0, 1]] apart")
    assert "- **accel_front_end**: every network's accelerometer front end" in report
    for stds, stored in (("2", 8), ("3", 0)):  # --status counts the runs of the evaluation the options ask for
        assert main([*args, *split, "--out", str(tmp_path / "report"), "--corruption-stds", stds, "--status"]) == 0
        status = json.loads(capsys.readouterr().out)
        assert status["experiments"]["robustness"] == {"stored": stored, "runs": 8}  # 4 networks at p = 0.5, 1
        assert status["experiments"]["table1"]["stored"] == status["experiments"]["table1"]["runs"] == 16
        assert status["experiments"]["single_sensor"] == {"stored": 0, "runs": 4}  # left out of the run above
    # the summed front end (the default) is another evaluation: none of its network runs is stored yet
    assert main([*args, "--out", str(tmp_path / "report"), "--corruption-stds", "2", "--status"]) == 0
    status = json.loads(capsys.readouterr().out)
    assert status["experiments"]["robustness"]["stored"] == status["experiments"]["table1"]["stored"] == 0
    for bad in ("-1", "0", "nan"):
        code = main([*args, "--out", str(tmp_path / "bad"), "--corruption-stds", "3", bad])
        err = capsys.readouterr().err
        assert code == 2 and "corruption_stds must be one or more finite noise stds > 0" in err
        assert len(err.strip().splitlines()) == 1 and not (tmp_path / "bad").exists()


def test_command_config_sets_every_runs_accelerometer_front_end_and_names_an_unknown_one():
    from perception.evaluate import command_config

    assert command_config().train.feature_config.accel.channel_groups == ()  # the paper's summed spectrum
    config = command_config(quick=True, accel_axes="normal-tangential")
    assert config.train.feature_config.accel.channel_groups == ((2,), (0, 1))
    assert config.train.epochs == quick_config().train.epochs  # the rest of the quick settings kept
    with pytest.raises(ValueError, match="accel_axes must be one of \\['normal-tangential', 'sum'\\], got 'xyz'"):
        command_config(accel_axes="xyz")


def test_run_store_keeps_outcomes_and_names_a_bad_line(tmp_path):
    from perception.run_store import RunStore, RunStoreError, decode_array, encode_array

    store = RunStore(tmp_path / "outcomes.jsonl")
    assert store.load() == {}
    emb = np.random.default_rng(0).normal(size=(5, 3)).astype(np.float32)
    store.append("a", "ssmc/lstm/seed0_p0.0", {"pred": {"none": [0, 1]}, "embedding": encode_array(emb)})
    store.append("b", "ssmc/lstm/seed1_p0.0", {"pred": {"none": [1, 1]}})
    store.append("a", "ssmc/lstm/seed0_p0.0", {"pred": {"none": [1, 0]}})  # a later line replaces an earlier one
    loaded = store.load()
    assert set(loaded) == {"a", "b"} and loaded["a"]["pred"]["none"] == [1, 0]
    np.testing.assert_allclose(decode_array(encode_array(emb)), emb, atol=2e-3)  # float16
    with open(store.path, "a") as handle:  # an evaluation killed mid-write leaves an unfinished last line
        handle.write('{"id": "c", "run": "x", "outc')
    assert set(store.load()) == {"a", "b"}
    store.append("d", "y", {"pred": {}})  # the unfinished line is dropped, the new one complete
    assert set(store.load()) == {"a", "b", "d"}
    lines = store.path.read_text().splitlines()
    store.path.write_text("\n".join(lines))  # a whole last record without its newline (an edit) is kept
    store.append("e", "z", {"pred": {}})
    assert set(store.load()) == {"a", "b", "d", "e"}
    lines = store.path.read_text().splitlines()
    store.path.write_text("\n".join(lines[:1] + ["not json"] + lines[1:]) + "\n")
    with pytest.raises(RunStoreError, match=r"outcomes.jsonl: line 2 is not a run outcome"):
        store.load()


def test_an_evaluation_resumes_from_its_run_store_without_the_run_folders(tmp_path):
    from perception.evaluate import OUTCOMES_FILE, evaluation_status

    torch.set_num_threads(1)
    _write_toy_clean_and_fire(tmp_path)
    config = dataclasses.replace(quick_config(), models=("touchformer", "lstm", "reference"),
                                 ablation_models=("touchformer_mag", "touchformer"), robustness_models=("lstm",),
                                 corruption_ratios=(0.0, 1.0), corruption_stds=(3.0,), fire_models=("lstm",),
                                 single_sensor_models=("lstm",))
    out = tmp_path / "report"

    def run(cfg=config, workers=2):
        results = evaluate(tmp_path / "clean", out, config=cfg, progress=False, workers=workers,
                           fire_dir=tmp_path / "fire")
        return {k: results[k] for k in ("table1", "missing_modality", "ablation", "probes", "robustness", "fire",
                                        "single_sensor", "modality_weights")}, results["provenance"]["outcomes"]

    def status():
        return evaluation_status(tmp_path / "clean", out, fire_dir=tmp_path / "fire", config=config)

    # what the evaluation needs, named as it names its runs: Table 1 4 splits x 2 networks, the ablation's
    # touchformer_mag on the 4, the fire shift's 3 runs, lstm on each sensor, lstm at p = 1 (p = 0 is Table 1's)
    runs = {"table1": 8, "ablation": 4, "fire": 3, "single_sensor": 4, "robustness": 1}
    # and the robustness curve's two runs (p = 0 and 1) scored on fire strokes
    before = status()
    assert {name: match["kept"] for name, match in before.pop("data").items()} == {"clean": False, "fire": False}
    interim = before.pop("interim")
    assert {(c["mean"], c["stored"]) for cells in interim["tasks"].values() for c in cells.values()} == {(None, 0)}
    assert sum(c["runs"] for cells in interim["tasks"].values() for c in cells.values()) == 8 + 4  # as above
    assert interim["robustness"][0]["seeds"] == []
    assert before == {"store": str(out / OUTCOMES_FILE), "stored": 0, "runs": 20,
                      "experiments": {name: {"stored": 0, "runs": n} for name, n in runs.items()},
                      "robustness_fire_scores": {"stored": 0, "scores": 2}}
    first, outcomes = run()
    assert {name: match["kept"] for name, match in status()["data"].items()} == {"clean": True, "fire": True}
    assert outcomes["read"] == outcomes["scored_here"] > 0 and outcomes["from_store"] == 0
    assert status()["experiments"] == {name: {"stored": n, "runs": n} for name, n in runs.items()}
    assert status()["robustness_fire_scores"] == {"stored": 2, "scores": 2}
    interim = status()["interim"]  # read from the store: the report's own figures
    for task in ("ssmc", "usmc", "fine"):
        for model, cell in interim["tasks"][task].items():
            mean = (first["table1"][task][model]["accuracy"] if model in config.models
                    else first["ablation"][model][task])["mean"]
            assert cell == {"mean": round(100 * mean, 1), "stored": cell["runs"], "runs": cell["runs"]}
    [level] = interim["robustness"]
    assert level["seeds"] == list(config.seeds)
    curve = first["robustness"]["levels"][0]["curves"]["lstm"]
    assert {p: cell["mean"] for p, cell in level["curves"]["lstm"].items()} == {p: round(100 * a, 1)
                                                                                for p, a in curve.items()}
    for name in ("clean", "fire"):  # the shards each stored run names, to compare a data set recorded again with
        [kept] = (out / "data_manifests").glob(f"{name}-*.json")
        assert json.loads(kept.read_text()) == json.loads((tmp_path / name / "manifest.json").read_text())
    n_lines = len((out / OUTCOMES_FILE).read_text().splitlines())
    assert n_lines == outcomes["read"]  # each run scored once, by the worker that trained it

    def strip(results):  # run folders are named in the results; they may be gone
        return json.loads(json.dumps(results, default=str).replace(str(out), "OUT"))

    shutil.rmtree(out / "runs")
    manifest = json.loads((tmp_path / "clean" / "manifest.json").read_text())
    manifest["recorder_sha256"] = "0" * 64  # the same strokes, recorded by code changed elsewhere
    (tmp_path / "clean" / "manifest.json").write_text(json.dumps(manifest))
    assert status()["data"]["clean"]["kept"]  # the strokes are the stored runs' strokes
    second, outcomes = run(workers=1)
    assert not (out / "runs").exists()  # nothing trained: every outcome came from the store
    assert len(list((out / "data_manifests").glob("clean-*.json"))) == 1  # same strokes, same name
    assert outcomes == {"file": OUTCOMES_FILE, "read": n_lines, "scored_here": 0, "from_store": n_lines}
    assert f"this report read {n_lines} runs, {n_lines} of them from the store" in (out / "REPORT.md").read_text()
    np.testing.assert_equal(strip(second), strip(first))
    assert (out / "tsne.png").stat().st_size > 0  # drawn from the stored embeddings

    # a fine-tuned run missing from the store trains again, and so does the clean run it starts from
    lines = (out / OUTCOMES_FILE).read_text().splitlines()
    (out / OUTCOMES_FILE).write_text("\n".join(l for l in lines if "finetuned_lstm" not in l) + "\n")
    third, outcomes = run()
    assert outcomes["scored_here"] == 1
    assert (out / "runs" / "fire" / "seed0" / "clean_lstm" / "checkpoint" / "model.safetensors").is_file()
    np.testing.assert_equal(strip(third), strip(first))

    # fire scores missing from the store are scored again, their runs trained again where the folders are gone
    shutil.rmtree(out / "runs")
    lines = (out / OUTCOMES_FILE).read_text().splitlines()
    (out / OUTCOMES_FILE).write_text("\n".join(l for l in lines if "zero-shot on fire" not in l) + "\n")
    assert len(lines) - len((out / OUTCOMES_FILE).read_text().splitlines()) == 2
    fourth, outcomes = run()
    assert outcomes["scored_here"] == 2
    np.testing.assert_equal(strip(fourth), strip(first))  # same weights: same fire scores, full agreement
    assert {a for level in fourth["robustness"]["fire_zero_shot"] for runs in
            level["stored_test_agreement"]["lstm"].values() for a in runs} == {1.0}

    # another setting is another run: nothing is reused
    fewer = dataclasses.replace(config, train=dataclasses.replace(config.train, epochs=1))
    _, outcomes = run(fewer)
    assert outcomes["from_store"] == 0


def test_a_robustness_run_is_scored_on_fire_strokes_by_the_worker_that_trains_it(tmp_path, monkeypatch):
    """Run folders do not outlive a session: an evaluation cut off once its workers are done keeps every
    robustness run's fire score in the store, and the next one, without the folders, trains nothing again."""
    import perception.evaluate as evaluation
    from perception.evaluate import evaluation_status

    torch.set_num_threads(1)
    _write_toy_clean_and_fire(tmp_path)
    config = dataclasses.replace(quick_config(), models=("lstm", "reference"), ablation=False, probes=False,
                                 robustness_models=("lstm",), corruption_ratios=(0.0, 1.0), corruption_stds=(3.0,),
                                 fire_models=("lstm",), single_sensor_models=(), tsne=False)
    out = tmp_path / "report"

    def run(workers):
        return evaluate(tmp_path / "clean", out, config=config, progress=False, workers=workers,
                        fire_dir=tmp_path / "fire")

    class SessionEnded(Exception):
        pass

    def session_ends(ctx, job):  # the evaluation's first step after the workers' training
        raise SessionEnded

    with monkeypatch.context() as patch:
        patch.setattr(evaluation, "_run", session_ends)
        with pytest.raises(SessionEnded):
            run(workers=2)
    status = evaluation_status(tmp_path / "clean", out, fire_dir=tmp_path / "fire", config=config)
    assert status["stored"] == status["runs"] > 0
    assert status["robustness_fire_scores"] == {"stored": 2, "scores": 2}  # p = 0 (Table 1's run) and p = 1

    shutil.rmtree(out / "runs")  # the next session's checkout
    results = run(workers=1)
    assert not (out / "runs").exists()  # nothing trained again
    assert results["provenance"]["outcomes"]["scored_here"] == 0
    [level] = results["robustness"]["fire_zero_shot"]
    assert {a for runs in level["stored_test_agreement"]["lstm"].values() for a in runs} == {1.0}


def test_interim_figures_count_only_seeds_stored_for_every_model_and_ratio():
    from perception.evaluate import _interim_accuracy, _TrainJob

    config = dataclasses.replace(quick_config(), seeds=(0, 1, 2), corruption_ratios=(0.0, 0.5, 1.0),
                                 corruption_stds=(1.0, 5.0),
                                 robustness_models=("touchformer", "lstm", "touchformer_soft"))
    split = (np.arange(3), np.arange(3, 5))
    rob = [_TrainJob(m, "ssmc", f"seed{s}", s, split, p, std if p > 0 else 1.0) for s in config.seeds
           for m in config.robustness_models for std in config.corruption_stds for p in config.corruption_ratios
           if p > 0 or std == 1.0]
    table = [job for job in rob if job.corruption == 0.0]

    def accuracy(job):  # TouchFormer above the LSTM at p > 0, below its own soft variant; seed 2 unfinished at std 5
        if job.seed == 2 and job.corruption_std == 5.0 and job.corruption > 0 and job.model == "touchformer":
            return None
        base = {"touchformer": 0.6, "lstm": 0.5, "touchformer_soft": 0.9}[job.model]
        return base - (0.2 if job.model == "touchformer" and job.corruption == 0.0 else 0.0) + 0.01 * job.seed

    interim = _interim_accuracy(config, table, rob, accuracy)
    assert interim["tasks"]["ssmc"]["lstm"] == {"mean": 51.0, "stored": 3, "runs": 3}
    low, high = interim["robustness"]
    assert low["seeds"] == [0, 1, 2] and high["seeds"] == [0, 1]
    # p = 0.5 and 1.0: above the only baseline (the LSTM); the soft variant is no baseline
    assert low["touchformer_above_the_baselines_at"] == high["touchformer_above_the_baselines_at"] == 2
    assert high["curves"]["touchformer"]["1.0"] == {"mean": 60.5, "stored": 2, "runs": 3}
    assert high["curves"]["touchformer"]["0.0"] == low["curves"]["touchformer"]["0.0"] == {
        "mean": 41.0, "stored": 3, "runs": 3}  # p = 0 is one run for every std


def test_status_tells_a_recording_made_with_other_numerics_from_one_made_by_other_code(tmp_path):
    from types import SimpleNamespace

    from perception.evaluate import _keep_manifest, kept_manifest_match

    numerics = {"machine": "x86_64", "cpu": "Intel Xeon", "packages": {"numpy": "2.4.6"},
                "blas": [{"api": "openblas", "version": "0.3.31", "architecture": "SkylakeX"}], "env": {}}
    manifest = {"recorder_sha256": "a" * 64, "config": {"seed": 1}, "numerics": numerics,
                "shards": [{"file": f"shards/shard-{i:05d}.npz", "sha256": str(i) * 64} for i in range(3)]}
    _keep_manifest(SimpleNamespace(manifest=manifest), tmp_path, "clean")  # what the stored runs trained on
    assert kept_manifest_match(SimpleNamespace(manifest=manifest), tmp_path, "clean")["kept"]

    elsewhere = json.loads(json.dumps(manifest))  # recorded again on a machine whose BLAS sums otherwise
    elsewhere["numerics"].update(cpu="AMD EPYC", blas=[{**numerics["blas"][0], "architecture": "Haswell"}])
    elsewhere["shards"][1]["sha256"] = "f" * 64
    match = kept_manifest_match(SimpleNamespace(manifest=elsewhere), tmp_path, "clean")
    [kept] = (tmp_path / "data_manifests").glob("clean-*.json")
    assert match == {"strokes": match["strokes"], "kept": False, "closest": kept.name,
                     "differing_shards": 1, "shards": 3, "same_code_and_options": True,
                     "numerics_changed": ["BLAS kernels openblas SkylakeX -> openblas Haswell"]}

    edited = json.loads(json.dumps(elsewhere))  # the same machine, other recorder code; an old manifest
    edited["recorder_sha256"] = "b" * 64
    del edited["numerics"]
    match = kept_manifest_match(SimpleNamespace(manifest=edited), tmp_path, "clean")
    assert (match["same_code_and_options"], match["numerics_changed"]) == (False, ["not recorded"])
    assert kept_manifest_match(SimpleNamespace(manifest=edited), tmp_path, "fire") == {
        "strokes": match["strokes"], "kept": False}  # nothing kept under that name to compare with


def test_category_recall_pools_the_runs_test_strokes():
    runs = [{"_names": ("metal", "wood"), "_y_true": np.array([0, 0, 1]), "_y_pred": np.array([0, 1, 1])},
            {"_names": ("metal", "wood"), "_y_true": np.array([0, 1]), "_y_pred": np.array([1, 0])}]
    assert _category_recall(runs) == {"metal": pytest.approx(1 / 3), "wood": pytest.approx(1 / 2)}
