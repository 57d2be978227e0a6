"""Fuzz corpus, bags: damaged MCAP / sqlite3 bags, wrong or unknown types, undecodable and
malformed messages through ``pcc info``, ``pcc replay``, ``pcc extract`` and ``read_frames``.

Every case ends in a named error (file, MCAP offset or topic) with no output left behind,
or in a counted skip whose message is left out of the outputs.
"""

from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np
import pytest
from conftest import assert_named_failure, assert_no_internal_error, run_cli
from fuzz_support import flip, small_frames
from hypothesis import HealthCheck, example, given, settings
from hypothesis import strategies as st
from rosbags.rosbag2 import Writer
from rosbags.rosbag2.enums import StoragePlugin
from rosbags.typesys import Stores, get_types_from_msg
from rosbags.typesys import get_typestore as rosbags_typestore

from pcc_ros.cli.info import summarize
from pcc_ros.data.bag import ReadStats, mcap_chunk_damage, open_bag, read_frames
from pcc_ros.data.bag_writer import write_bag
from pcc_ros.errors import BagError
from pcc_ros.msg.typestore import get_typestore
from pcc_ros.pipeline.core import Pipeline, PipelineConfig
from pcc_ros.runtime.bag_replay import replay_bag

POINTS, DETECTIONS = "sensor_msgs/msg/PointCloud2", "vision_msgs/msg/Detection3DArray"


@pytest.fixture(scope="module")
def frames():
    return small_frames(3)


@pytest.fixture(scope="module")
def bags(frames, tmp_path_factory):
    root = tmp_path_factory.mktemp("fuzz_bags")
    out = {}
    for storage in ("mcap", "sqlite3"):
        out[storage] = root / storage
        write_bag(frames, out[storage], storage=storage, compress=True, progress=False)
    return out


@pytest.fixture(scope="module")
def raw_messages(bags):
    """``topic -> [(time, raw bytes)]`` of the good MCAP bag."""
    reader = open_bag(bags["mcap"])
    out: dict[str, list] = {}
    try:
        for c, t, raw in reader.messages():
            out.setdefault(c.topic, []).append((t, bytes(raw)))
    finally:
        reader.close()
    return out


def write_raw_bag(out: Path, connections: list[tuple[str, str, object, list]], storage: str = "mcap") -> Path:
    """A bag of raw CDR records: ``(topic, msgtype, typestore, [(time, raw)])`` per connection."""
    plugin = StoragePlugin.MCAP if storage == "mcap" else StoragePlugin.SQLITE3
    writer = Writer(out, version=9, storage_plugin=plugin)
    writer.open()
    for topic, msgtype, store, messages in connections:
        conn = writer.add_connection(topic, msgtype, typestore=store)
        for t, raw in messages:
            writer.write(conn, t, raw)
    writer.close()
    return out


def _pipeline():
    return Pipeline(PipelineConfig(backend="mirror", min_points=10))


def _mcap(bag: Path) -> Path:
    return next(bag.glob("*.mcap"))


# ----------------------------------------------------------------------------- integrity


def test_our_mcap_bags_carry_chunk_crcs(bags):
    from mcap.reader import make_reader
    from mcap.stream_reader import StreamReader

    path = _mcap(bags["mcap"])
    with path.open("rb") as stream:
        summary = make_reader(stream).get_summary()
        crcs = []
        for index in summary.chunk_indexes:
            stream.seek(index.chunk_start_offset)
            crcs.append(next(iter(StreamReader(stream, skip_magic=True, emit_chunks=True).records)).uncompressed_crc)
    assert crcs and all(crcs)
    assert mcap_chunk_damage(path) is None
    assert summarize(bags["mcap"])["chunk_crcs"] == "all" and summarize(bags["sqlite3"])["chunk_crcs"] == "n/a"


@pytest.mark.parametrize("mask", [0x01, 0xFF])
def test_flip_inside_an_mcap_chunk_is_named_with_its_offset(bags, tmp_path, caplog, mask):
    bag = shutil.copytree(bags["mcap"], tmp_path / "bag")
    chunk = 43  # the first chunk follows the magic and header records
    damage = mcap_chunk_damage(_mcap(bag))
    assert damage is None
    flip(_mcap(bag), chunk + 200, mask)  # inside the compressed data of the first chunk
    where = f"{_mcap(bag)}@"
    rc, text = run_cli(["info", bag], caplog)
    assert_named_failure(rc, text, where)
    out = tmp_path / "replayed"
    rc, text = run_cli(["replay", bag, "--out", out, "--backend", "mirror"], caplog)
    assert_named_failure(rc, text, where, output=out)
    cache = tmp_path / "cache"
    rc, text = run_cli(["extract", bag, "--out", cache, "--no-progress"], caplog)
    assert_named_failure(rc, text, where, output=cache)


@settings(max_examples=25, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(position=st.floats(0.0, 1.0, exclude_max=True), mask=st.integers(1, 255))
@example(position=0.99694, mask=1)  # a damaged length field in the summary: rosbags asked for petabytes
@example(position=0.99582, mask=1)  # a damaged chunk index: rosbags skipped a chunk without any error
@example(position=0.99419, mask=128)  # a damaged index offset: OverflowError from a seek
def test_any_single_byte_flip_is_harmless_or_named(bags, frames, tmp_path_factory, position, mask):
    """A flip anywhere in the file: either the frames read back identical, or a named BagError."""
    bag = shutil.copytree(bags["mcap"], tmp_path_factory.mktemp("flip") / "bag")
    path = _mcap(bag)
    flip(path, int(position * path.stat().st_size), mask)
    try:
        back = list(read_frames(bag))
    except BagError as exc:
        assert str(bag) in str(exc)
        return
    assert len(back) == len(frames)
    for a, b in zip(frames, back):
        assert b.stamp_ns == a.stamp_ns
        assert np.array_equal(b.points, a.points)


def test_truncated_mcap_is_named(bags, tmp_path, caplog):
    bag = shutil.copytree(bags["mcap"], tmp_path / "bag")
    path = _mcap(bag)
    path.write_bytes(path.read_bytes()[: path.stat().st_size // 2])
    for args in (["info", bag], ["replay", bag, "--out", tmp_path / "o", "--backend", "mirror"]):
        rc, text = run_cli(args, caplog)
        assert_named_failure(rc, text, str(bag), output=tmp_path / "o")


def test_corrupt_sqlite_pages_are_named_with_the_database(bags, tmp_path, caplog):
    bag = shutil.copytree(bags["sqlite3"], tmp_path / "bag")
    db = next(bag.glob("*.db3"))
    data = bytearray(db.read_bytes())
    for offset in range(4096 * 2, len(data) - 4096, 4096 * 3):
        data[offset : offset + 32] = b"\xff" * 32
    db.write_bytes(bytes(data))
    rc, text = run_cli(["info", bag], caplog)
    assert_named_failure(rc, text, str(bag))
    out = tmp_path / "o"
    rc, text = run_cli(["replay", bag, "--out", out, "--backend", "mirror"], caplog)
    assert_named_failure(rc, text, str(bag), output=out)


# ----------------------------------------------------------------------------- types


def test_wrong_and_unknown_types_are_named(raw_messages, tmp_path, caplog):
    ts = get_typestore()
    string = bytes(ts.serialize_cdr(ts.types["std_msgs/msg/String"](data="x"), "std_msgs/msg/String"))
    dets = (DETECTIONS, raw_messages["/detections"])
    wrong = write_raw_bag(tmp_path / "wrong", [
        ("/points", "std_msgs/msg/String", ts, [(t, string) for t, _ in raw_messages["/points"]]),
        ("/detections", dets[0], ts, dets[1])])
    custom = rosbags_typestore(Stores.ROS2_JAZZY)
    custom.register(get_types_from_msg("int32 x", "foo_msgs/msg/Bar"))
    bar = bytes(custom.serialize_cdr(custom.types["foo_msgs/msg/Bar"](x=1), "foo_msgs/msg/Bar"))
    unknown_tf = write_raw_bag(tmp_path / "unknown_tf", [
        ("/points", POINTS, ts, raw_messages["/points"]), ("/detections", dets[0], ts, dets[1]),
        ("/tf", "foo_msgs/msg/Bar", custom, [(raw_messages["/points"][0][0], bar)])])
    for bag, topic in ((wrong, "/points has type std_msgs/msg/String"), (unknown_tf, "/tf has type foo_msgs/msg/Bar")):
        out = tmp_path / f"{bag.name}_out"
        rc, text = run_cli(["replay", bag, "--out", out, "--backend", "mirror"], caplog)
        assert_named_failure(rc, text, str(bag), topic, output=out)
        cache = tmp_path / f"{bag.name}_cache"
        rc, text = run_cli(["extract", bag, "--out", cache, "--no-progress"], caplog)
        assert_named_failure(rc, text, topic, output=cache)
        rc, text = run_cli(["info", bag], caplog)  # info lists any type
        assert rc == 0, text
    # an extra topic of a type pcc_ros does not know is listed and ignored
    extra = write_raw_bag(tmp_path / "extra", [
        ("/points", POINTS, ts, raw_messages["/points"]), ("/detections", dets[0], ts, dets[1]),
        ("/foo", "foo_msgs/msg/Bar", custom, [(raw_messages["/points"][0][0], bar)])])
    assert summarize(extra)["topics"]["/foo"]["type"] == "foo_msgs/msg/Bar"
    rc, text = run_cli(["replay", extra, "--out", tmp_path / "extra_out", "--backend", "mirror"], caplog)
    assert rc == 0, text


# ----------------------------------------------------------------------------- messages


def _bag_with_points(tmp_path: Path, raw_messages, points: list, name: str) -> Path:
    ts = get_typestore()
    return write_raw_bag(tmp_path / name, [("/points", POINTS, ts, points),
                                           ("/detections", DETECTIONS, ts, raw_messages["/detections"]),
                                           ("/ground_truth", DETECTIONS, ts, raw_messages["/ground_truth"])])


def test_undecodable_message_is_skipped_counted_and_left_out(raw_messages, tmp_path, caplog):
    points = list(raw_messages["/points"])
    points[1] = (points[1][0], points[1][1][:100])  # truncated CDR
    bag = _bag_with_points(tmp_path, raw_messages, points, "bad_cdr")
    rc, text = run_cli(["info", bag], caplog)  # info reports the damage and fails
    assert_named_failure(rc, text, "1 undecodable /points")
    out = tmp_path / "out"
    summary = replay_bag(bag, out, _pipeline(), progress=False)
    assert summary.undecodable == 1 and summary.frames == 2
    copied = summarize(out)
    assert copied["topics"]["/points"]["count"] == 2  # left out of the output, not copied raw
    assert copied["topics"]["/completed"]["count"] == 2
    assert "undecodable" not in copied["topics"]["/points"]
    stats = ReadStats()
    assert len(list(read_frames(bag, stats=stats))) == 2
    assert stats.undecodable["/points"] == 1


def test_all_undecodable_or_malformed_gives_no_output(raw_messages, tmp_path, caplog):
    ts = get_typestore()
    bad = [(t, raw[:100]) for t, raw in raw_messages["/points"]]
    malformed = []
    for t, raw in raw_messages["/points"]:
        msg = ts.deserialize_cdr(raw, POINTS)
        msg.row_step += 4  # decodable CDR, inconsistent PointCloud2
        malformed.append((t, bytes(ts.serialize_cdr(msg, POINTS))))
    for name, points, reason in (("undecodable", bad, "undecodable"), ("malformed", malformed, "malformed")):
        bag = _bag_with_points(tmp_path, raw_messages, points, name)
        out = tmp_path / f"{name}_out"
        rc, text = run_cli(["replay", bag, "--out", out, "--backend", "mirror"], caplog)
        assert_named_failure(rc, text, str(bag), reason, output=out)
        cache = tmp_path / f"{name}_cache"
        rc, text = run_cli(["extract", bag, "--out", cache, "--no-progress"], caplog)
        assert_named_failure(rc, text, str(bag), output=cache)


def test_unpairable_bag_leaves_no_output(raw_messages, tmp_path, caplog):
    ts = get_typestore()
    shifted = []
    for t, raw in raw_messages["/detections"]:
        msg = ts.deserialize_cdr(raw, DETECTIONS)
        msg.header.stamp.sec += 100
        shifted.append((t, bytes(ts.serialize_cdr(msg, DETECTIONS))))
    bag = write_raw_bag(tmp_path / "unpaired", [("/points", POINTS, ts, raw_messages["/points"]),
                                                ("/detections", DETECTIONS, ts, shifted)])
    out = tmp_path / "out"
    out_existing = tmp_path / "existing"
    out_existing.mkdir()
    (out_existing / "metadata.yaml").write_text("old bag\n")
    rc, text = run_cli(["replay", bag, "--out", out, "--backend", "mirror"], caplog)
    assert_named_failure(rc, text, str(bag), "no scan could be paired", output=out)
    rc, text = run_cli(["replay", bag, "--out", out_existing, "--backend", "mirror", "--force"], caplog)
    assert_named_failure(rc, text, str(bag), "no scan could be paired")
    assert (out_existing / "metadata.yaml").read_text() == "old bag\n"  # --force replaced nothing


def test_missing_bag_and_junk_are_named(tmp_path, caplog):
    (tmp_path / "junk.mcap").write_bytes(b"\x89MCAP0\r\n" + bytes(range(256)) * 4)
    (tmp_path / "junk.db3").write_bytes(b"SQLite format 3\x00" + b"\x00" * 200)
    for bag in (tmp_path / "missing", tmp_path / "junk.mcap", tmp_path / "junk.db3"):
        rc, text = run_cli(["info", bag], caplog)
        assert_named_failure(rc, text, str(bag))


@pytest.mark.slow  # 30 bags written and replayed: 12 s of test-fast (load 13 on 2 cores)
@settings(max_examples=30, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(data=st.binary(min_size=0, max_size=400), cut=st.integers(0, 400))
def test_random_cdr_payloads_never_crash_replay(raw_messages, tmp_path_factory, data, cut):
    """Random bytes (and random prefixes of a real message) as /points: skipped or named, never a crash."""
    tmp = tmp_path_factory.mktemp("cdr")
    real = raw_messages["/points"][0][1]
    points = [(raw_messages["/points"][0][0], data), (raw_messages["/points"][1][0], real[: cut * 50]),
              raw_messages["/points"][2]]
    bag = _bag_with_points(tmp, raw_messages, points, "bag")
    summary = replay_bag(bag, tmp / "out", _pipeline(), progress=False)
    assert summary.frames >= 1
    assert summary.frames + summary.undecodable + summary.skipped_frames + summary.unpaired_clouds == 3
    assert_no_internal_error(0, "")
