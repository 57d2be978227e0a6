"""Conversion to rosbag2 (MCAP and sqlite3) and reading back: real KITTI / nuScenes samples."""

from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np
import pytest
from conftest import assert_named_failure, run_cli
from test_kitti import OXTS, _copy_tracking
from test_nuscenes import build_tables

from pcc_ros.cli.info import summarize
from pcc_ros.cli.main import main
from pcc_ros.data.bag import read_frames
from pcc_ros.data.bag_writer import write_bag
from pcc_ros.data.kitti import KittiObject, KittiTracking
from pcc_ros.data.nuscenes import NuScenes
from pcc_ros.data.sources import count_frames, kind_of, open_frames
from pcc_ros.errors import DataError
from pcc_ros.types import Sample

STORAGES = ("mcap", "sqlite3")


def assert_same_frames(original: list[Sample], back: list[Sample]) -> None:
    assert len(back) == len(original)
    for a, b in zip(original, back):
        assert (b.stamp_ns, b.frame_id, b.sequence, b.index) == (a.stamp_ns, a.frame_id, a.sequence, a.index)
        assert b.fields == a.fields
        assert np.array_equal(b.points, a.points)
        for mine, theirs in ((a.ground_truth, b.ground_truth), (a.detections, b.detections)):
            if mine is None:
                assert theirs is None
            else:  # boxes without 3D extent (DontCare) are not written
                assert theirs.equals(mine[mine.valid_mask()], atol=1e-9)
        if a.pose is None:
            assert b.pose is None
        else:
            assert np.allclose(b.pose, a.pose, atol=1e-9)
            assert np.allclose(b.extras["sensor_to_base"], a.extras["sensor_to_base"], atol=1e-9)


@pytest.mark.parametrize("storage", STORAGES)
def test_kitti_tracking_cli_round_trip(shared_data, tmp_path, storage):
    src = shared_data / "kitti_tracking"
    out = tmp_path / "bag"
    rc = main(["convert", "kitti-tracking", str(src), "--sequence", "0000", "--frames", "3",
               "--detections", str(src / "detections/pointrcnn"), "--out", str(out), "--storage", storage])
    assert rc == 0
    original = list(KittiTracking(src).frames("0000", src / "detections/pointrcnn", stop=3))
    back = list(read_frames(out))
    assert_same_frames(original, back)
    assert "DontCare" in original[0].ground_truth.label.tolist()  # read, but not a 3D box in the bag
    summary = summarize(out)
    assert summary["storage"] == storage
    assert summary["compression"] == ("chunk zstd" if storage == "mcap" else "message zstd")
    assert {t: v["count"] for t, v in summary["topics"].items()} == {"/points": 3, "/ground_truth": 3,
                                                                     "/detections": 3}
    assert summary["topics"]["/points"]["frame_ids"] == ["velodyne"]
    assert summary["topics"]["/points"]["points_per_scan"]["min"] > 100_000
    assert summary["duration_s"] == pytest.approx(0.2, abs=1e-6)


@pytest.mark.parametrize("storage", STORAGES)
def test_kitti_object_round_trip(shared_data, tmp_path, storage):
    src = shared_data / "kitti_object"
    original = list(KittiObject(src).frames(stop=2))
    write_bag(original, tmp_path / "bag", storage=storage, progress=False)
    back = list(read_frames(tmp_path / "bag"))
    assert_same_frames(original, back)
    assert all(f.detections is None for f in back)
    assert "/detections" not in summarize(tmp_path / "bag")["topics"]


@pytest.mark.parametrize("storage", STORAGES)
def test_nuscenes_round_trip_with_tf(shared_data, tmp_path, storage):
    build_tables(shared_data, tmp_path / "nuscenes")
    out = tmp_path / "bag"
    assert main(["convert", "nuscenes", str(tmp_path / "nuscenes"), "--out", str(out), "--storage", storage]) == 0
    original = list(NuScenes(tmp_path / "nuscenes").frames())
    back = list(read_frames(out))
    assert_same_frames(original, back)
    assert back[0].fields == ("x", "y", "z", "intensity", "ring")
    summary = summarize(out)
    assert {(e["topic"], e["parent"], e["child"]) for e in summary["tf"]} == {
        ("/tf", "odom", "base_link"), ("/tf_static", "base_link", "LIDAR_TOP")}
    assert summary["topics"]["/tf_static"]["count"] == 1 and summary["topics"]["/tf"]["count"] == 2


def test_kitti_oxts_poses_round_trip(shared_data, tmp_path):
    root = _copy_tracking(shared_data, tmp_path / "kitti")
    (root / "training/oxts").mkdir()
    (root / "training/oxts/0000.txt").write_text("\n".join(OXTS) + "\n")
    original = list(KittiTracking(root).frames("0000"))
    write_bag(original, tmp_path / "bag", progress=False)
    back = list(read_frames(tmp_path / "bag"))
    assert back[1].pose is not None and not np.allclose(back[1].pose, back[0].pose)
    assert_same_frames(original, back)


def test_bare_storage_file_and_sources(shared_data, tmp_path):
    src = shared_data / "kitti_object"
    original = list(KittiObject(src).frames(stop=1))
    write_bag(original, tmp_path / "bag", progress=False)
    mcap = tmp_path / "bag" / "bag.mcap"
    assert kind_of(tmp_path / "bag") == "bag" and kind_of(mcap) == "bag"
    assert kind_of(src) == "kitti-object" and kind_of(shared_data / "kitti_tracking") == "kitti-tracking"
    assert np.array_equal(next(open_frames(mcap)).points, original[0].points)
    assert next(open_frames(shared_data / "kitti_tracking", sequence="0000")).index == 0
    with pytest.raises(DataError, match="not a bag"):
        kind_of(shared_data / "nuscenes_sample")


def test_count_frames_is_what_open_frames_yields(shared_data, tmp_path):
    """The total of `pcc extract`'s progress bar (it had none: no ETA), from the index / file names."""
    write_bag(KittiObject(shared_data / "kitti_object").frames(stop=3), tmp_path / "bag", progress=False)
    for path, sequence in ((tmp_path / "bag", None), (tmp_path / "bag" / "bag.mcap", None),
                           (shared_data / "kitti_object", None), (shared_data / "kitti_tracking", None),
                           (shared_data / "kitti_tracking", "0000")):
        assert count_frames(path, sequence) == sum(1 for _ in open_frames(path, sequence=sequence)), path
    assert count_frames(shared_data / "nuscenes_mini") is None  # not known without reading the tables


def test_refuses_overwrite_and_force_replaces(shared_data, tmp_path, caplog):
    src = shared_data / "kitti_object"
    out = tmp_path / "bag"
    args = ["convert", "kitti-object", str(src), "--frames", "1", "--out", str(out)]
    assert main(args) == 0
    before = (out / "metadata.yaml").read_text()
    assert_named_failure(*run_cli(args, caplog), out, "exists; pass --force")
    assert (out / "metadata.yaml").read_text() == before
    assert main([*args[:4], "2", *args[5:], "--force"]) == 0
    assert len(list(read_frames(out))) == 2


@pytest.mark.parametrize("name", ["x.mcap", "x.db3"])
def test_out_named_like_a_storage_file_is_refused_naming_the_folder_to_use(shared_data, tmp_path, caplog, name):
    """`--out x.mcap` made a folder x.mcap/ holding x.mcap.mcap (rosbags writes a bag folder), which
    `pcc info x.mcap` then could not read; now it is refused before any work, saying what to pass."""
    src = str(shared_data / "kitti_object")
    rc, text = run_cli(["convert", "kitti-object", src, "--frames", "1", "--out", str(tmp_path / name)], caplog)
    assert_named_failure(rc, text, f"{name}: name the bag folder", f"use {tmp_path / 'x'}")
    assert not list(tmp_path.iterdir())


def test_info_reads_a_bag_folder_whose_name_ends_in_mcap(shared_data, tmp_path, capsys):
    """`ros2 bag record -o run.mcap` makes a folder run.mcap/: `pcc info` took the name for a file
    ("Is a directory")."""
    write_bag(KittiObject(shared_data / "kitti_object").frames(stop=1), tmp_path / "run", progress=False)
    (tmp_path / "run").rename(tmp_path / "run.mcap")
    assert main(["info", str(tmp_path / "run.mcap")]) == 0
    assert "chunk CRCs: all" in capsys.readouterr().out


def test_failure_leaves_no_partial_bag(shared_data, tmp_path):
    frames = list(KittiObject(shared_data / "kitti_object").frames(stop=2))

    def broken():
        yield frames[0]
        raise DataError("scan 000001.bin: truncated")

    out = tmp_path / "bag"
    with pytest.raises(DataError, match="truncated"):
        write_bag(broken(), out, progress=False)
    assert list(tmp_path.iterdir()) == []
    # a failure while replacing keeps the old bag intact
    write_bag(frames[:1], out, progress=False)
    with pytest.raises(DataError, match="truncated"):
        write_bag(broken(), out, force=True, progress=False)
    assert [p.name for p in tmp_path.iterdir()] == ["bag"]
    assert len(list(read_frames(out))) == 1


def test_bad_frames_rejected(shared_data, tmp_path):
    frame = next(KittiObject(shared_data / "kitti_object").frames(stop=1))
    with pytest.raises(DataError, match="increasing stamps"):
        write_bag([frame, frame], tmp_path / "bag", progress=False)
    with pytest.raises(DataError, match="no frames"):
        write_bag([], tmp_path / "bag", progress=False)
    with pytest.raises(DataError, match="unknown storage"):
        write_bag([frame], tmp_path / "bag", storage="rosbag1", progress=False)
    assert list(tmp_path.iterdir()) == []
    with pytest.raises(DataError, match="cannot open bag"):
        list(read_frames(tmp_path / "missing"))
    (tmp_path / "junk.mcap").write_bytes(b"not an mcap file at all")
    with pytest.raises(DataError, match="cannot open bag"):
        list(read_frames(tmp_path / "junk.mcap"))


def test_tracking_needs_sequence_choice(shared_data, tmp_path, caplog):
    src = tmp_path / "two"
    for seq in ("0000", "0001"):
        (src / "training/velodyne" / seq).mkdir(parents=True)
    rc, text = run_cli(["convert", "kitti-tracking", str(src), "--out", str(tmp_path / "bag")], caplog)
    assert_named_failure(rc, text, "choose --sequence among 0000, 0001", output=tmp_path / "bag")


def test_synth_layout_uses_its_detections(shared_data, tmp_path):
    """``pcc convert synth`` reads ``DIR/detections/synthetic/SSSS`` without --detections."""
    root = _copy_tracking(shared_data, tmp_path / "synth")
    dets = root / "detections/synthetic/0000"
    dets.mkdir(parents=True)
    for i in range(2):
        shutil.copy(shared_data / f"kitti_tracking/detections/pointrcnn/0000/{i:06d}.txt", dets)
    assert main(["convert", "synth", str(root), "--out", str(tmp_path / "bag")]) == 0
    back = list(read_frames(tmp_path / "bag"))
    assert [len(f.detections) for f in back] == [3, 3]


@pytest.mark.slow
def test_synthcars_output_converts(tmp_path):
    from pcc_ros.data import synthetic

    synthetic.generate(tmp_path / "synth", sequences=1, frames=2, seed=0)
    seq = KittiTracking(tmp_path / "synth").sequences()[0]
    assert main(["convert", "synth", str(tmp_path / "synth"), "--sequence", seq, "--out", str(tmp_path / "bag")]) == 0
    original = list(KittiTracking(tmp_path / "synth").frames(seq, tmp_path / "synth/detections/synthetic"))
    assert_same_frames(original, list(read_frames(tmp_path / "bag")))


def test_progress_and_source_metadata(shared_data, tmp_path):
    frames = list(KittiObject(shared_data / "kitti_object").frames(stop=1))
    summary = write_bag(frames, tmp_path / "bag", progress=False, source="unit test")
    assert summary.frames == 1 and summary.messages == {"/points": 1, "/ground_truth": 1}
    assert summarize(tmp_path / "bag")["custom_data"]["pcc_ros.source"] == "unit test"
    assert Path(summary.path) == tmp_path / "bag"


def test_mcap_decodes_with_independent_reader(shared_data, tmp_path):
    """The MCAP bag carries its schemas: mcap-ros2-support (the decoder Foxglove's own
    implementation mirrors) decodes every topic, vision_msgs included, from the file alone."""
    from mcap.reader import make_reader
    from mcap_ros2.decoder import DecoderFactory

    build_tables(shared_data, tmp_path / "nuscenes")
    original = list(NuScenes(tmp_path / "nuscenes").frames())
    write_bag(original, tmp_path / "bag", progress=False)
    seen: dict[str, int] = {}
    with (tmp_path / "bag" / "bag.mcap").open("rb") as stream:
        reader = make_reader(stream, decoder_factories=[DecoderFactory()])
        assert reader.get_header().profile == "ros2"
        for schema, channel, _, msg in reader.iter_decoded_messages():
            assert schema.encoding == "ros2msg" and channel.message_encoding == "cdr"
            seen[channel.topic] = seen.get(channel.topic, 0) + 1
            if channel.topic == "/points":
                assert msg.width == 34688 and [f.name for f in msg.fields] == ["x", "y", "z", "intensity", "ring"]
            elif channel.topic == "/ground_truth":
                assert len(msg.detections) == len(original[0].ground_truth)
                assert msg.detections[0].id == original[0].ground_truth.track_id[0]
            elif channel.topic == "/tf_static":
                assert msg.transforms[0].child_frame_id == "LIDAR_TOP"
    assert seen == {"/points": 2, "/ground_truth": 2, "/tf_static": 1, "/tf": 2}


def test_recorded_bag_late_detections_and_orphans(tmp_path, caplog):
    """A bag as ``ros2 bag record`` writes it: detections arrive later in bag time than their
    scan; they still join it by header stamp, and boxes whose scan never came are counted."""
    from rosbags.rosbag2 import StoragePlugin, Writer

    from pcc_ros.msg.detections import detection_array_from_boxes
    from pcc_ros.msg.pointcloud2 import create_cloud
    from pcc_ros.msg.typestore import get_typestore
    from pcc_ros.types import Boxes

    store = get_typestore()
    rng = np.random.default_rng(3)
    boxes = Boxes(rng.uniform(-5, 5, (2, 3)), [[4.0, 2.0, 1.5]] * 2, [0.1, -0.2], track_id=["7", "9"])
    clouds = [rng.normal(size=(50, 4)).astype(np.float32) for _ in range(3)]
    stamps = [1_000_000_000 + k * 100_000_000 for k in range(3)]
    with Writer(tmp_path / "rec", version=9, storage_plugin=StoragePlugin.MCAP) as writer:
        pc = writer.add_connection("/points", "sensor_msgs/msg/PointCloud2", typestore=store)
        det = writer.add_connection("/detections", "vision_msgs/msg/Detection3DArray", typestore=store)
        for k, stamp in enumerate(stamps):
            msg = create_cloud(clouds[k], ("x", "y", "z", "intensity"), "lidar", stamp)
            writer.write(pc, stamp + 5_000_000, store.serialize_cdr(msg, "sensor_msgs/msg/PointCloud2"))
            if k != 1:  # detector latency: 150 ms after the scan, i.e. after the next scan arrived
                msg = detection_array_from_boxes(boxes[: k + 1], "lidar", stamp)
                writer.write(det, stamp + 150_000_000, store.serialize_cdr(msg, "vision_msgs/msg/Detection3DArray"))
        orphan = detection_array_from_boxes(boxes, "lidar", 5_000_000_000)
        writer.write(det, 5_000_000_000, store.serialize_cdr(orphan, "vision_msgs/msg/Detection3DArray"))
    frames = list(read_frames(tmp_path / "rec"))
    assert [f.stamp_ns for f in frames] == stamps
    assert [f.index for f in frames] == [0, 1, 2] and frames[0].sequence == ""
    assert [None if f.detections is None else len(f.detections) for f in frames] == [1, None, 2]
    assert frames[2].detections.equals(boxes[:2])
    assert all(np.array_equal(f.points, c) for f, c in zip(frames, clouds))
    assert "1 stamps had boxes but no /points scan" in caplog.text
