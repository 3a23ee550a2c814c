"""The command line's answers to bad input: one line naming the problem, exit code 2, nothing written over,
and no work done before a bad output path is found."""

from __future__ import annotations

import time

import pytest

from perception.dataset import write_dataset
from robotdemo.cli import main
from tests.test_dataset import make_material_strokes


@pytest.fixture(scope="module")
def tiny_data(tmp_path_factory):
    root = tmp_path_factory.mktemp("cli") / "ds"
    recs = make_material_strokes(3, n_categories=3, n_instances=2, n_objects=2, n_strokes=2, duration_s=0.2)
    write_dataset(root, recs, env="clean", seed=3)
    return root


def _one_line_error(capsys, code: int, message: str) -> str:
    err = capsys.readouterr().err
    assert code == 2, err
    assert message in err and len(err.strip().splitlines()) == 1, err
    assert "Traceback" not in err
    return err


@pytest.mark.parametrize("options, message", [
    (["--dropout", "nan"], "model option dropout must be finite"),
    (["--feature-noise", "nan"], "feature_noise_std must be a number >= 0"),
    (["--lr", "-1"], "lr must be a positive number"),
    (["--epochs", "0"], "epochs and batch_size must be >= 1, got 0"),
    (["--model-option", "d_model=-4"], "d_model must be a whole number >= 1, got -4"),
    (["--model-option", "d_model='x'"], "d_model must be a whole number >= 1, got 'x'"),
    (["--model-option", "n_classes=3"], "model option n_classes comes from the data"),
    (["--model", "mtcnn", "--model-option", "channels='x'"], "mtcnn: model options {'channels': 'x'} do not make"),
])
def test_train_rejects_bad_settings_in_one_line(tiny_data, tmp_path, capsys, options, message):
    code = main(["train", "--data", str(tiny_data), "--out", str(tmp_path / "run"), "--quiet", *options])
    _one_line_error(capsys, code, message)
    assert not (tmp_path / "run").exists()


def test_train_refuses_an_output_that_is_a_file_before_training(tiny_data, tmp_path, capsys):
    target = tmp_path / "notadir"
    target.write_text("keep me")
    start = time.perf_counter()
    code = main(["train", "--data", str(tiny_data), "--out", str(target), "--epochs", "50", "--quiet"])
    _one_line_error(capsys, code, "exists and is not a folder")
    assert time.perf_counter() - start < 5.0  # refused before 50 epochs of training
    assert target.read_text() == "keep me"


def test_a_run_folder_of_another_config_and_a_malformed_resume_state(tiny_data, tmp_path, capsys):
    run = tmp_path / "run"
    args = ["train", "--data", str(tiny_data), "--out", str(run), "--model", "mtcnn", "--epochs", "1",
            "--model-option", "channels=8", "--quiet"]
    assert main(args) == 0
    capsys.readouterr()
    _one_line_error(capsys, main([*args, "--lr", "0.001"]), "holds a run with another config")
    state = run / "resume" / "state.json"
    state.write_text("{}")
    _one_line_error(capsys, main(args), "malformed resume state")
    assert state.read_text() == "{}"  # left for the user to look at


@pytest.mark.parametrize("command", ["evaluate", "dataset"])
def test_evaluate_and_dataset_refuse_an_output_that_is_a_file(tiny_data, tmp_path, capsys, command):
    target = tmp_path / "notadir"
    target.write_text("keep me")
    args = ["evaluate", "--data", str(tiny_data), "--quick"] if command == "evaluate" else ["dataset"]
    _one_line_error(capsys, main([*args, "--out", str(target), "--quiet"]), "exists and is not a folder")
    assert target.read_text() == "keep me"


@pytest.mark.parametrize("option", ["--report", "--record"])
def test_demo_refuses_a_folder_as_its_output_file_before_simulating(tmp_path, capsys, option):
    start = time.perf_counter()
    code = main(["demo", "--objects", "1", option, str(tmp_path)])
    _one_line_error(capsys, code, "is a folder; give a file name")
    assert time.perf_counter() - start < 5.0


def test_dataset_refuses_a_malformed_manifest_in_its_folder(tmp_path, capsys):
    (tmp_path / "manifest.json").write_text("[1, 2]")
    code = main(["dataset", "--out", str(tmp_path), "--categories", "metal", "--quiet"])
    _one_line_error(capsys, code, "not a data set manifest")
    assert (tmp_path / "manifest.json").read_text() == "[1, 2]"


def test_plot_strokes_names_the_file_it_wrote(tiny_data, tmp_path, capsys):
    assert main(["plot-strokes", str(tiny_data), "--out", str(tmp_path / "noext")]) == 0
    assert capsys.readouterr().out.strip() == str(tmp_path / "noext.png")
    assert (tmp_path / "noext.png").is_file() and not (tmp_path / "noext").exists()
    (tmp_path / "adir").mkdir()
    (tmp_path / "adir.png").mkdir()
    _one_line_error(capsys, main(["plot-strokes", str(tiny_data), "--out", str(tmp_path / "adir.png")]),
                    "is a folder")


def test_bench_inference_names_an_unknown_checkpoint(tmp_path, capsys):
    code = main(["bench", "inference", "--checkpoint", str(tmp_path / "missing"), "--n", "1"])
    _one_line_error(capsys, code, "is neither a checkpoint folder nor a model name")


@pytest.mark.parametrize("argv", [
    ["bench", "ik", "--n", "-1"], ["bench", "trajectory", "--n", "0"], ["bench", "inference", "--n", "x"],
    ["scene", "--seconds", "inf"], ["scene", "--seconds", "nan"], ["scene", "--seed", "-1"],
    ["evaluate", "--data", "d", "--seeds"], ["demo", "--objects", "-2"], ["dataset", "--out", "o", "--workers", "0"],
])
def test_bad_numbers_are_refused_by_the_parser_naming_the_option(argv, capsys):
    with pytest.raises(SystemExit) as info:
        main(argv)
    err = capsys.readouterr().err
    assert info.value.code == 2 and "error: argument" in err.strip().splitlines()[-1]


def test_output_path_checks_accept_new_paths(tmp_path):
    """The checks refuse only what cannot be written: a report file in a new folder is fine."""
    from robotdemo.cli import _output_file, _output_folder

    _output_folder(str(tmp_path / "new" / "run"), "--out")
    _output_file(str(tmp_path / "new" / "report.json"), "--report")
    (tmp_path / "file").write_text("x")
    with pytest.raises(Exception, match="is not a folder"):
        _output_file(str(tmp_path / "file" / "report.json"), "--report")
