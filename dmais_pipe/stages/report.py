"""`dmais report`: the results beside the paper's tables, then the self-contained HTML report.

Writes tables/<name>_vs_paper.csv for every table with a published counterpart (report.paper),
the report (report.html, which renders the written files only) and a copy of every table beside it.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from ..files import copy_atomic
from ..report.html import write_report
from ..report.paper import PAPER_TABLES, paper_comparisons
from ..workspace import Workspace
from . import setting


@dataclass(frozen=True)
class Conf:
    """Where the published tables come from, and the other runs to compare with."""

    paper_dir: str = setting("", "folder of the published tables to compare with ('': the package's "
                                 "transcription of the paper)")
    compare_with: tuple = setting((), "other runs whose pose accuracy per camera subset (tables/conf.csv) the "
                                      "report shows beside this run's: results folders beside this one "
                                      "(results/<name>) by name, or paths")


CONFS = {"default": Conf()}


def run(workspace: Workspace, html: Path, conf: Conf = Conf(), benchmarks: Path | None = None) -> list[Path]:
    """Compare with the paper, write the report to `html` and the CSV tables beside it (html's tables/)."""
    paper_dir = conf.paper_dir or None
    ours = {name: table for name, spec in PAPER_TABLES.items()
            if (table := workspace.load_table(name, spec.keys)) is not None}
    written = [workspace.save_table(f"{name}_vs_paper", table)
               for name, table in paper_comparisons(ours, paper_dir).items()]
    written.append(write_report(workspace, html, benchmarks_dir=benchmarks, paper_dir=paper_dir,
                                compare_with=conf.compare_with))
    written += [copy_atomic(table, Path(html).parent / "tables" / table.name) for table in workspace.table_paths()]
    return written
