"""`dmais` as a process of its own (a workflow job): it imports its command's modules with the garbage
collector paused and ends without tearing its modules down (cli._end), yet prints everything and
exits with the command's status; `cli.main(argv)` called in a Python leaves its collector as it was."""

from __future__ import annotations

import gc
import json
import subprocess
import sys

import pytest

from dmais_pipe import cli

from test_dataset import _inputs, _write


def _dmais(*args: str) -> subprocess.CompletedProcess:
    """`dmais ARGS...` run as the console script runs it, its output through pipes."""
    return subprocess.run([sys.executable, "-m", "dmais_pipe.cli", *args], capture_output=True, text=True,
                          timeout=300)


def test_its_output_is_all_there_and_its_status_the_commands(tmp_path):
    root = _write(tmp_path / "ds", _inputs())
    done = _dmais("plan", str(root), "--per-job", "1")
    assert done.returncode == 0, done.stderr
    assert json.loads(done.stdout)["cameras"] == ["C0", "C1"]  # the whole JSON, flushed before the end
    done = _dmais("validate", str(root), "--skip-images")
    assert done.returncode == 0 and done.stdout.startswith("dataset tiny") and "observations: 3" in done.stdout


def test_a_user_error_is_one_line_and_status_2(tmp_path):
    done = _dmais("validate", str(tmp_path / "missing"))
    assert done.returncode == 2 and done.stdout == ""
    assert done.stderr.strip().splitlines() == [f"dmais validate: error: {tmp_path / 'missing'}: is not a dataset "
                                                "directory"]
    done = _dmais("plan", str(tmp_path), "--slices", "pose")
    assert done.returncode == 2 and len(done.stderr.strip().splitlines()) == 1


def test_the_version_is_printed_only_when_asked():
    done = _dmais("--version")
    assert done.returncode == 0 and done.stdout.startswith("dmais ")


@pytest.mark.parametrize("enabled", [True, False])
def test_main_called_in_a_python_leaves_its_collector_as_it_was(tmp_path, capsys, enabled):
    root = _write(tmp_path / "ds", _inputs())
    frozen = gc.get_freeze_count()
    (gc.enable if enabled else gc.disable)()
    try:
        assert cli.main(["validate", str(root), "--skip-images"]) == 0
        assert gc.isenabled() == enabled and gc.get_freeze_count() == frozen
    finally:
        gc.enable()
    assert "dataset tiny" in capsys.readouterr().out


def test_importing_cli_loads_none_of_the_libraries():
    """So that a job's heavy imports all come after main paused the collector."""
    code = "import sys\nfrom dmais_pipe import cli\nprint(sorted({'numpy', 'pandas', 'yaml'} & set(sys.modules)))"
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300, check=True)
    assert done.stdout.strip() == "[]"


def test_every_commands_modules_exist():
    commands = cli._parser()._subparsers._group_actions[0].choices
    for command, names in cli._MODULES.items():
        assert command in commands
        for name in names:
            assert (cli.Path(cli.__file__).parent / f"{name.replace('.', '/')}.py").is_file(), name


def test_an_error_importing_the_commands_modules_is_one_line_and_status_2(monkeypatch, capsys):
    def imported(command):
        raise cli.DmaisError("the pose solver's compiled cores were built for a CPU with avx512f")

    monkeypatch.setattr(cli, "_imported", imported)
    assert cli.main(["pose", "somewhere", "--out", "elsewhere"]) == 2
    err = capsys.readouterr().err
    assert err == "dmais pose: error: the pose solver's compiled cores were built for a CPU with avx512f\n"
