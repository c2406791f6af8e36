"""The check that the compiled cores run on this CPU (pose/build_cpu.py), and its one-line CLI error."""

import pytest

from dmais_pipe import cli
from dmais_pipe.errors import DmaisError
from dmais_pipe.pose import build_cpu

HERE = "processor\t: 0\nflags\t\t: fpu sse2 ssse3 sse4_2 avx avx2 fma hypervisor\n\nprocessor\t: 1\nflags\t\t: fpu\n"


def test_flags_of_the_first_processor():
    assert build_cpu.cpu_flags(HERE) == {"fpu", "sse2", "ssse3", "sse4_2", "avx", "avx2", "fma", "hypervisor"}
    assert build_cpu.cpu_flags("processor\t: 0\n") == set()


def test_only_missing_instruction_sets_count():
    here = build_cpu.cpu_flags(HERE)
    # a flag of the build machine that is not an instruction set (a VM's, a bug's) does not matter
    assert build_cpu.missing_instruction_sets(here | {"rep_good", "bug_spectre"}, here) == []
    assert build_cpu.missing_instruction_sets(here | {"avx512f", "avx512bw"}, here) == ["avx512bw", "avx512f"]


def test_cores_built_for_a_newer_cpu_is_one_clear_error(tmp_path):
    record, cpuinfo = tmp_path / "_build_cpu.txt", tmp_path / "cpuinfo"
    cpuinfo.write_text(HERE)
    record.write_text("flags\t\t: fpu sse2 avx avx2 avx512f\n")
    with pytest.raises(DmaisError, match=r"built for a CPU with avx512f, which this machine's CPU lacks.*"
                                          r"DMAIS_PORTABLE_BUILD=1 make install"):
        build_cpu.check_cpu(record, cpuinfo)
    record.write_text("flags\t\t: fpu sse2 avx avx2\n")
    build_cpu.check_cpu(record, cpuinfo)  # an older build CPU is fine
    build_cpu.check_cpu(tmp_path / "absent.txt", cpuinfo)  # a portable build records nothing


def test_this_machine_runs_its_own_build():
    build_cpu.check_cpu()


def test_cli_reports_it_in_one_line_exit_2(monkeypatch, capsys):
    def parser():
        raise DmaisError("the pose solver's compiled cores were built for a CPU with avx512f")

    monkeypatch.setattr(cli, "_parser", parser)
    assert cli.main(["pose", "--help"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and err.startswith("dmais: error: the pose solver's compiled cores")
