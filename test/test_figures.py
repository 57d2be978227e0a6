"""The figure tables of the README and docs are rendered from committed result JSON
(``scripts/render_figures.py``), never typed: a table that differs from its JSON fails here."""

from __future__ import annotations

import importlib.util
import json
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


def _load():
    spec = importlib.util.spec_from_file_location("render_figures", ROOT / "scripts" / "render_figures.py")
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module  # dataclasses look their module up while the class is made
    spec.loader.exec_module(module)
    return module


figures = _load()


def test_every_figure_matches_its_json():
    problems = figures.check(ROOT)
    assert not problems, "\n".join(problems) + "\n(run `python scripts/render_figures.py` to re-render)"


def test_every_result_names_its_command_commit_and_date():
    results = sorted((ROOT / figures.RESULTS).glob("*.json"))
    assert results
    for path in results:
        provenance = json.loads(path.read_text())["provenance"]
        assert provenance["command"] and provenance["commit"] and provenance["date"][:4].isdigit(), path


@pytest.fixture
def copy(tmp_path):
    """The README, docs and results of this checkout, in a scratch folder."""
    shutil.copy(ROOT / "README.md", tmp_path / "README.md")
    shutil.copytree(ROOT / "docs", tmp_path / "docs")
    return tmp_path


def test_a_retyped_table_or_a_changed_json_is_caught_and_re_rendered(copy):
    doc = next(p for p in figures.documents(copy) if "<!-- figure: bench-crop -->" in p.read_text())
    text = doc.read_text()
    start = text.index("<!-- figure: bench-crop -->")
    row = text.index("| 30 |", start)
    doc.write_text(text[:row] + "| 31 |" + text[row + len("| 30 |"):])  # a hand edit in the table
    assert any("'bench-crop' differs" in p for p in figures.check(copy))
    assert figures.render_all(copy) == [f"{doc.relative_to(copy)}: bench-crop"]
    assert doc.read_text() == text and not figures.check(copy)

    result = copy / figures.RESULTS / "bench-crop.json"
    data = json.loads(result.read_text())
    data["rows"][0]["cropped_points"] += 1  # a new run: the table must follow it
    result.write_text(json.dumps(data))
    assert any("'bench-crop' differs" in p for p in figures.check(copy))


def test_unknown_unclosed_and_unused_figures_are_named(copy):
    readme = copy / "README.md"
    readme.write_text(readme.read_text() + "\n<!-- figure: no-such-table -->\n<!-- /figure -->\n")
    assert any("README.md" in p and "unknown figure 'no-such-table'" in p for p in figures.check(copy))
    readme.write_text(readme.read_text().replace("<!-- figure: no-such-table -->\n<!-- /figure -->\n",
                                                 "<!-- figure: bench-crop -->\n"))
    assert any("never closed" in p for p in figures.check(copy))
    for doc in figures.documents(copy):  # no block left for bench-crop
        doc.write_text(doc.read_text().replace("<!-- figure: bench-crop -->", "<!-- bench-crop -->"))
    assert "figure 'bench-crop' appears in no document" in figures.check(copy)


def test_store_records_the_provenance(tmp_path):
    result = tmp_path / "crop.json"
    result.write_text(json.dumps({"rows": [], "cpu_count": 2,
                                  "run": {"commit": "abc1234", "utc": "2026-11-28 14:31:40",
                                          "other_processes_cores": 0.004}}))
    stored = json.loads(figures.store(tmp_path, "bench-x", result, "pcc bench crop").read_text())
    assert stored["provenance"] == {"command": "pcc bench crop", "commit": "abc1234", "date": "2026-11-28 14:31",
                                    "machine": {"cpu_count": 2, "other_processes_cores": 0.004}}
    assert "idle)" in figures.provenance(stored, "bench-x")


def test_a_run_that_measured_nothing_leaves_the_stored_result(tmp_path):
    """`pcc bench gpu` without CUDA writes only its reason: the H200's stored figures must stay."""
    measured = tmp_path / "gpu.json"
    measured.write_text(json.dumps({"rows": [1], "run": {"commit": "abc1234", "utc": "2026-11-28 17:07:21"}}))
    stored = figures.store(tmp_path, "bench-gpu", measured, "pcc bench gpu")
    before = stored.read_text()
    measured.write_text(json.dumps({"skipped": "no CUDA device on this machine: nothing to measure"}))
    with pytest.raises(SystemExit, match=r"measured nothing.*no CUDA device"):
        figures.store(tmp_path, "bench-gpu", measured, "pcc bench gpu")
    assert stored.read_text() == before


def test_a_result_no_figure_renders_is_named(copy):
    (copy / figures.RESULTS / "stray.json").write_text("{}")
    assert f"{figures.RESULTS / 'stray.json'} is rendered by no figure" in figures.check(copy)


def test_json_output_is_the_last_json_of_the_command():
    assert figures.json_output("pcc synth --out a && pcc eval detections --json out/x.json --plot p.png") == \
        Path("out/x.json")
    assert figures.json_output("pcc bench crop --repeat 30") is None


def test_rerun_runs_the_recorded_command_and_stores_its_output(tmp_path):
    subprocess.run(["git", "init", "-q"], cwd=tmp_path, check=True)
    subprocess.run(["git", "-c", "user.name=t", "-c", "user.email=t@t", "commit", "-q", "--allow-empty", "-m", "x"],
                   cwd=tmp_path, check=True)
    (tmp_path / "new.json").write_text(json.dumps({"rows": [1, 2]}))
    command = "cp new.json res.json && true --json res.json"  # `true` ignores its arguments
    (tmp_path / "old.json").write_text(json.dumps({"rows": [1]}))
    figures.store(tmp_path, "x", tmp_path / "old.json", command)
    assert figures.rerun(tmp_path, ["x"]) == [tmp_path / figures.RESULTS / "x.json"]
    stored = json.loads((tmp_path / figures.RESULTS / "x.json").read_text())
    assert stored["rows"] == [1, 2] and stored["provenance"]["command"] == command
    with pytest.raises(SystemExit, match="no stored result matches"):
        figures.rerun(tmp_path, ["nothing-*"])


def test_a_typed_table_of_measurements_is_named_unless_a_dated_record(copy):
    doc = copy / "docs" / "typed.md"
    typed = "| backend | CD-L1 |\n| --- | --- |\n| a | 0.123 |\n| b | **4.5 ms** |\n"
    doc.write_text("# x\n\n" + typed)
    assert any("typed.md:3: a table of measured values typed by hand" in p for p in figures.check(copy))
    doc.write_text("# x\n\nA dated record of commit abc1234:\n\n" + typed)
    assert not any("typed.md" in p for p in figures.check(copy))
    doc.write_text("# x\n\n| setting | default |\n| --- | --- |\n| `workers` | `2` |\n| `rate` | 0.5 |\n")
    assert not any("typed.md" in p for p in figures.check(copy))  # one number is not a table of figures
