"""`cnnps run-stage` executor flags."""

import importlib.util

import pytest

from cnnps.pipeline import cli_stages
from cnnps.pipeline.cli import main


def test_executor_flags_override_params(repo_root, monkeypatch):
    monkeypatch.chdir(repo_root)
    conf = cli_stages._config(None, None, None, None, None)
    assert conf.executor.kind == "local"
    if importlib.util.find_spec("ray") is None:
        pytest.skip("ray not installed")
    conf = cli_stages._config(None, None, None, "ray", "ray://head:10001")
    assert (conf.executor.kind, conf.executor.address) == ("ray", "ray://head:10001")
    assert conf.executor.workers == 0  # the rest of the params file's executor section is kept


@pytest.mark.parametrize(
    "args, message",
    [
        (["run-stage", "meshes", "--address", "auto"], "--address applies to --executor ray"),
        (["run-stage", "meshes", "--executor", "slurm"], "executor.kind must be 'local' or 'ray'"),
    ],
)
def test_bad_executor_flags_are_one_line_errors(repo_root, monkeypatch, capsys, args, message):
    monkeypatch.chdir(repo_root)
    with pytest.raises(SystemExit) as exc:
        main(args)
    assert exc.value.code == 2
    err = capsys.readouterr().err.strip()
    assert message in err and len(err.splitlines()) == 1
