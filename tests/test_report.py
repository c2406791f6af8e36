"""HTML report (sections, self-containment, escaping, missing inputs) and the paper comparisons."""

from __future__ import annotations

import json
import shutil
from html.parser import HTMLParser

import jinja2
import numpy as np
import pandas as pd
import pytest
import yaml

from dmais_pipe.calib.extrinsics import extrinsics_tables
from dmais_pipe.calib.intrinsics import TABLE_COLUMNS
from dmais_pipe.dataset import Dataset, flight_observations
from dmais_pipe.errors import DmaisError
from dmais_pipe.evaluate import conf_table, pose_methods_table
from dmais_pipe.geometry import Rigid3, quat_from_rotation, rotation_from_euler_zyx
from dmais_pipe.report import page
from dmais_pipe.report.dataset import page_values, summarize, summary_table
from dmais_pipe.report.html import FIGURE_FILES, SECTIONS, Section, benchmark_table
from dmais_pipe.report.page import Image, Table, cell_text
from dmais_pipe.report.paper import BY_CONSTRUCTION, PAPER_DIR, PAPER_TABLES, compare_with_paper, paper_comparisons, paper_notes
from dmais_pipe.pose.flight import pixel_residuals
from dmais_pipe.rig import Rig
from dmais_pipe.stages import evaluate, report
from dmais_pipe.workspace import POSE_OBSERVATION_COLUMNS, Workspace

from conftest import observation_only

SIM = observation_only("report-small", seed=9, calib_images=2, eval_images=1, frames_per_group=2)
SECTION_IDS = [key for key, _ in SECTIONS]


class Page(HTMLParser):
    """Section ids in order, the 'missing' notes and figures (svg, img) per section, every src, the tags."""

    def __init__(self):
        super().__init__()
        self.ids, self.missing, self.figures, self.srcs, self.tags = [], {}, {}, [], []
        self._in_missing = False

    def handle_starttag(self, tag, attrs):
        attrs = dict(attrs)
        self.tags.append(tag)
        if tag == "h2":
            self.ids.append(attrs.get("id"))
        if "src" in attrs:
            self.srcs.append(attrs["src"])
        if tag in ("svg", "img") and self.ids:
            self.figures[self.ids[-1]] = self.figures.get(self.ids[-1], 0) + 1
        self._in_missing = tag == "p" and attrs.get("class") == "missing"

    def handle_endtag(self, tag):
        if tag == "p":
            self._in_missing = False

    def handle_data(self, data):
        if self._in_missing and self.ids:
            self.missing[self.ids[-1]] = self.missing.get(self.ids[-1], "") + data


def parse(path) -> Page:
    page = Page()
    page.feed(path.read_text(encoding="utf-8"))
    page.close()
    return page


def poses_from_truth(dataset, cameras: str) -> pd.DataFrame:
    """poses.csv rows at the true poses, centres moved by 2 cm."""
    truth = pd.read_csv(dataset / "truth" / "frames.csv", dtype={"frame": str, "group": str})
    rows = []
    for k, r in enumerate(truth.itertuples(index=False)):
        pose = Rigid3.from_quat([r.qw, r.qx, r.qy, r.qz], [r.tx, r.ty, r.tz])
        center = pose.center + [0.02, 0.0, 0.0]
        rows.append({"frame": r.frame, "group": r.group, "cameras": cameras, "n_points": 40,
                     **dict(zip(("qw", "qx", "qy", "qz"), pose.quat)),
                     **dict(zip(("tx", "ty", "tz"), -pose.R @ center)), **dict(zip("xyz", center)),
                     "eps_proj_px": 4.0 + 0.1 * k, "time_ms": 0.5})
    return pd.DataFrame(rows)


def pose_observations(workspace: Workspace, rig: Rig, poses: pd.DataFrame) -> pd.DataFrame:
    """The per-observation file of `poses` as `dmais pose` writes it: every observation used."""
    observations = flight_observations(workspace.dataset, workspace.load_observations())
    parts = []
    for pose in poses.itertuples(index=False):
        rows = observations[observations["frame"] == pose.frame]
        rig_from_world = Rigid3.from_quat([pose.qw, pose.qx, pose.qy, pose.qz], [pose.tx, pose.ty, pose.tz])
        X = workspace.dataset.points.loc[rows["point_id"], ["x", "y", "z"]].to_numpy(float)
        residuals = pixel_residuals(rig, rig_from_world, rows["camera"].to_numpy(str),
                                           rows[["u", "v"]].to_numpy(float), X)
        parts.append(rows.assign(used=True, du=residuals[:, 0], dv=residuals[:, 1]))
    return pd.concat(parts)[list(POSE_OBSERVATION_COLUMNS)]


def write_results(dataset, results) -> None:
    """Every input of the report, written directly with known values."""
    truth = Rig.load(dataset / "truth" / "rig.json")
    truth.save(results / "rig.json")
    poses = poses_from_truth(dataset, "C0+C1+C2+C3+C4")
    poses.to_csv(results / "poses.csv", index=False)
    pose_observations(Workspace.open(dataset, results), truth, poses).to_csv(
        results / "poses.observations.csv", index=False)
    for label in ("0", "012", "01234"):
        names = "+".join(truth.camera_names[int(d)] for d in label)
        poses_from_truth(dataset, names).to_csv(results / f"poses_{label}.csv", index=False)
    budget = [{"frame": frame, "component": component, "sigma": sigma, "unit": unit, "source": "estimated",
               "var_x_m2": var, "var_y_m2": var, "var_z_m2": var, "var_heading_arcmin2": 100 * var,
               "var_pitch_arcmin2": 100 * var, "var_roll_arcmin2": 100 * var}
              for frame in poses["frame"] for component, sigma, unit, var in (("pixel", 0.3, "px", 1e-4),
                                                                              ("survey", 0.02, "m", 3e-4))]
    pd.DataFrame(budget).to_csv(results / "poses.budget.csv", index=False)
    pd.DataFrame([{"group": g, "camera": c, "d_rx_arcmin": 0.0 if c == "C0" else 0.4, "d_ry_arcmin": 0.0,
                   "d_rz_arcmin": 0.0 if c == "C0" else -1.0, "sigma_rx_arcmin": 0.0 if c == "C0" else 1.7,
                   "sigma_ry_arcmin": 0.0 if c == "C0" else 2.2, "sigma_rz_arcmin": 0.0 if c == "C0" else 3.4,
                   "significant": False} for g in ("1", "2") for c in truth.camera_names]).to_csv(
        results / "poses.mounting.csv", index=False)
    evaluate.run(Workspace.open(dataset, results))
    rows = []
    for name, camera in truth.cameras.items():
        record = {"camera": name, **camera.to_dict(), "std": {"fx": 2.5, "fy": 2.4, "cx": 1.1, "cy": 0.9, "d": 0.01},
                  "eps_calib_px": 0.12, "eps_eval_px": 0.15, "n_images": 3, "n_observations": 90,
                  "image_eps_calib_px": {f"{name}_a": 0.11, f"{name}_b": 0.13}, "image_eps_eval_px": {f"{name}_c": 0.15}}
        (results / "intrinsics").mkdir(exist_ok=True)
        (results / "intrinsics" / f"{name}.json").write_text(json.dumps(record))
        pd.DataFrame({"image": [f"{name}_a", f"{name}_c"], "split": ["calib", "eval"], "point_id": ["P1", "P2"],
                      "u": [100.0, 2000.0], "v": [200.0, 1500.0], "du": [0.1, -0.2], "dv": [0.05, 0.1]}).to_csv(
            results / "intrinsics" / f"{name}.residuals.csv", index=False)
        rows.append({"method": "ours", **{k: record[k] for k in TABLE_COLUMNS[1:]}})
        rows.append({"method": "dlt_lm", **{k: record[k] for k in TABLE_COLUMNS[1:]}})
    pd.DataFrame(rows, columns=list(TABLE_COLUMNS)).to_csv(results / "tables" / "intrinsics.csv", index=False)
    unknown = Rig(truth.cameras, {n: Rigid3(p.R, p.t + [0.3, -0.2, 1.0]) if n != "C0" else p
                                  for n, p in truth.cam_from_rig.items()}, "C0")
    truth.save(results / "extrinsics" / "rig_known.json")
    unknown.save(results / "extrinsics" / "rig_unknown.json")
    table_R, table_t = extrinsics_tables(truth, unknown)
    table_R.to_csv(results / "tables" / "extrinsics_R.csv", index=False)
    table_t.to_csv(results / "tables" / "extrinsics_t.csv", index=False)
    pd.DataFrame({"n_points": [10, 50, 100], "ours_ms": [0.2, 0.3, 0.4], "pycolmap_ms": [0.5, 0.6, 0.8],
                  "paper_ms": [0.34, 0.44, 0.55]}).to_csv(results / "tables" / "time_points.csv", index=False)


def write_benchmarks(folder) -> None:
    header = "s\th:m:s\tmax_rss\tmax_vms\tmax_uss\tmax_pss\tio_in\tio_out\tmean_load\tcpu_time\n"
    for relative, seconds, rss in (("markers/img1.tsv", 2.0, 100.0), ("markers/img2.tsv", 4.0, 150.0),
                                   ("intrinsics/C0.tsv", 10.0, 300.0), ("evaluate.tsv", 0.5, 80.0)):
        path = folder / relative
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(header + f"{seconds}\t0:00:0{int(seconds)}\t{rss}\t0\t0\t0\t0\t0\t0\t{seconds}\n")


@pytest.fixture(scope="module")
def dataset(simulated_dataset):
    return simulated_dataset(SIM)


@pytest.fixture(scope="module")
def results(dataset, tmp_path_factory):
    out = tmp_path_factory.mktemp("results")
    write_results(dataset, out)
    return out


# ------------------------------------------------------------------------------ the report


def render(dataset, results, html, **options):
    """The report stage on `results`: the comparisons with the paper, then the page; its path."""
    written = report.run(Workspace.open(dataset, results), html, **options)
    assert html in written
    return html


def test_report_has_every_section_and_is_self_contained(dataset, results, tmp_path):
    write_benchmarks(tmp_path / "benchmarks")
    out = render(dataset, results, tmp_path / "report" / "report.html", benchmarks=tmp_path / "benchmarks")
    page = parse(out)
    assert page.ids == SECTION_IDS
    assert list(page.missing) == ["markers", "extraction"] and "observations given" in page.missing["markers"]
    assert "No image with a file" in page.missing["extraction"]  # observation-only: no image files
    assert set(page.figures) == {"intrinsics", "rig", "fov", "residuals", "frames", "attitude", "subsets", "budget",
                                 "mounting", "runtime", "stages"}
    assert page.figures["intrinsics"] == 2  # residual vectors and eps per image
    assert {p.name for p in (out.parent / "figures").iterdir()} == set(FIGURE_FILES) - {
        "markers_calibration.jpg", "markers_flight.jpg"}
    assert all(src.startswith("data:") for src in page.srcs)
    assert "script" not in page.tags and "link" not in page.tags
    text = out.read_text()
    for expected in ("C4", "eps_pos_mean_m", "true_ang_err_arcmin", "#012", "extrinsics_R",
                     "markers", "± 2.5", "Total angular extent of the 5 cameras", "eps_ang is not a measured",
                     "rms_sigma_position_m"):
        assert expected in text, expected


def test_missing_inputs_make_sections_say_so(dataset, tmp_path):
    empty = tmp_path / "results"
    empty.mkdir()
    with pytest.raises(DmaisError, match="no-dataset"):  # the report is of a dataset: it must load
        render(tmp_path / "no-dataset", empty, tmp_path / "report.html")
    page = parse(render(dataset, empty, tmp_path / "report.html"))
    assert page.ids == SECTION_IDS
    assert set(page.missing) == set(SECTION_IDS) - {"dataset"}
    assert "intrinsics holds no" in page.missing["intrinsics"]
    assert "rig.json is missing" in page.missing["rig"]
    assert "evaluation.csv is missing" in page.missing["frames"]
    assert "conf.csv is missing" in page.missing["subsets"]
    assert "error_budget.csv is missing" in page.missing["budget"]
    assert "mounting.csv is missing" in page.missing["mounting"]
    assert "no benchmark folder" in page.missing["stages"]
    assert "poses.csv is missing" in page.missing["residuals"]
    # A malformed table costs its section only.
    pd.DataFrame({"frame": ["x"], "eps_pos_m": [0.1]}).to_csv(empty / "evaluation.csv", index=False)
    page = parse(render(dataset, empty, tmp_path / "report3.html"))
    assert page.ids == SECTION_IDS and "malformed input: KeyError" in page.missing["frames"]


def test_layout_figure_is_embedded_and_text_escaped(dataset, results, tmp_path):
    copy = tmp_path / "dataset"
    shutil.copytree(dataset, copy)
    manifest = yaml.safe_load((copy / "dataset.yaml").read_text())
    manifest["name"] = "<script>alert(1)</script>"
    (copy / "dataset.yaml").write_text(yaml.safe_dump(manifest))
    mine = tmp_path / "results"
    shutil.copytree(results, mine)
    evaluation = pd.read_csv(mine / "evaluation.csv", dtype=str, keep_default_na=False)
    evaluation["note"] = "<b>bold</b> & co"
    evaluation.to_csv(mine / "evaluation.csv", index=False)
    (mine / "figures").mkdir()
    (mine / "figures" / "extrinsics_layout.svg").write_text(
        '<svg xmlns="http://www.w3.org/2000/svg" width="10" height="10"><circle r="4"/></svg>')
    out = render(copy, mine, tmp_path / "report.html")
    text = out.read_text()
    assert "<script" not in text and "<b>bold" not in text
    assert "&lt;script&gt;alert(1)&lt;/script&gt;" in text and "&lt;b&gt;bold&lt;/b&gt; &amp; co" in text
    page = parse(out)
    assert any(src.startswith("data:image/svg+xml;base64,") for src in page.srcs)
    assert page.ids == SECTION_IDS


class Tables(HTMLParser):
    """Per section (its h2's id, or its heading where it has none), its tables, each a list of rows of cell
    texts (the header row first)."""

    def __init__(self):
        super().__init__()
        self.sections: dict[str, list[list[list[str]]]] = {}
        self._section, self._cell, self._heading = None, None, None

    def handle_starttag(self, tag, attrs):
        if tag == "h2":
            self._section = dict(attrs).get("id")
            self._heading = [] if self._section is None else None
        elif tag == "table":
            self.sections.setdefault(self._section, []).append([])
        elif tag == "tr":
            self.sections[self._section][-1].append([])
        elif tag in ("td", "th"):
            self._cell = []

    def handle_endtag(self, tag):
        if tag in ("td", "th"):
            self.sections[self._section][-1][-1].append("".join(self._cell))
            self._cell = None
        elif tag == "h2" and self._heading is not None:
            self._section, self._heading = "".join(self._heading), None

    def handle_data(self, data):
        if self._cell is not None:
            self._cell.append(data)
        elif self._heading is not None:
            self._heading.append(data)


def cells_by(table: list[list[str]], key: str) -> dict[str, dict[str, str]]:
    """The table's rows keyed by their cell in column `key`, each row a mapping column -> cell."""
    header, *rows = table
    return {row[header.index(key)]: dict(zip(header, row)) for row in rows}


def test_tables_show_each_number_in_its_cell(dataset, results, tmp_path):
    write_benchmarks(tmp_path / "benchmarks")
    out = render(dataset, results, tmp_path / "report.html", benchmarks=tmp_path / "benchmarks")
    parser = Tables()
    parser.feed(out.read_text(encoding="utf-8"))
    tables = parser.sections
    time_points = cells_by(tables["runtime"][0], "n_points")
    assert time_points["50"]["pycolmap_ms"] == "0.6" and time_points["100"]["paper_ms"] == "0.55"
    stages = cells_by(tables["stages"][0], "stage")
    assert (stages["markers"]["jobs"], stages["markers"]["total_s"], stages["markers"]["max_rss_mb"]) == ("2", "6", "150")
    intrinsics = cells_by(tables["intrinsics"][0], "camera")
    assert intrinsics["C3"]["fy"].endswith(" ± 2.4") and intrinsics["C3"]["eps_eval_px"] == "0.15"
    fx = Rig.load(dataset / "truth" / "rig.json").cameras["C0"].fx
    assert fx >= 1e4 and cells_by(tables["rig"][0], "camera")["C0"]["fx"] == f"{fx:.1f}"  # large: to 0.1, no exponent


def test_cells_are_text_as_the_tables_showed_them():
    values = (12345.678, 0.000123456, 2.0, np.float32(0.5), -3e-12, np.nan, None, pd.NA, np.int64(7), True, "a<b")
    assert [cell_text(v) for v in values] == ["12345.7", "0.0001235", "2", "0.5", "-3e-12", "", "", "", "7", "True",
                                              "a<b"]


HOSTILE = "<script>alert(1)</script>"


def test_templates_escape_text_from_files():
    escaped = "&lt;script&gt;alert(1)&lt;/script&gt;"
    fov = page.render("sections/fov.html.j2", extent={"cameras": 1, "axis_camera": HOSTILE, "width": "1.0",
                                                      "height": "2.0"},
                      cameras=[{"name": HOSTILE, "width": "1.00", "height": "2.00"}], footprints_missing=None,
                      footprints=Image.inline("<svg><circle r='1'/></svg>"), frame=HOSTILE, ground_z="75.0",
                      points_kind="ground", not_drawn=[HOSTILE, "C1"])
    assert "<script" not in fov and fov.count(escaped) == 4
    assert "<svg><circle r='1'/></svg>" in fov  # our figure's markup, marked as such, is embedded as it is
    assert f"Not drawn (looking above the horizon): {escaped}, C1." in fov
    macros = page.environment().get_template("macros.html.j2").module
    assert f"<td>{escaped}</td>" in macros.table(Table(["camera"], [[HOSTILE]]))
    image = Image.data_uri(b"<svg/>", "image/svg+xml", alt=f'a"{HOSTILE}')
    figure = macros.figure(image, caller=lambda: HOSTILE)
    assert "<script" not in figure and f'alt="a&#34;{escaped}"' in figure and f"<figcaption>{escaped}" in figure
    whole = page.render("report.html.j2", dataset_name=HOSTILE, dataset_root="/data/<x>", results="r & s",
                        sections=[Section("fov", "Fields of view", missing=HOSTILE)])
    assert "<script" not in whole and whole.count(escaped) == 3  # the title twice, the note
    assert "<code>/data/&lt;x&gt;</code>" in whole and "r &amp; s" in whole


def test_a_value_missing_from_a_template_context_raises():
    values = {"runtime_figure": Image.inline("<svg/>"), "time_points": Table(["n_points"], [["10"]])}
    assert "<td>10</td>" in page.render("sections/runtime.html.j2", **values)
    misspelt = {"runtime_figure": values["runtime_figure"], "time_point": values["time_points"]}
    with pytest.raises(jinja2.UndefinedError, match="time_points"):
        page.render("sections/runtime.html.j2", **misspelt)
    with pytest.raises(jinja2.UndefinedError, match="colums"):
        page.environment().from_string("{% for c in t.colums %}{{ c }}{% endfor %}").render(t=Table([], []))
    with pytest.raises(jinja2.UndefinedError):  # not even in a condition: a misspelt flag does not hide its branch
        page.render("sections/attitude.html.j2", scater=None)


def test_benchmark_table(tmp_path):
    write_benchmarks(tmp_path)
    table = benchmark_table(tmp_path).set_index("stage")
    assert set(table.index) == {"markers", "intrinsics", "evaluate"}
    assert table.loc["markers", "jobs"] == 2 and table.loc["markers", "total_s"] == 6.0
    assert table.loc["markers", "mean_s"] == 3.0 and table.loc["markers", "max_rss_mb"] == 150.0
    assert benchmark_table(tmp_path / "nothing").empty


# ------------------------------------------------------------------------------ the paper


def test_compare_with_paper_side_by_side():
    ours = pd.DataFrame({"group": ["1", "1", "all"], "subset": ["012", "0", "012"], "cameras": ["a", "b", "c"],
                         "eps_pos_mean_m": [0.1, 2.0, 0.3], "n_frames": [3, 3, 6]})
    paper = pd.DataFrame({"group": [1, 1, 2], "subset": ["0", "012", "0"], "eps_pos_mean_m": [1.0, 0.05, 0.9]})
    table = compare_with_paper(ours, paper, ["group", "subset"])
    assert list(table.columns) == ["group", "subset", "quantity", "ours", "paper", "ratio", "difference"]
    assert table["quantity"].unique().tolist() == ["eps_pos_mean_m"]  # n_frames: the paper has none
    rows = {(g, s): r for g, s, r in zip(table["group"], table["subset"], table.itertuples())}
    assert rows["1", "012"].ratio == pytest.approx(2.0) and rows["1", "0"].ratio == pytest.approx(2.0)
    assert rows["1", "012"].difference == pytest.approx(0.05)
    assert np.isnan(rows["all", "012"].paper) and np.isnan(rows["2", "0"].ours)
    assert list(rows)[:3] == [("1", "012"), ("1", "0"), ("all", "012")]  # ours first, in our order
    mapped = compare_with_paper(pd.DataFrame({"n_points": [10, 50], "ours_ms": [0.17, 0.22]}),
                                pd.DataFrame({"n_points": [10, 50], "paper_ms": [0.34, 0.44]}),
                                ["n_points"], {"ours_ms": "paper_ms"})
    np.testing.assert_allclose(mapped["ratio"], [0.5, 0.5])


def test_paper_tables_have_our_columns_and_the_published_numbers(dataset):
    def published(name):
        return pd.read_csv(PAPER_DIR / f"{name}.csv", dtype={k: str for k in PAPER_TABLES[name].keys})

    intrinsics = published("intrinsics")
    assert list(intrinsics.columns) == list(TABLE_COLUMNS) and len(intrinsics) == 20
    assert intrinsics.set_index(["method", "camera"]).loc[("ours", "C4"), "eps_eval_px"] == 0.6303
    rig = Rig.load(dataset / "truth" / "rig.json")
    table_R, table_t = extrinsics_tables(rig, rig)
    assert list(published("extrinsics_R").columns) == list(table_R.columns)
    assert list(published("extrinsics_t").columns) == list(table_t.columns)
    assert published("extrinsics_t").set_index("camera").loc["C1", "eps_t_m"] == 3.432
    evaluation = pd.DataFrame({"frame": ["a", "b"], "group": ["1", "1"], "eps_pos_m": [0.1, 0.2],
                               "eps_ang_arcmin": [0.3, 0.4], "eps_proj_px": [4.0, 5.0], "time_ms": [0.5, 0.6]})
    pose_methods = published("pose_methods")
    assert set(pose_methods.columns) <= set(pose_methods_table(evaluation).columns)
    assert pose_methods["group"].tolist() == ["1", "2", "3", "4", "5"]
    conf = published("conf")
    assert set(conf.columns) <= set(conf_table({"0": evaluation}, rig).columns)
    assert conf["subset"].unique().tolist() == ["0", "01", "012", "1234", "01234"]
    assert conf.set_index(["group", "subset"]).loc[("5", "0"), "eps_proj_mean_px"] == 91.832
    assert published("time_points")["paper_ms"].tolist() == [0.34, 0.44, 0.55, 0.75, 0.96, 1.14, 1.36]


def test_paper_comparisons_are_written_by_the_report_stage(dataset, results, tmp_path):
    workspace = Workspace.open(dataset, results)
    ours = {name: workspace.load_table(name, spec.keys) for name, spec in PAPER_TABLES.items()}
    assert set(paper_comparisons(ours)) == set(PAPER_TABLES)
    written = report.run(workspace, tmp_path / "report.html")
    assert {workspace.table_path(f"{name}_vs_paper") for name in PAPER_TABLES} <= set(written)
    assert {p.name for p in (tmp_path / "tables").glob("*_vs_paper.csv")} == {f"{n}_vs_paper.csv" for n in PAPER_TABLES}
    intrinsics = pd.read_csv(workspace.table_path("intrinsics_vs_paper"))
    # our dlt_lm baseline meets the paper's Bouguet row; BabelCalib has no counterpart of ours
    bouguet = intrinsics[(intrinsics["method"] == "bouguet") & (intrinsics["quantity"] == "fx")]
    assert bouguet["ours"].notna().all() and bouguet["paper"].notna().all()
    assert intrinsics.loc[intrinsics["method"] == "babelcalib", "ours"].isna().all()
    conf = pd.read_csv(workspace.table_path("conf_vs_paper"), dtype={"subset": str, "group": str})
    row = conf[(conf["group"] == "1") & (conf["subset"] == "012") & (conf["quantity"] == "eps_proj_mean_px")]
    assert len(row) == 1 and row["paper"].item() == 4.398
    assert row["ratio"].item() == pytest.approx(row["ours"].item() / 4.398)
    time_points = pd.read_csv(workspace.table_path("time_points_vs_paper"))
    assert time_points["ratio"].iloc[0] == pytest.approx(0.2 / 0.34)


def test_paper_notes_cover_every_table_and_reach_the_report(dataset, results, tmp_path):
    notes = paper_notes()
    assert set(notes) == set(PAPER_TABLES) and all(len(text) > 80 for text in notes.values())
    (results / "tables" / "extrinsics_note.txt").write_text("Without the priors the centres move by 1 cm.")
    html = render(dataset, results, tmp_path / "report.html").read_text()
    assert html.count('<p class="note">') == len(notes) + 1 + len(BY_CONSTRUCTION)  # simulated: by construction
    assert html.count("By construction: ") == len(BY_CONSTRUCTION)
    assert "This run: Without the priors the centres move by 1 cm." in html
    (tmp_path / "paper").mkdir()
    (tmp_path / "paper" / "notes.yaml").write_text("intrinsic: typo\n")
    with pytest.raises(DmaisError, match="intrinsic"):
        paper_notes(tmp_path / "paper")


def test_marker_quality_flags_the_image_whose_corners_are_poor():
    """Per image and camera: counts, sigma quantiles; an image 5x worse than its camera's others is flagged."""
    from dmais_pipe.markers.quality import camera_quality, image_quality

    rng = np.random.default_rng(0)

    def markers(n, sigma, identified):
        return pd.DataFrame({"u": rng.uniform(0, 4096, n), "v": rng.uniform(0, 3000, n), "score": 0.9,
                             "sigma_px": rng.uniform(0.8, 1.2, n) * sigma, "fit_residual": 0.02,
                             "point_id": [f"P{k}" if k < identified else "" for k in range(n)]})

    tables = {"a0": markers(20, 0.02, 18), "a1": markers(15, 0.02, 15), "a2": markers(12, 0.10, 10),
              "b0": markers(10, 0.20, 10), "b1": markers(10, 0.22, 9)}
    camera_of = {"a0": "A", "a1": "A", "a2": "A", "b0": "B", "b1": "B"}
    images = image_quality(tables, camera_of)
    assert images.set_index("image")["flagged"].to_dict() == {"a0": False, "a1": False, "a2": True, "b0": False,
                                                               "b1": False}
    assert images.set_index("image").loc["a0", ["detected", "identified"]].tolist() == [20, 18]
    cameras = camera_quality(images, tables, camera_of).set_index("camera")
    assert cameras.loc["A", "flagged_images"] == "a2" and cameras.loc["B", "flagged_images"] == "none"
    assert cameras.loc["A", ["images", "detected", "identified"]].tolist() == [3, 47, 43]
    expected = np.median(np.concatenate([tables[i]["sigma_px"] for i in ("a0", "a1", "a2")]))
    assert cameras.loc["A", "sigma_median_px"] == pytest.approx(expected)


# ------------------------------------------------------------------------------ the dataset page (dmais summarize)


def test_dataset_page_escapes_camera_and_image_names(dataset, tmp_path):
    """A dataset and a camera named like markup show as text: in the title, the table, the marker's caption."""
    copy = tmp_path / "dataset"
    shutil.copytree(dataset, copy)
    manifest = yaml.safe_load((copy / "dataset.yaml").read_text())
    manifest["name"] = HOSTILE
    manifest["cameras"][HOSTILE] = manifest["cameras"].pop("C4")
    (copy / "dataset.yaml").write_text(yaml.safe_dump(manifest))
    images = pd.read_csv(copy / "images.csv", dtype=str, keep_default_na=False)
    images.assign(camera=images["camera"].replace("C4", HOSTILE)).to_csv(copy / "images.csv", index=False)
    escaped = "&lt;script&gt;alert(1)&lt;/script&gt;"
    text = summarize(copy, tmp_path / "reports").read_text(encoding="utf-8")
    assert "<script" not in text and f"<h1>Dataset {escaped}</h1>" in text
    assert text.count(f"<td>{escaped}</td>") == 3  # its intrinsics, extrinsics and flight rows
    loaded = Dataset.load(copy)  # this dataset renders no image: the marker's caption as marker_example writes it
    values = page_values(loaded, summary_table(loaded), (b"png", f"Image {HOSTILE}, point P1."))
    with_marker = page.render("dataset_page.html.j2", **values)
    assert "<script" not in with_marker and f"<figcaption>Image {escaped}, point P1.</figcaption>" in with_marker


def test_dataset_page_shows_each_value_in_its_cell(dataset, tmp_path):
    parser = Tables()
    parser.feed(summarize(dataset, tmp_path / "reports").read_text(encoding="utf-8"))
    tables = parser.sections
    assert list(tables) == ["Images and observations", "Truth rig", "Simulator noise budget"]
    header, *rows = tables["Images and observations"][0]
    by_stage_camera = {(row[0], row[1]): dict(zip(header, row)) for row in rows}
    images = pd.read_csv(dataset / "images.csv", dtype=str, keep_default_na=False)
    observations = pd.read_csv(dataset / "observations.csv", dtype=str).merge(images, on="image")
    given = len(observations.query("stage == 'intrinsics' and camera == 'C2'"))
    assert by_stage_camera["intrinsics", "C2"] == {"stage": "intrinsics", "camera": "C2", "images": "3",
                                                   "image_files": "0", "observations": str(given)}
    fx = Rig.load(dataset / "truth" / "rig.json").cameras["C0"].fx
    assert cells_by(tables["Truth rig"][0], "camera")["C0"]["fx"] == f"{fx:.4g}"  # this page: 4 digits, always
    pixel_sigma = yaml.safe_load((dataset / "truth" / "simulation.yaml").read_text())["flight"]["pixel_sigma_px"]
    noise = cells_by(tables["Simulator noise budget"][0], "source")
    assert noise["flight markers, not rendered"]["standard deviation"] == f"{pixel_sigma:g} px per axis"
