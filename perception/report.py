"""The evaluation's report: the paper's figures, the names the report and its plots print, and ``REPORT.md``
written from the results :func:`perception.evaluate.evaluate` collects (also saved as ``results.json``).

Nothing here trains or scores; :func:`write_report` only formats a results mapping, so a report can be written
again from a saved ``results.json``.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any, Mapping

from perception.streams import MODALITIES, MODALITY_SYMBOL

PAPER: dict[str, Any] = {
    "table1": {  # accuracy %, G-mean; LMTHM, 4 modalities
        "ssmc": {"ddqn": (92.71, 0.93), "mmusr": (79.7, 0.80), "mmusr_vision": (93.8, 0.94),
                 "touchformer": (95.19, 0.95)},
        "usmc": {"lstm": (74.23, 0.73), "dalnet": (46.67, 0.47), "mtcnn": (87.55, 0.88),
                 "touchformer": (94.38, 0.94)},
        "fine": {"lstm": (65.75, 0.66), "dalnet": (42.62, 0.43), "mtcnn": (80.21, 0.80),
                 "touchformer": (89.77, 0.90)},
    },
    "missing_modality_usmc": {  # accuracy % with one modality removed
        "lstm": {"sound": 73.78, "normal": 71.69, "friction": 69.09, "accel": 75.50, "none": 74.23},
        "mtcnn": {"sound": 83.43, "normal": 83.18, "friction": 84.99, "accel": 87.00, "none": 87.55},
        "touchformer": {"sound": 87.92, "normal": 88.55, "friction": 89.12, "accel": 89.84, "none": 94.38},
    },
    "ablation": {  # accuracy %, SSMC / USMC / fine
        "touchformer_fusion": {"ssmc": 91.32, "usmc": 90.17, "fine": 83.53},
        "touchformer_mag": {"ssmc": 93.15, "usmc": 92.56, "fine": 84.88},
        "touchformer": {"ssmc": 95.19, "usmc": 94.38, "fine": 89.77},
    },
    "fishm": {  # TouchFormer on the robot data set, accuracy % without / with environment noise
        "without_noise": {"ssmc": 91.47, "usmc": 90.26, "fine": 90.05},
        "with_noise": {"ssmc": 89.54, "usmc": 88.03, "fine": 87.76},
    },
    "robustness": "figure only: TouchFormer's accuracy stays above the baselines' for p in 0.0 ... 1.0",
}
"""The paper's figures (from /work/shared/reference/paper-facts.md), printed beside ours in REPORT.md."""

MODEL_LABEL = {"touchformer": "TouchFormer", "touchformer_mag": "fusion + MAG (no CER)",
               "touchformer_fusion": "fusion only", "touchformer_soft": "TouchFormer, MAG without threshold",
               "lstm": "LSTM", "mtcnn": "MTCNN", "reference": "reference (logreg)"}
TASK_LABEL = {"ssmc": "SSMC", "usmc": "USMC", "fine": "fine-grained"}
PROBE_LABEL = {"intact": "as recorded", "time_shuffled": "frames shuffled", "time_reversed": "time reversed",
               "desync": "sensors shifted apart", "swap": "sensors from other strokes"}
"""The probes' alterations (:data:`perception.probes.ALTERATIONS`, and the unaltered strokes) as the report
names them."""


def numerics_line(numerics: Mapping[str, Any]) -> str:
    """:func:`perception.evaluate._numerics` in one line of the report's provenance."""
    blas = ", ".join(f"{b['api']} {b['version']} ({b['architecture']} kernels)" for b in numerics.get("blas", []))
    versions = ", ".join(f"{name} {v}" for name, v in (numerics.get("packages") or {}).items() if v is not None)
    env = "".join(f", {k}={v}" for k, v in (numerics.get("env") or {}).items())
    return (f"{numerics.get('cpu')} ({numerics.get('machine')}), BLAS {blas or 'none loaded'}, torch CPU code path "
            f"{numerics.get('torch_cpu_capability')}; {versions}{env}")


def _pct(stat: Mapping[str, float]) -> str:
    if stat["mean"] != stat["mean"]:
        return "-"
    return f"{100 * stat['mean']:.2f}" + (f" ± {100 * stat['std']:.2f}" if stat["std"] == stat["std"] else " (n=1)")


def _g(stat: Mapping[str, float]) -> str:
    if stat["mean"] != stat["mean"]:
        return "-"
    return f"{stat['mean']:.2f}" + (f" ± {stat['std']:.2f}" if stat["std"] == stat["std"] else " (n=1)")


def _paper(value: Any) -> str:
    """A figure from the paper as printed there (two decimals)."""
    return f"{value:.2f}" if isinstance(value, (int, float)) else str(value)


def _zero_shot_lines(rob: Mapping[str, Any]) -> list[str]:
    """The report's tables of the robustness runs scored zero-shot on fire strokes
    (:func:`perception.evaluate._robustness_on_fire`)."""
    levels = rob["fire_zero_shot"]
    n = sorted({k for level in levels for curve in level["n_test"].values() for runs in curve.values() for k in runs})
    lines = ["### The robustness runs on fire strokes (zero-shot accuracy [%])", "",
             "Every run above (trained on clean strokes only, with noise of ratio p) scored on the fire room's "
             f"test strokes of its seed's SSMC split ({' / '.join(map(str, n))} strokes), without test noise: "
             "does training on corrupted modalities make a clean-only model hold up in the fire room? Mean over "
             "the seeds; below each TouchFormer variant, its gate's mean weight on each modality for these "
             f"strokes ({', '.join(MODALITY_SYMBOL.get(m, m) for m in MODALITIES)}). Figure: "
             "`robustness_fire.png`.", ""]
    agreement = list({(model, p, float(p) > 0 and level["corruption_std"], k): a for level in levels  # p = 0: one run
                      for model, curve in level["stored_test_agreement"].items()
                      for p, runs in curve.items() for k, a in enumerate(runs)}.values())
    differ = sum(a < 1.0 for a in agreement)
    lines += [f"Each scored checkpoint predicts its run's own clean test strokes as the run store holds "
              + ("on every stroke" if not differ else
                 f"on {100 * min(agreement):.1f} % of the strokes or more ({differ} of {len(agreement)} checkpoints "
                 "differ: trained again, their folders gone, with other weights)")
              + f" ({len(agreement)} checkpoints).", ""]
    for level in levels:
        ps = sorted({p for curve in level["curves"].values() for p in curve}, key=float)
        lines += [f"| trained at noise std {level['corruption_std']:g} | " + " | ".join(f"p={p}" for p in ps) + " |",
                  "|---|" + "---|" * len(ps)]
        for model, curve in level["curves"].items():
            lines.append(f"| {MODEL_LABEL.get(model, model)} | " + " | ".join(
                f"{100 * curve[p]:.1f} ± {100 * level['curves_std'][model][p]:.1f}" if curve[p] == curve[p] else "-"
                for p in ps) + " |")
            for j, modality in enumerate(MODALITIES) if model in level["alpha_mean"] else ():
                symbol = MODALITY_SYMBOL.get(modality, modality)
                lines.append(f"| {MODEL_LABEL.get(model, model)}: gate weight {symbol} | " + " | ".join(
                    f"{level['alpha_mean'][model][p][j]:.2f}" for p in ps) + " |")
        lines.append("")
    return lines


def write_report(path: Path, results: Mapping[str, Any]) -> None:
    """Write ``REPORT.md`` to ``path`` from an evaluation's results (:func:`perception.evaluate.evaluate`'s
    return value, or the ``results.json`` it saved: both give the same text)."""
    prov, cfg = results["provenance"], results["config"]
    lines = ["# TouchFormer evaluation on our data", "",
             "Our numbers are mean ± sample std (ddof 1) over seeds (SSMC, fine-grained) or folds (USMC); the paper's are on the "
             "LMT haptic database (LMTHM) unless said otherwise, so they set the scale, not a target to match "
             "on a different data set.", "",
             "## Provenance", "",
             f"- command: `{prov['command']}`",
             f"- git commit when this report was written: `{prov['git_commit']}`"
             + (" (with uncommitted changes to tracked files)" if prov.get("git_dirty") else ""),
             *([f"- runs by the commit that trained them (a run is reused while its config, data and model config "
                f"are unchanged): " + ", ".join(f"`{c[:10]}` {n}" for c, n in prov["run_commits"].items())]
               if prov.get("run_commits") else []),
             *([f"- every network run's test predictions and training summary: `{prov['outcomes']['file']}` (the run "
                f"store; this report read {prov['outcomes']['read']} runs, {prov['outcomes']['from_store']} of them "
                f"from the store and {prov['outcomes']['scored_here']} trained or scored by this command)"]
               if prov.get("outcomes") else []),
             f"- data: `{prov['data_dir']}` (env {prov['data_env']}, {prov['n_strokes']} strokes, "
             f"{prov['n_categories']} categories, {prov['n_instances']} instances), manifest sha256 "
             f"`{prov['data_manifest_sha256']}`",
             *([f"- fire data: `{prov['fire_dir']}`, manifest sha256 `{prov['fire_manifest_sha256']}`"]
               if prov.get("fire_dir") else []),
             *([f"- numerics of this command (`perception/numerics.py`; a run is bit for bit the same only where they "
                f"agree): {numerics_line(prov['numerics'])}"] if prov.get("numerics") else []),
             f"- seeds {cfg['seeds']}, USMC {cfg['n_folds']} folds, {cfg['train']['epochs']} epochs, batch "
             f"{cfg['train']['batch_size']}, {cfg['train']['optimizer']} lr {cfg['train']['lr']} wd "
             f"{cfg['train']['weight_decay']} ({cfg['train']['schedule']}), device {prov['device']}, quick={prov['quick']}",
             f"- wall time of this command {results['seconds']:.0f} s (reused runs are not trained again)", ""]

    lines += ["## Table 1: material classification", "",
              "| task | model | accuracy [%] (ours) | G-mean (ours) | paper accuracy [%] | paper G-mean |",
              "|---|---|---|---|---|---|"]
    for task, per_model in results["table1"].items():
        for model, summ in per_model.items():
            paper = PAPER["table1"][task].get(model)
            lines.append(f"| {TASK_LABEL[task]} | {MODEL_LABEL.get(model, model)} | {_pct(summ['accuracy'])} | "
                         f"{_g(summ['g_mean'])} | {_paper(paper[0]) if paper else '-'} | {_paper(paper[1]) if paper else '-'} |")
        for model, paper in PAPER["table1"][task].items():
            if model not in per_model:
                lines.append(f"| {TASK_LABEL[task]} | {model} (paper only) | - | - | {_paper(paper[0])} | "
                             f"{_paper(paper[1])} |")
    lines.append("")
    if results.get("paired"):
        lines += ["### TouchFormer against each model on the same test strokes", "",
                  "Each seed's (fold's) test strokes are the same for every model, so the two can be compared stroke "
                  "by stroke (`perception/paired.py`): the difference of the accuracies (mean over the runs, as "
                  "above), its 95 % bootstrap interval over the test strokes (BCa, each run's strokes resampled on "
                  "their own), the strokes only one of the two classifies right (over all runs) and McNemar's exact "
                  "p on them. The interval holds the test split's sampling noise for these trained networks; how much "
                  "a model moves when trained again is the ± std above.", "",
                  "| task | against | TouchFormer - it [points] | 95 % interval | right for TouchFormer only / "
                  "for it only | McNemar p | test strokes (runs) |", "|---|---|---|---|---|---|---|"]
        for task, per_model in results["paired"].items():
            for model, c in per_model.items():
                low, high = c["ci95_points"]
                lines.append(f"| {TASK_LABEL[task]} | {MODEL_LABEL.get(model, model)} | "
                             f"{c['difference_points']:+.2f} | {low:+.2f} to {high:+.2f} | {c['model_only_right']} / "
                             f"{c['baseline_only_right']} | {c['mcnemar_p']:.3g} | {c['n_strokes']} "
                             f"({c['n_runs']}) |")
        lines.append("")

    if results.get("category_recall"):
        lines += ["### Recall per category (test strokes of all seeds or folds pooled, %)", ""]
        for task, per_model in results["category_recall"].items():
            models = list(per_model)
            categories = list(per_model[models[0]])
            lines += [f"| {TASK_LABEL[task]} | " + " | ".join(MODEL_LABEL.get(m, m) for m in models) + " |",
                      "|---|" + "---|" * len(models)]
            for c in categories:
                best = max(per_model[m][c] for m in models)
                lines.append(f"| {c} | " + " | ".join(
                    (f"**{100 * per_model[m][c]:.1f}**" if per_model[m][c] == best else f"{100 * per_model[m][c]:.1f}")
                    for m in models) + " |")
            lines.append("")
    if results.get("missing_modality"):
        lines += ["## Missing modality (USMC, modality removed at test time)", "",
                  "| model | " + " | ".join(f"no {MODALITY_SYMBOL[m]}" for m in MODALITIES) + " | all four |",
                  "|---|" + "---|" * (len(MODALITIES) + 1)]
        for model, row in results["missing_modality"].items():
            paper = PAPER["missing_modality_usmc"].get(model, {})
            cells = [f"{_pct(row[m])} (paper {_paper(paper[m])})" if m in paper else _pct(row[m]) for m in MODALITIES]
            cells.append(f"{_pct(row['none'])} (paper {_paper(paper['none'])})" if paper else _pct(row["none"]))
            lines.append(f"| {MODEL_LABEL.get(model, model)} | " + " | ".join(cells) + " |")
        lines.append("")

    if results.get("ablation"):
        lines += ["## Ablation (accuracy [%], ours (paper))", "", "| configuration | SSMC | USMC | fine-grained |",
                  "|---|---|---|---|"]
        for model, row in results["ablation"].items():
            lines.append(f"| {MODEL_LABEL.get(model, model)} | " + " | ".join(
                f"{_pct(row[t])} ({_paper(PAPER['ablation'].get(model, {}).get(t, 'not in the paper'))})"
                for t in ("ssmc", "usmc", "fine")) + " |")
        lines.append("")
        if results.get("ablation_paired"):
            lines += ["Each step against the one before it on the same test strokes (as Table 1's paired "
                      "comparison):", "",
                      "| step | task | difference [points] | 95 % interval | right for the step only / before it only "
                      "| McNemar p |", "|---|---|---|---|---|---|"]
            for c in results["ablation_paired"]:
                low, high = c["ci95_points"]
                lines.append(f"| {MODEL_LABEL.get(c['baseline'], c['baseline'])} -> "
                             f"{MODEL_LABEL.get(c['model'], c['model'])} | {TASK_LABEL[c['task']]} | "
                             f"{c['difference_points']:+.2f} | {low:+.2f} to {high:+.2f} | {c['model_only_right']} / "
                             f"{c['baseline_only_right']} | {c['mcnemar_p']:.3g} |")
            lines.append("")
        if "touchformer_soft" in results["ablation"]:
            lines += [f"'{MODEL_LABEL['touchformer_soft']}' is our variant, not the paper's: TouchFormer with "
                      "gate_th = 0, so the gates only weight the modalities and never drop one, and eq. 3's softmax "
                      "temperature 1 (TouchFormer's is 0.2, see Deviations). It is here because it beat TouchFormer "
                      "on validation at temperature 1; Table 1 lists both.", ""]

    else:
        lines += ["## Ablation", "", "Not run in this report (`--no-ablation`).", ""]

    if results.get("modality_weights"):
        lines += ["## Which sensors the models trusted (mean weight alpha on the test strokes; share dropped by "
                  "the gate)", "",
                  "alpha_m weights each modality's features (the four sum to 1); the gate drops a modality whose "
                  "gate value falls below gate_th. 'fusion only' has uniform weights by construction.", "",
                  "| task | model | " + " | ".join(f"alpha {MODALITY_SYMBOL[m]}" for m in MODALITIES) + " | "
                  + " | ".join(f"dropped {MODALITY_SYMBOL[m]} [%]" for m in MODALITIES) + " |",
                  "|---|---|" + "---|" * (2 * len(MODALITIES))]
        for task, per_model in results["modality_weights"].items():
            for model, row in per_model.items():
                lines.append(f"| {TASK_LABEL[task]} | {MODEL_LABEL.get(model, model)} | "
                             + " | ".join(f"{a:.3f}" for a in row["alpha_mean"]) + " | "
                             + " | ".join(f"{100 * d:.1f}" for d in row["gate_dropped_share"]) + " |")
        lines.append("")

    if results.get("robustness"):
        rob = results["robustness"]
        lines += ["## Robustness to corrupted modalities (SSMC accuracy [%])", "",
                  "Each modality of each sample gets N(0, std²) noise (std in units of the per-channel training "
                  "feature std) with probability p, in training and testing, at each noise intensity "
                  f"(std {', '.join(f'{s:g}' for s in rob['corruption_stds'])}). Mean over the seeds "
                  f"({', '.join(map(str, rob['seeds']))}; each its own SSMC split), ± std in the second table of "
                  "each intensity; p = 0 is Table 1's runs. Figure: `robustness.png` (band: ± one std).", ""]
        for level in rob["levels"]:
            ps = sorted({p for curve in level["curves"].values() for p in curve}, key=float)
            for title, table in ((f"noise std {level['corruption_std']:g}", level["curves"]),
                                 ("std over the seeds", level["curves_std"])):
                lines += [f"| {title} | " + " | ".join(f"p={p}" for p in ps) + " |", "|---|" + "---|" * len(ps)]
                for model, curve in table.items():
                    lines.append(f"| {MODEL_LABEL.get(model, model)} | " + " | ".join(
                        f"{100 * curve[p]:.1f}" if p in curve and curve[p] == curve[p] else "-" for p in ps) + " |")
                if table is level["curves"] and level.get("seed_wins"):
                    n = len(rob["seeds"])
                    lines.append(f"| seeds where TouchFormer is above every other model (of {n}) | " + " | ".join(
                        str(level["seed_wins"].get(p, "-")) for p in ps) + " |")
                paired = level.get("paired_best_baseline") if table is level["curves"] else None
                if paired:
                    lines.append("| best baseline at this p | " + " | ".join(
                        MODEL_LABEL.get(paired[p]["baseline"], paired[p]["baseline"]) if p in paired else "-"
                        for p in ps) + " |")
                    lines.append("| TouchFormer - it [points] (95 % interval over the test strokes) | " + " | ".join(
                        f"{paired[p]['difference_points']:+.1f} ({paired[p]['ci95_points'][0]:+.1f}, "
                        f"{paired[p]['ci95_points'][1]:+.1f})" if p in paired else "-" for p in ps) + " |")
                lines.append("")
        if any(level.get("paired_best_baseline") for level in rob["levels"]):
            lines += ["The last two rows of each intensity's first table compare TouchFormer with the baseline that "
                      "has the higher mean at that p, stroke by stroke on the same test strokes (as in Table 1's "
                      "paired comparison): an interval that holds 0 is a difference the test split's draw could "
                      "make.", ""]
        lines += [f"Paper: {PAPER['robustness']}.", ""]
        if rob.get("fire_zero_shot"):
            lines += _zero_shot_lines(rob)
    else:
        lines += ["## Robustness to corrupted modalities", "", "Not run in this report (`--no-robustness`).", ""]

    if results.get("single_sensor"):
        single = results["single_sensor"]
        models = list(single)
        lines += ["## One sensor at a time (SSMC accuracy [%], test; best validation in brackets)", "",
                  "Each network trained and tested on one sensor, the other three treated as missing (our "
                  "diagnostic, not in the paper); 'all four' are the same network's Table-1 runs.", "",
                  "| sensor | " + " | ".join(MODEL_LABEL.get(m, m) for m in models) + " |",
                  "|---|" + "---|" * len(models)]
        for sensor in (*MODALITIES, "all"):
            label = "all four" if sensor == "all" else f"{sensor} ({MODALITY_SYMBOL[sensor]})"
            lines.append(f"| {label} | " + " | ".join(
                f"{_pct(single[m][sensor]['accuracy'])} ({100 * single[m][sensor]['best_val_accuracy']['mean']:.1f})"
                if sensor in single[m] else "-" for m in models) + " |")
        lines.append("")
    else:
        lines += ["## One sensor at a time", "", "Not run in this report (`--no-single-sensor`).", ""]

    if results.get("probes"):
        kinds = list(PROBE_LABEL)
        lines += ["## What the networks use (test accuracy [%] on altered test strokes)", "",
                  "Each Table-1 run tested again on its own test strokes altered at inference, one kind of structure "
                  "removed at a time (our diagnostic, not in the paper; nothing trained or selected; every model of "
                  "a split sees the same altered strokes): each stream's frames shuffled in time, or reversed; each "
                  "stream circularly shifted by its own random number of frames, so that what happens in one sensor "
                  "no longer lines up with the others; each stream taken from another test stroke of the same "
                  "class, so that the four sensors no longer come from one stroke (`perception/probes.py`). The "
                  "reference classifier reads stream statistics, which do not depend on the order of frames, so it "
                  "is tested on the last only. Mean ± std over seeds or folds.", ""]
        for task, per_model in results["probes"].items():
            lines += [f"**{TASK_LABEL[task]}**", "", "| model | " + " | ".join(PROBE_LABEL[k] for k in kinds) + " |",
                      "|---|" + "---|" * len(kinds)]
            for model, per_kind in per_model.items():
                lines.append(f"| {MODEL_LABEL.get(model, model)} | " + " | ".join(
                    _pct(per_kind[k]) if k in per_kind else "-" for k in kinds) + " |")
            lines.append("")

    if results.get("fire"):
        fire = results["fire"]
        lines += ["## Clean -> fire shift (category accuracy on the fire test part)", "",
                  f"Mean ± std over the seeds ({fire['split']}; each seed splits the fire strokes and trains every "
                  "network again, the clean ones included); the accuracy of each seed in its own column. The "
                  "clean-only models train on the seed's clean SSMC training part, which holds no clean twin "
                  "of a fire test stroke (the same object and stroke draw recorded in the clean room).", "",
                  "| model | accuracy [%] | per seed [%] | G-mean | combustible accuracy [%] |",
                  "|---|---|---|---|---|"]
        for row in fire["rows"]:
            per_seed = " ".join(f"{100 * r['accuracy']:.1f}" for r in row["runs"])
            lines.append(f"| {row['label']} | {_pct(row['accuracy'])} | {per_seed} | {_g(row['g_mean'])} | "
                         f"{_pct(row['combustible_accuracy'])} |")
        lines += ["", f"Paper (FISHM robot data, TouchFormer, SSMC): {PAPER['fishm']['without_noise']['ssmc']} % without, "
                      f"{PAPER['fishm']['with_noise']['ssmc']} % with environment noise.", ""]
    else:
        lines += ["## Clean -> fire shift", "", "Not run in this report (no `--fire` data set given).", ""]

    if results.get("fitting"):
        lines += ["## How far the models fit (mean over runs)", "",
                  "Training accuracy at the last epoch against the best validation accuracy (which chose the epoch) "
                  "and the test accuracy, for the Table-1 networks and the ablation variants. Figure: "
                  "`training_curves.png`.", "",
                  "| task | model | chosen epoch | training acc. [%] | validation acc. [%] | test acc. [%] |",
                  "|---|---|---|---|---|---|"]
        for task, per_model in results["fitting"].items():
            for model, row in per_model.items():
                lines.append(f"| {TASK_LABEL[task]} | {MODEL_LABEL.get(model, model)} | "
                             f"{row['best_epoch']['mean']:.1f} | {_pct(row['final_train_accuracy'])} | "
                             f"{_pct(row['best_val_accuracy'])} | {_pct(row['test_accuracy'])} |")
        lines.append("")

    if "failed_runs" in results:
        lines += ["## Runs that never learned", "",
                  "Network runs whose training accuracy stayed under twice chance (2 / K) in every epoch; each "
                  "counts in the means above as it scored.", ""]
        if results["failed_runs"]:
            lines += ["| model | task | split | p | noise std | max training acc. [%] | test acc. [%] | run |",
                      "|---|---|---|---|---|---|---|---|"]
            for r in results["failed_runs"]:
                noise = f"{r['corruption_std']:g}" if r["corruption_std"] else "-"  # 0 without corruption
                lines.append(f"| {MODEL_LABEL.get(r['model'], r['model'])} | {TASK_LABEL.get(r['task'], r['task'])} | "
                             f"{r['split']} | {r['corruption_ratio']:g} | {noise} | "
                             f"{100 * r['max_train_accuracy']:.1f} | {100 * r['accuracy']:.1f} | `{r['checkpoint']}` |")
        else:
            lines.append("None: every network run's training accuracy reached twice chance.")
        lines.append("")

    lines += ["## Deviations from the paper", ""]
    lines += [f"- **{k}**: {v}" for k, v in results["deviations"].items()]
    lines += ["", "## Figures", ""] + [f"- `{f}`" for f in results["figures"]] + [""]
    path.write_text("\n".join(lines), encoding="utf-8")
