"""`pcc replay`: the nodes' pipeline over a bag, outputs recorded on the nodes' topics."""

from __future__ import annotations

import numpy as np
import pytest
from conftest import assert_named_failure, run_cli
from rosbags.highlevel import AnyReader

from pcc_ros.cli.main import main
from pcc_ros.data.bag_writer import write_bag
from pcc_ros.data.kitti import KittiTracking
from pcc_ros.errors import DataError
from pcc_ros.models.registry import load_completer
from pcc_ros.msg.pointcloud2 import read_xyz
from pcc_ros.msg.typestore import get_typestore
from pcc_ros.pipeline.config import load_config
from pcc_ros.pipeline.core import Pipeline, PipelineConfig
from pcc_ros.runtime.bag_replay import replay_bag


@pytest.fixture(scope="module", params=["mcap", "sqlite3"])
def kitti_bag(request, shared_data, tmp_path_factory):
    root = shared_data / "kitti_tracking"
    frames = KittiTracking(root / "training").frames(
        "0000", detections_dir=root / "detections" / "pointrcnn", stop=3
    )
    out = tmp_path_factory.mktemp(request.param) / "kitti"
    write_bag(frames, out, storage=request.param, progress=False)
    return out


def read_topics(bag):
    with AnyReader([bag], default_typestore=get_typestore()) as reader:
        out: dict[str, list] = {}
        for conn, _, raw in reader.messages():
            out.setdefault(conn.topic, []).append(reader.deserialize(raw, conn.msgtype))
        return out


def test_replay_writes_node_topics_matching_the_pipeline(kitti_bag, tmp_path):
    config = PipelineConfig(backend="mirror", min_points=10)
    pipeline = Pipeline(config, completer=load_completer("mirror"))
    results = []
    summary = replay_bag(
        kitti_bag, tmp_path / "out", pipeline, on_result=lambda r, c, d: results.append(r), progress=False
    )
    assert summary.frames == 3 and summary.skipped_frames == 0
    topics = read_topics(tmp_path / "out")
    for name in ("/completed", "/completed_markers", "/detections_filtered", "/detections_rejected", "/points"):
        assert len(topics[name]) == 3, name
    for msg, result in zip(topics["/completed"], results):
        np.testing.assert_array_equal(read_xyz(msg), result.completed_points)
        assert msg.header.frame_id == "velodyne"
    assert sum(len(m.detections) for m in topics["/detections_filtered"]) == summary.kept


def test_replay_opens_the_bag_once(kitti_bag, tmp_path, monkeypatch):
    """Topic check, transforms and messages come from one open reader."""
    import pcc_ros.runtime.bag_replay as replay_module

    opened = []
    real_open = replay_module.open_bag
    monkeypatch.setattr(replay_module, "open_bag", lambda path: opened.append(path) or real_open(path))
    pipeline = Pipeline(PipelineConfig(backend="input"), completer=load_completer("input"))
    summary = replay_bag(kitti_bag, tmp_path / "out", pipeline, progress=False)
    assert summary.frames == 3 and opened == [kitti_bag]


def test_pairs_report_unpaired_messages(kitti_bag):
    """Replay pairs with the node's own pairer; its summary reports what stayed unpaired."""
    pipeline = Pipeline(PipelineConfig(backend="input"), completer=load_completer("input"))
    summary = replay_bag(kitti_bag, None, pipeline, detections_topic="/ground_truth", progress=False)
    assert summary.frames == 3
    assert summary.unpaired_clouds == 0 and summary.unpaired_detections == 0


def test_missing_topic_is_a_clear_error(kitti_bag, tmp_path):
    pipeline = Pipeline(PipelineConfig(backend="input"), completer=load_completer("input"))
    with pytest.raises(DataError, match="no /nothing topic"):
        replay_bag(kitti_bag, tmp_path / "x", pipeline, detections_topic="/nothing", progress=False)
    assert not (tmp_path / "x").exists()  # no partial bag left behind


def test_cli_replay_refuses_an_out_named_like_a_storage_file_before_loading_the_backend(kitti_bag, tmp_path,
                                                                                         caplog, monkeypatch):
    """`--out y.mcap` made a folder y.mcap/ holding y.mcap.mcap; now refused, and (like an existing
    --out without --force) before the backend loads or the bag is read."""
    import pcc_ros.runtime.bag_replay as replay_module

    def loaded(*args, **kwargs):
        raise AssertionError("the pipeline was built before --out was checked")

    monkeypatch.setattr(replay_module, "Pipeline", loaded)
    rc, text = run_cli(["replay", str(kitti_bag), "--out", str(tmp_path / "y.mcap")], caplog)
    assert_named_failure(rc, text, "y.mcap: name the bag folder", output=tmp_path / "y.mcap")
    (tmp_path / "y").mkdir()
    (tmp_path / "y" / "metadata.yaml").write_text("")
    rc, text = run_cli(["replay", str(kitti_bag), "--out", str(tmp_path / "y")], caplog)
    assert_named_failure(rc, text, tmp_path / "y", "exists; pass --force")


def test_a_warning_during_the_progress_bar_is_its_own_line(kitti_bag, tmp_path):
    """`pcc replay` on PointRCNN logits with score_mapping identity: the warning was printed glued to
    the progress bar's line ("replay:   0%|  | 0/9 [...]WARNING pcc_ros.pipeline.core: ..."); log
    lines now go above the bar (the command's real console logging, so a separate process)."""
    import subprocess
    import sys

    run = subprocess.run([sys.executable, "-m", "pcc_ros.cli", "replay", str(kitti_bag), "--out", str(tmp_path / "o"),
                          "--filter", "--backend", "mirror", "--score-mapping", "identity"],
                         capture_output=True, text=True, timeout=120)
    assert run.returncode == 0, run.stderr
    pieces = [piece.strip() for line in run.stderr.splitlines() for piece in line.split("\r")]
    warning = [piece for piece in pieces if "outside [0, 1]" in piece]
    # labelled with the node's name, as the node's own lines and a live node's ([detection_filter_node]),
    # not with the pipeline module's (pcc_ros.pipeline.core)
    assert warning and all(piece.startswith("WARNING pcc_ros.detection_filter_node: ") for piece in warning), run.stderr


def test_cli_replay_with_filter(kitti_bag, tmp_path, capsys):
    out = tmp_path / "cli"
    code = main(["replay", str(kitti_bag), "--out", str(out), "--backend", "densify", "--filter", "--no-copy-inputs"])
    assert code == 0 and "replay timing" in capsys.readouterr().out
    assert set(read_topics(out)) == {
        "/completed", "/completed_markers", "/detections_filtered", "/detections_rejected", "/filter_markers"
    }


def test_shipped_config_loads_with_overrides():
    config, slop = load_config(None, with_filter=True, backend="mirror")
    assert config.backend == "mirror" and config.filter.match_threshold == 0.3 and slop > 0


def test_a_bag_without_tf_loads_no_transforms_and_warns_nothing(kitti_bag, caplog):
    """The KITTI sample has no /tf: reading its (empty) set of transform topics reads nothing.

    rosbags reads *every* topic when asked for an empty list of connections; replay and the
    demo then decoded each scan as a transform and warned once per message."""
    from pcc_ros.data.bag import iter_messages, open_bag
    from pcc_ros.runtime.bag_replay import load_transforms
    from pcc_ros.runtime.local import LocalGraph

    caplog.set_level("WARNING")
    with open_bag(kitti_bag) as reader:
        assert list(iter_messages(reader, kitti_bag, [])) == []
        assert load_transforms(LocalGraph(), reader, kitti_bag) == 0
    assert not [r for r in caplog.records if "transforms" in r.getMessage()]
