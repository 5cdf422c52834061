"""The ``deltar train`` command: config printing, override and resume checks, errors."""

from __future__ import annotations

import pytest
from typer.testing import CliRunner

from deltar.cli.main import app
from tests.training.conftest import TINY_CONFIG


def _cli(*args):
    return CliRunner().invoke(app, ["train", *args])


def test_cli_prints_the_resolved_config():
    result = _cli("--config", str(TINY_CONFIG), "-o", "optim.lr=5e-4", "--print-config")
    assert result.exit_code == 0, result.output
    assert "lr: 0.0005" in result.output


def test_cli_rejects_unknown_override_keys():
    result = _cli("--config", str(TINY_CONFIG), "-o", "optim.learning_rate=1")
    assert result.exit_code == 2
    assert "optim.learning_rate" in result.output


def test_cli_resume_takes_no_other_config(tmp_path):
    result = _cli("--resume", str(tmp_path), "--config", str(TINY_CONFIG))
    assert result.exit_code == 2
    assert "--resume" in result.output
    afile = tmp_path / "afile"
    afile.write_text("notes", encoding="utf-8")
    result = _cli("--config", str(TINY_CONFIG), "--run-dir", str(afile))
    assert result.exit_code == 2 and "--run-dir" in result.output and "is a file" in \
        result.output and afile.read_text(encoding="utf-8") == "notes"

    # A file on the way to the run folder: named before the network and data are built.
    for named, option in (("--run-dir", ["--run-dir", str(afile / "run")]),
                          ("output_dir", ["-o", f"output_dir={afile}"])):
        result = _cli("--config", str(TINY_CONFIG), *option)
        assert result.exit_code == 2, result.output
        assert "is a file, not a folder" in result.output, result.output
        assert f"{named} {afile}" in " ".join(result.output.split()), result.output
    assert afile.read_text(encoding="utf-8") == "notes"


def test_cli_reports_missing_data_without_a_traceback(tmp_path):
    missing = tmp_path / "no_such_folder"
    result = _cli("--config", str(TINY_CONFIG), "--run-dir", str(tmp_path / "run"),
                  "-o", "data.sources.0.kind=rgbd", "-o", f"data.sources.0.path={missing}")
    assert result.exit_code == 1
    assert str(missing) in result.output and "data.sources.0.path" in result.output
    assert not (tmp_path / "run" / "config.yaml").exists()
    # A relative path says where it was looked for.
    result = _cli("--config", str(TINY_CONFIG), "--run-dir", str(tmp_path / "run"),
                  "-o", "data.sources.0.kind=rgbd", "-o", "data.sources.0.path=no/such")
    assert result.exit_code == 1 and "read from the working folder" in result.output
    # A frame size the network cannot take is refused with the config, not mid-run.
    result = _cli("--config", str(TINY_CONFIG), "--run-dir", str(tmp_path / "run"),
                  "-o", "data.sources.0.resize=[120,150]")
    assert result.exit_code == 2 and "data.sources.0.resize must be multiples of 32" in \
        " ".join(result.output.split())


def test_a_run_folder_inside_a_data_source_is_refused_before_any_work(tmp_path):
    import numpy as np

    from deltar.data.zju_l5 import write_zju_l5
    from tests.data.test_zju_l5 import _sample

    write_zju_l5(tmp_path / "set", [_sample(np.random.default_rng(0), "a")])
    for run_dir in (tmp_path / "set", tmp_path / "set" / "run"):
        result = _cli("--config", str(TINY_CONFIG), "--run-dir", str(run_dir),
                      "-o", "data.sources.0.kind=zju_l5", "-o", "data.sources.0.resize=null",
                      "-o", f"data.sources.0.path={tmp_path / 'set' / 'data.json'}")
        assert result.exit_code == 1, result.output
        assert f"run_dir {run_dir} is " in " ".join(result.output.split())
    assert sorted(p.name for p in (tmp_path / "set").iterdir()) == ["a.h5", "data.json"]


def test_a_bad_validation_frame_fails_before_any_training(tmp_path):
    """A validation frame that cannot be read is found before the first step (and before
    config.yaml makes the folder a run's): not after an epoch of training."""
    import yaml

    for name in ("train", "val"):
        done = CliRunner().invoke(app, ["simulate", "procedural:4:0:64x96",
                                        str(tmp_path / name)])
        assert done.exit_code == 0, done.output
    missing = next((tmp_path / "val").rglob("*.h5"))
    missing.unlink()
    config = yaml.safe_load(TINY_CONFIG.read_text())
    config["data"].update(training_grid=8, sources=[
        {"kind": "zju_l5", "path": str(tmp_path / name / "data.json"), "split": "test",
         "role": name} for name in ("train", "val")])
    (tmp_path / "config.yaml").write_text(yaml.safe_dump(config))
    result = _cli("--config", str(tmp_path / "config.yaml"), "--run-dir",
                  str(tmp_path / "run"))
    assert result.exit_code == 1, result.output
    assert str(missing) in " ".join(result.output.split())
    assert not (tmp_path / "run" / "config.yaml").exists()
    assert not (tmp_path / "run" / "checkpoints").exists()


def test_fit_uncertainty_names_each_outlier_choice_in_words():
    """The fit's report tells "every zone kept", a rule and a detector apart."""
    import numpy as np

    from deltar.cli.train import _rule_text
    from deltar.sensor.zone_outlier_detector import ZONE_FEATURE_NAMES, OutlierDetector
    from deltar.sensor.zone_outliers import OutlierRule

    size = len(ZONE_FEATURE_NAMES)
    detector = OutlierDetector(np.zeros(size), np.ones(size),
                               ((np.zeros((size, 1)), np.zeros(1)),), threshold=0.85)
    assert _rule_text(None) == "every zone kept"
    assert _rule_text(OutlierRule(0.05, min_zones=3), short=True) == "0.05 / 3"
    assert "frames with >= 3 such zones" in _rule_text(OutlierRule(0.05, min_zones=3))
    assert _rule_text(detector, short=True) == "detector > 0.85"
    assert "learned detector gives > 0.85" in _rule_text(detector)


def test_cli_ends_a_run_stopped_by_a_signal_with_its_status(tmp_path, monkeypatch):
    """A requeue script reads the status: a run stopped by SIGTERM exits 143 (128 + 15)
    with the error line naming the resume, not 0 as a finished run."""
    import deltar.training.run as run_module

    def stopped(config, run_dir, resume=False):
        raise run_module.TrainingInterrupted(tmp_path / "run", "SIGTERM", 3)

    monkeypatch.setattr(run_module, "train", stopped)
    result = _cli("--config", str(TINY_CONFIG), "--run-dir", str(tmp_path / "run"))
    assert result.exit_code == 143
    assert "stopped by SIGTERM at step 3" in result.output
    assert "it stopped before its first checkpoint" in result.output


def test_fit_uncertainty_names_a_set_whose_split_is_empty(tmp_path):
    """Given alone it would fail naming nothing; beside a good set it was left out."""
    import json

    done = CliRunner().invoke(app, ["simulate", "procedural:2:0:64x96", str(tmp_path / "good")])
    assert done.exit_code == 0, done.output
    (tmp_path / "empty").mkdir()
    (tmp_path / "empty" / "data.json").write_text(json.dumps({"test": []}))
    result = CliRunner().invoke(app, [
        "fit-uncertainty", "default", "--data", str(tmp_path / "good"), "--data",
        str(tmp_path / "empty"), "--out", str(tmp_path / "fitted.pt")])
    assert result.exit_code == 2, result.output
    assert f"{tmp_path / 'empty' / 'data.json'}: split 'test' lists no frames" in \
        " ".join(result.output.split())
    assert not (tmp_path / "fitted.pt").exists()


def test_several_nodes_without_a_launcher_are_refused_instead_of_waiting(monkeypatch):
    for name in ("WORLD_SIZE", "MASTER_ADDR", "SLURM_NTASKS", "TORCHELASTIC_RUN_ID",
                 "LSB_JOBID", "OMPI_COMM_WORLD_SIZE", "PMI_SIZE"):
        monkeypatch.delenv(name, raising=False)
    result = _cli("--config", str(TINY_CONFIG), "-o", "trainer.num_nodes=2",
                  "-o", "trainer.strategy=ddp")
    assert result.exit_code == 2
    assert "trainer.num_nodes is 2: start each node with a launcher" in \
        " ".join(result.output.split())


def test_the_run_folder_check_probes_a_new_run_only(tmp_path, monkeypatch):
    # A finished run resumed from a read-only folder writes nothing: it is not refused;
    # a new run there is, with the reason the system gives.
    import errno

    import typer

    import deltar.io.atomic as atomic
    from deltar.cli.train import _check_run_folder

    def read_only(folder):
        raise OSError(errno.EROFS, "Read-only file system")

    monkeypatch.setattr(atomic, "prove_writable", read_only)
    run = tmp_path / "run"
    run.mkdir()
    _check_run_folder(run, True, "runs", None)
    with pytest.raises(typer.BadParameter, match=r"--run-dir .*run: cannot write in .*run "
                                                 r"\(read-only file system\)"):
        _check_run_folder(run, False, "runs", None)
