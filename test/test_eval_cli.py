"""`pcc eval` end to end on a tiny cache written with the instance extractor."""

from __future__ import annotations

import json

import numpy as np
import pytest
from shapes import car_with_cabin

from pcc_ros.cli.main import main
from pcc_ros.data.instances import ExtractConfig, extract_instances
from pcc_ros.geometry.canonical import from_canonical
from pcc_ros.types import Boxes, Sample


@pytest.fixture(scope="module")
def tiny_cache(tmp_path_factory):
    """2 sequences (train / test) x 3 frames x 3 cars beside the sensor, seen from one side only."""
    root = tmp_path_factory.mktemp("synth")
    rng = np.random.default_rng(0)
    (root / "meta.json").write_text(json.dumps({"seed": 0, "splits": {"train": ["0000"], "test": ["0001"]}}))
    frames = []
    for seq in ["0000", "0001"]:
        shapes = {}
        for t in range(3):
            shapes[str(t)] = car_with_cabin(rng)
            (root / "shapes" / seq).mkdir(parents=True, exist_ok=True)
            np.save(root / "shapes" / seq / f"{t}.npy", shapes[str(t)])
        for f in range(3):
            centers = np.array([[1.0 + f, 8.0, -0.9], [-2.0 + f, -25.0, -0.9], [2.0, 45.0 + f, -0.9]])
            yaws = np.array([0.1, -0.2, 0.3 + 0.1 * f])
            lengths = np.array([4.2, 4.6, 3.9])
            size = np.column_stack([lengths, lengths * 0.4, lengths * 0.35])
            points = []
            for t in range(3):
                shape = shapes[str(t)]
                sensor = from_canonical(shape, centers[t], yaws[t], lengths[t])
                towards = -centers[t] / np.linalg.norm(centers[t])
                outward = sensor - centers[t]
                seen = (outward @ towards) > 0  # the sensor-facing half only
                keep = seen & (rng.random(len(shape)) < [0.3, 0.1, 0.03][t])
                points.append(sensor[keep])
            pts = np.concatenate(points).astype(np.float32)
            pts = np.column_stack([pts, np.zeros(len(pts), np.float32)])
            boxes = Boxes(centers, size, yaws, ["Car"] * 3, None, [str(t) for t in range(3)])
            frames.append(Sample(stamp_ns=f * 100_000_000, frame_id="velodyne", points=pts, ground_truth=boxes,
                                sequence=seq, index=f))
    cache_dir = tmp_path_factory.mktemp("cache") / "cache"
    cache = extract_instances(frames, cache_dir, ExtractConfig(ground_margin=0.0), synthcars=root, progress=False)
    assert len(cache.indices("test")) == 9
    return cache_dir


def test_pcc_eval_end_to_end_ground_truth(tiny_cache, tmp_path, capsys):
    out_json, out_png = tmp_path / "eval.json", tmp_path / "eval.png"
    argv = ["eval", "--data", str(tiny_cache), "--split", "test", "--backends", "input,densify,mirror",
            "--json", str(out_json), "--plot", str(out_png), "--emd-points", "128", "--seed", "1"]
    assert main(argv) == 0
    text = capsys.readouterr().out
    assert "reference: ground_truth" in text and "cd_l1 [m, sensor frame" in text
    results = json.loads(out_json.read_text())
    assert results["reference"] == "ground_truth" and results["instances"] == 9 and results["split"] == "test"
    b = results["backends"]
    for name in ("input", "densify", "mirror"):
        overall = b[name]["overall"]
        assert set(overall) >= {"cd_l1", "cd_l2", "precision", "coverage", "fscore", "emd", "fidelity", "side_cd"}
        assert overall["count"] == 9
        assert [b[name]["by_distance"][k]["count"] for k in ("0-20m", "20-40m", "40m+")] == [3, 3, 3]
    # Half of each car seen: the mirror covers the other half.
    assert b["mirror"]["overall"]["coverage"] < 0.7 * b["input"]["overall"]["coverage"]
    assert b["input"]["overall"]["precision"] < b["densify"]["overall"]["precision"]
    assert out_png.stat().st_size > 10_000 and len(results["plot"]["instances"]) == 4
    # Re-running reuses the finished results and reproduces the file exactly.
    before = out_json.read_text()
    assert main(argv) == 0
    assert out_json.read_text() == before


def test_pcc_eval_aggregated_reference(tiny_cache, tmp_path):
    out_json = tmp_path / "agg.json"
    assert main(["eval", "--data", str(tiny_cache), "--backends", "input,mirror", "--reference", "aggregated",
                 "--no-emd", "--max-instances", "5", "--json", str(out_json)]) == 0
    results = json.loads(out_json.read_text())
    assert results["reference"] == "aggregated" and results["instances"] == 5
    overall = results["backends"]["input"]["overall"]
    # The aggregate contains the observation itself: input is exactly on it.
    assert overall["precision"] == 0.0 and overall["fidelity"] == 0.0 and "emd" not in overall
    assert results["backends"]["mirror"]["overall"]["side_cd"] >= 0.0


def test_pcc_eval_errors(tiny_cache, tmp_path, caplog):
    assert main(["eval", "--data", str(tmp_path / "none"), "--backends", "input"]) == 1
    assert main(["eval", "--data", str(tiny_cache), "--backends", "bogus"]) == 1
    assert "unknown completion backend 'bogus'" in caplog.text
    assert main(["eval", "--data", str(tiny_cache), "--split", "nope", "--backends", "input"]) == 1
    assert main(["eval", "--data", str(tiny_cache), "--backends", "input", "--checkpoint", "input=x"]) == 1
