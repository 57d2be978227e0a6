"""Summarise a ROS 2 bag: topics, types, counts, duration, frame ids, points per scan.

Reads every message of the PointCloud2, Detection3DArray and TFMessage topics (for frame
ids, point and box counts and the TF tree), so it takes about as long as reading the bag.
Storage damage (MCAP chunk CRC / compression, corrupt sqlite3) is an error naming the file
and offset; a message that does not deserialize is counted per topic (``undecodable``) and
reported, and the command then exits with status 1.
"""

from __future__ import annotations

import argparse
import logging
import struct
from collections import defaultdict
from pathlib import Path

import numpy as np
from mcap.reader import make_reader

from pcc_ros.data.bag import decode, iter_messages, open_bag
from pcc_ros.errors import PccError
from pcc_ros.files import write_json

log = logging.getLogger("pcc")

_INSPECTED = {
    "sensor_msgs/msg/PointCloud2",
    "vision_msgs/msg/Detection3DArray",
    "tf2_msgs/msg/TFMessage",
}


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("bag", type=Path, help="rosbag2 directory, .mcap or .db3")
    parser.add_argument("--json", type=Path, help="also write the summary as JSON")


def summarize(bag: str | Path) -> dict:
    """The summary as a JSON-able dict (what ``pcc info`` prints)."""
    path = Path(bag)
    reader = open_bag(path)
    try:
        storage = reader.readers[0].storage
        meta = storage.metadata
        topics: dict[str, dict] = {}
        for c in reader.connections:
            entry = topics.setdefault(c.topic, {"type": c.msgtype, "count": 0, "frame_ids": set()})
            entry["count"] += c.msgcount
        sizes: dict[str, list[int]] = defaultdict(list)
        tf_edges: set[tuple[str, str, str]] = set()
        inspected = [c for c in reader.connections if c.msgtype in _INSPECTED]
        for connection, time_ns, raw in iter_messages(reader, path, inspected):
            entry = topics[connection.topic]
            try:
                msg = decode(reader, raw, connection, time_ns, path)
                if connection.msgtype == "tf2_msgs/msg/TFMessage":
                    edges = [(str(t.header.frame_id), str(t.child_frame_id)) for t in msg.transforms]
                    size = None
                else:
                    edges = [(str(msg.header.frame_id), None)]
                    if connection.msgtype == "sensor_msgs/msg/PointCloud2":
                        size = int(msg.width) * int(msg.height)
                    else:
                        size = len(msg.detections)
            except (PccError, AttributeError, TypeError, ValueError) as exc:
                entry["undecodable"] = entry.get("undecodable", 0) + 1
                entry.setdefault("first_problem", str(exc))
                continue
            for parent, child in edges:
                entry["frame_ids"].add(parent)
                if child is not None:
                    tf_edges.add((connection.topic, parent, child))
            if size is not None:
                sizes[connection.topic].append(size)
        for topic, values in sizes.items():
            v = np.asarray(values)
            key = "points_per_scan" if topics[topic]["type"].endswith("PointCloud2") else "boxes_per_message"
            topics[topic][key] = {"min": int(v.min()), "mean": float(v.mean()), "max": int(v.max())}
        for entry in topics.values():
            entry["frame_ids"] = sorted(entry["frame_ids"])
        count = sum(t["count"] for t in topics.values())
        return {
            "path": str(path),
            "storage": path.suffix.lstrip(".") if path.is_file() else _storage_id(path),
            "compression": _compression(path, meta),
            "chunk_crcs": chunk_crcs(path),
            "messages": count,
            "start_ns": int(reader.start_time) if count else None,
            "duration_s": (reader.end_time - reader.start_time) / 1e9 if count else 0.0,
            "size_mb": sum(p.stat().st_size for p in ([path] if path.is_file() else path.iterdir())) / 1e6,
            "topics": topics,
            "tf": [{"topic": t, "parent": p, "child": c} for t, p, c in sorted(tf_edges)],
            "custom_data": dict(meta.custom or {}),
        }
    finally:
        reader.close()


def _compression(path: Path, meta) -> str:
    """rosbag2 file / message compression from the metadata, else the MCAP chunk compression."""
    if meta.compression_mode:
        return f"{meta.compression_mode} {meta.compression_format}"
    files = _mcap_files(path)
    if not files:
        return "none"

    with files[0].open("rb") as stream:
        summary = make_reader(stream).get_summary()
    kinds = {c.compression for c in summary.chunk_indexes} if summary else set()
    return "chunk " + ("/".join(sorted(k or "none" for k in kinds)) or "none")


def chunk_crcs(path: Path) -> str:
    """Whether the MCAP chunks carry CRCs (``all``, ``none``, ``N of M``), ``n/a`` for sqlite3.

    Without them a bit flip inside a chunk is undetectable (rosbags < 0.12 writes none;
    ``pcc convert`` and ``pcc replay`` fill them in)."""
    files = _mcap_files(path)
    if not files:
        return "n/a"
    with_crc = total = 0
    for file in files:
        with file.open("rb") as stream:
            summary = make_reader(stream).get_summary()
            for index in summary.chunk_indexes if summary else []:
                stream.seek(index.chunk_start_offset + 33)  # opcode, length, 3 x uint64, then the CRC
                with_crc += struct.unpack("<I", stream.read(4))[0] != 0
                total += 1
    return "all" if with_crc == total else "none" if with_crc == 0 else f"{with_crc} of {total}"


def _mcap_files(path: Path) -> list[Path]:
    """The MCAP files of a bag: the file itself, or those in the folder (whatever its name:
    ``ros2 bag record -o run.mcap`` makes a folder ``run.mcap/``)."""
    if path.is_dir():
        return sorted(path.glob("*.mcap"))
    return [path] if path.suffix == ".mcap" else []


def _storage_id(path: Path) -> str:
    return "mcap" if any(path.glob("*.mcap")) else "sqlite3" if any(path.glob("*.db3")) else "unknown"


def format_summary(s: dict) -> str:
    lines = [
        f"bag:         {s['path']}",
        f"storage:     {s['storage']} ({s['compression']}), {s['size_mb']:.1f} MB"
        + ("" if s.get("chunk_crcs", "n/a") == "n/a" else f", chunk CRCs: {s['chunk_crcs']}")
        + (" (bit flips inside chunks are undetectable)" if s.get("chunk_crcs") == "none" else ""),
        f"messages:    {s['messages']}",
        f"duration:    {s['duration_s']:.3f} s" + (f" from {s['start_ns'] / 1e9:.3f}" if s["start_ns"] else ""),
        "topics:",
    ]
    width = max((len(t) for t in s["topics"]), default=0)
    type_width = max((len(t["type"]) for t in s["topics"].values()), default=0)
    count_width = max((len(str(t["count"])) for t in s["topics"].values()), default=0)
    for name, t in sorted(s["topics"].items()):
        extra = ""
        if "points_per_scan" in t:
            p = t["points_per_scan"]
            extra = f"  points/scan {p['min']}..{p['max']} (mean {p['mean']:.0f})"
        elif "boxes_per_message" in t:
            b = t["boxes_per_message"]
            extra = f"  boxes/msg {b['min']}..{b['max']} (mean {b['mean']:.1f})"
        frames = ",".join(t["frame_ids"]) or "-"
        if t.get("undecodable"):
            extra += f"  UNDECODABLE {t['undecodable']}"
        lines.append(f"  {name.ljust(width)}  {t['type'].ljust(type_width)}  {str(t['count']).rjust(count_width)} msgs"
                     f"  frame {frames}{extra}")
    if s["tf"]:
        lines.append("tf:")
        lines.extend(f"  {e['topic']}: {e['parent']} -> {e['child']}" for e in s["tf"])
    return "\n".join(lines)


def run(args: argparse.Namespace) -> int:
    summary = summarize(args.bag)
    print(format_summary(summary))
    if args.json:
        write_json(args.json, summary, indent=2, sort_keys=True)
    bad = {name: t for name, t in summary["topics"].items() if t.get("undecodable")}
    for name, t in sorted(bad.items()):
        log.error("%s: %d undecodable %s message(s), first: %s", args.bag, t["undecodable"], name, t["first_problem"])
    return 1 if bad else 0
