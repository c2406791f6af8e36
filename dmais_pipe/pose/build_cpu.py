"""The CPU the compiled cores were built for, checked before they are loaded.

setup.py compiles `_kernels` and `_refine` with -march=native (docs/design.md, Layout) and then
records the build CPU's flags (the `flags` line of /proc/cpuinfo) in `_build_cpu.txt` beside them;
a portable build (DMAIS_PORTABLE_BUILD=1) records nothing. On a machine whose CPU lacks one of
the instruction-set extensions the build CPU had (a cluster node older than the login node that
ran `make install`), the cores would die of an illegal instruction, so this module turns that into
one clear error before they are imported.
"""

from __future__ import annotations

from pathlib import Path

from ..errors import DmaisError

RECORD = Path(__file__).with_name("_build_cpu.txt")
CPUINFO = Path("/proc/cpuinfo")
#: x86-64 extensions GCC's -march=native may emit instructions of (/proc/cpuinfo names).
INSTRUCTION_SETS = frozenset(
    "sse3 pni ssse3 sse4_1 sse4_2 sse4a popcnt abm lzcnt movbe fma fma4 f16c avx avx2 bmi1 bmi2 adx aes "
    "pclmulqdq vpclmulqdq vaes gfni sha_ni xop tbm avx512f avx512dq avx512cd avx512bw avx512vl avx512ifma "
    "avx512vbmi avx512_vbmi2 avx512_vnni avx512_bitalg avx512_vpopcntdq avx512_bf16 avx512_fp16 avx_vnni "
    "amx_tile amx_int8 amx_bf16".split())


def cpu_flags(cpuinfo: str) -> set[str]:
    """The flags of the first processor in the text of /proc/cpuinfo (empty if it has none)."""
    for line in cpuinfo.splitlines():
        key, _, value = line.partition(":")
        if key.strip() == "flags":
            return set(value.split())
    return set()


def missing_instruction_sets(built_for: set[str], here: set[str]) -> list[str]:
    """The instruction-set extensions of the build CPU this CPU lacks, sorted."""
    return sorted((built_for - here) & INSTRUCTION_SETS)


def check_cpu(record: Path = RECORD, cpuinfo: Path = CPUINFO) -> None:
    """Raise DmaisError if the cores were built for instructions this CPU lacks (no record or no
    /proc/cpuinfo: nothing to check)."""
    if not (record.is_file() and cpuinfo.is_file()):
        return
    missing = missing_instruction_sets(cpu_flags(record.read_text()), cpu_flags(cpuinfo.read_text()))
    if missing:
        raise DmaisError(
            f"the pose solver's compiled cores ({record.parent}) were built for a CPU with {', '.join(missing)}, "
            "which this machine's CPU lacks: rebuild them on this machine (rm -rf .venv && make install) or "
            "build them for every machine (rm -rf .venv && DMAIS_PORTABLE_BUILD=1 make install)")
