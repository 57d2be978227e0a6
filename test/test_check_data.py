"""`pcc check-data`: the layout found and what is missing, for KITTI tracking / object, nuScenes and
Argoverse 2 roots built broken by the tests; a missing default data folder says what to download."""

from __future__ import annotations

import numpy as np
from av2_fixture import write_log
from conftest import assert_named_failure, run_cli

from pcc_ros.cli.main import main
from pcc_ros.data.layouts import check_layout, check_tree
from pcc_ros.data.nuscenes import TABLES


def _scan(path, n: int = 10) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    np.zeros((n, 4), np.float32).tofile(path)


def _text(path, text: str = "x") -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(text)


def test_kitti_tracking_with_a_gap_and_no_calibration(tmp_path):
    split = tmp_path / "kitti" / "training"
    for f in ("000000", "000001", "000003"):
        _scan(split / "velodyne" / "0000" / f"{f}.bin")
    _scan(split / "velodyne" / "0001" / "000000.bin")
    _text(split / "calib" / "0001.txt")
    _text(split / "label_02" / "0001.txt")
    report = check_layout(tmp_path / "kitti")
    assert report.layout == "KITTI tracking" and not report.ok
    missing = "\n".join(report.missing)
    assert "0000: 1 scan(s) missing in the numbering" in missing
    assert str(split / "calib" / "0000.txt") in missing and "0001.txt" not in missing
    assert any(str(split / "label_02" / "0000.txt") in n for n in report.notes)  # labels: a note, not fatal
    _scan(split / "velodyne" / "0000" / "000002.bin")
    _text(split / "calib" / "0000.txt")
    assert check_layout(split).ok  # the split directory itself is accepted too


def test_kitti_object_missing_calibration_files(tmp_path):
    for f in ("000000", "000001", "000002"):
        _scan(tmp_path / "training" / "velodyne" / f"{f}.bin")
    _text(tmp_path / "training" / "calib" / "000000.txt")
    report = check_layout(tmp_path)
    assert report.layout == "KITTI object" and not report.ok
    assert report.missing == [f"{tmp_path / 'training' / 'calib'}/000001.txt and 1 more: calibration (every "
                              "command needs it)"]
    assert "no labels" in report.notes[0]


def test_nuscenes_without_tables_or_scans(tmp_path):
    _text(tmp_path / "v1.0-mini" / "scene.json", "[]")
    report = check_layout(tmp_path)
    assert report.layout == "nuScenes" and not report.ok
    assert "sample_annotation.json" in report.missing[0] and "scene.json" not in report.missing[0]
    assert "LIDAR_TOP" in report.missing[1]
    for table in TABLES:
        _text(tmp_path / "v1.0-mini" / f"{table}.json", "[]")
    _scan(tmp_path / "samples" / "LIDAR_TOP" / "a.pcd.bin")
    assert check_layout(tmp_path).ok


def test_av2_log_and_split_name_what_is_missing_or_damaged(tmp_path):
    split = tmp_path / "val"
    good = write_log(split / "log_good", sweeps=2)
    report = check_layout(good.root)
    assert report.ok and report.layout == "AV2 log" and report.found == ["log_good: 2 sweeps"]
    assert report.notes == [f"{good.root / 'annotations.feather'}: 1 annotation(s) at a time without a sweep "
                            "(counted and left out by the conversion)"]
    bad = write_log(split / "log_bad", sweeps=2)
    (bad.root / "calibration" / "egovehicle_SE3_sensor.feather").unlink()
    (bad.root / "city_SE3_egovehicle.feather").write_bytes(b"not arrow")
    (bad.root / "annotations.feather").unlink()
    report = check_layout(bad.root)
    assert not report.ok
    assert any("egovehicle_SE3_sensor.feather: sensor calibration missing" in m for m in report.missing)
    assert any("city_SE3_egovehicle.feather: unreadable Arrow feather file" in m for m in report.missing)
    assert any("--no-labels" in n for n in report.notes)  # a test-split log has no annotations
    whole = check_layout(split)
    assert whole.layout == "AV2 split" and whole.found == ["2 logs, 1 complete"] and len(whole.missing) == 2
    import pyarrow as pa
    import pyarrow.feather as feather

    poses = good.root / "city_SE3_egovehicle.feather"
    table = feather.read_table(poses)
    feather.write_feather(table.filter(pa.array(table.column("timestamp_ns").to_numpy() != good.stamps[1])), poses)
    assert check_layout(good.root).missing == [f"{poses}: no pose at 1 sweep time(s), first {good.stamps[1]}"]


def test_cli_reports_and_exit_status(tmp_path, capsys):
    write_log(tmp_path / "data" / "log", sweeps=1)
    assert main(["check-data", str(tmp_path / "data" / "log")]) == 0
    assert "AV2 log layout — complete" in capsys.readouterr().out
    assert main(["check-data", str(tmp_path / "nowhere")]) == 1
    out = capsys.readouterr().out
    assert "does not exist" in out and "cvlibs.net" in out and "nuscenes.org" in out and "argoverse.org" in out
    (tmp_path / "empty").mkdir()
    assert main(["check-data", str(tmp_path / "empty")]) == 1
    assert "unknown layout" in capsys.readouterr().out


def test_a_folder_of_datasets_reports_each(shared_data):
    layouts = {r.layout for r in check_tree(shared_data)}
    assert {"KITTI tracking", "KITTI object", "nuScenes"} <= layouts


def test_eval_real_without_the_default_data_says_what_to_download(tmp_path, caplog):
    rc, text = run_cli(["eval", "--real", "--real-sources", tmp_path / "shared" / "data" / "kitti_tracking",
                        "--backends", "input", "--json", tmp_path / "r.json"], caplog)
    assert_named_failure(rc, text, "real dataset not found", "cvlibs.net", "check-data", output=tmp_path / "r.json")
