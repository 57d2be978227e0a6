"""Track-level completion: each car's recent observations, kept in its own box frame.

A car is seen over many frames, from a changing angle; completing each frame alone throws
away what the earlier frames saw. With ``track_memory`` on, the pipeline hands the completer
a car's *accumulated* partial cloud instead of the current crop alone: this frame's crop plus
the crops of the same car in the last ``track_max_age`` seconds, each stored in the box frame
of its own detection (box centre, x forward, y left, z up, in metres), so a car that moves,
or a sensor that moves, needs no ego poses: a rigid car sits at the same place in its own
box frame in every frame (the same reasoning as ``pcc_ros.data.track_aggregate``'s reference).

Only past frames are used (causal). Memory is bounded: at most :data:`MAX_TRACKS` tracks (the
least recently seen is dropped first), at most :data:`MAX_POINTS` stored points per track (the
oldest frames are dropped first, then a frame is thinned by a stride), and a track not seen
for ``max_age_s`` seconds is freed, so ids that vanish cost nothing after that. A scan stamp
earlier than the last one (a bag played again) clears the memory.

Which detections are the same car: the detection's id (``Detection3D.id``, a tracker's
track id) when it has one; otherwise the nearest remembered box centre (scan frame) within
``gate_m`` metres and not already taken this frame, assigned greedily from the closest pair,
among tracks that were themselves associated this way. The gate must cover how far a box
centre moves between two frames in the scan frame (the car's and the sensor's motion): 2 m
is 20 m/s of relative speed at 10 Hz. Ids are then "auto:N".
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from pcc_ros.types import Boxes

#: Tracks remembered at most (least recently seen dropped first).
MAX_TRACKS = 256
#: Stored points per track at most (oldest frames dropped first, then a frame thinned).
MAX_POINTS = 8192
#: Past frames per track at most.
MAX_FRAMES = 20


@dataclass
class _Track:
    centre: np.ndarray  # (3,) last box centre, scan frame (association without ids)
    last_ns: int
    frames: list[tuple[int, np.ndarray]] = field(default_factory=list)  # (stamp, (n, 3) box frame, metres)

    def points(self) -> int:
        return sum(len(p) for _, p in self.frames)


class TrackMemory:
    """Per-track past observations in the box frame; :meth:`update` once per frame, in stamp order."""

    def __init__(self, max_age_s: float = 1.0, gate_m: float = 2.0, max_tracks: int = MAX_TRACKS,
                 max_points: int = MAX_POINTS, max_frames: int = MAX_FRAMES) -> None:
        if max_age_s <= 0 or gate_m <= 0 or max_tracks < 1 or max_points < 1 or max_frames < 1:
            raise ValueError("track memory: max_age_s, gate_m, max_tracks, max_points and max_frames must be positive")
        self.max_age_ns = int(max_age_s * 1e9)
        self.gate_m = float(gate_m)
        self.max_tracks, self.max_points, self.max_frames = int(max_tracks), int(max_points), int(max_frames)
        self.tracks: dict[str, _Track] = {}
        self.last_ns: int | None = None
        self._next_auto = 0

    def __len__(self) -> int:
        return len(self.tracks)

    @property
    def stored_points(self) -> int:
        return sum(t.points() for t in self.tracks.values())

    def clear(self) -> None:
        self.tracks.clear()
        self.last_ns = None

    def update(self, boxes: Boxes, crops: list[np.ndarray], stamp_ns: int) -> list[np.ndarray]:
        """The accumulated canonical cloud of each box (this frame's crop first, then the same
        track's remembered points in this box's canonical frame), then remember this frame.

        ``boxes``: the completed detections (scan frame); ``crops``: their canonical crops, same
        order. Returns float32 clouds; a box without history gets its crop back unchanged."""
        if len(boxes) != len(crops):
            raise ValueError(f"track memory: {len(boxes)} boxes but {len(crops)} crops")
        stamp_ns = int(stamp_ns)
        if self.last_ns is not None and stamp_ns < self.last_ns:
            self.clear()  # time went backwards (a bag looped): nothing remembered is in the past any more
        self.last_ns = stamp_ns
        self._expire(stamp_ns)
        keys = self._associate(boxes)
        out = []
        for i, (key, crop) in enumerate(zip(keys, crops)):  # the completed boxes of one frame (tens)
            length = float(boxes.size[i, 0])
            crop = np.asarray(crop, dtype=np.float32).reshape(-1, 3)
            track = self.tracks.get(key)
            if track is not None and track.frames:
                past = np.concatenate([p for _, p in track.frames]) / length
                out.append(np.concatenate([crop, past.astype(np.float32)]))
            else:
                out.append(crop)
            if track is None:
                track = self.tracks[key] = _Track(np.asarray(boxes.center[i], dtype=np.float64), stamp_ns)
            track.centre, track.last_ns = np.asarray(boxes.center[i], dtype=np.float64), stamp_ns
            track.frames.append((stamp_ns, crop.astype(np.float32) * np.float32(length)))
            self._bound(track)
        self._evict()
        return out

    # ------------------------------------------------------------------ internals

    def _expire(self, stamp_ns: int) -> None:
        for key in [k for k, t in self.tracks.items() if stamp_ns - t.last_ns > self.max_age_ns]:
            del self.tracks[key]
        for track in self.tracks.values():  # frames older than the age limit leave a live track too
            track.frames = [(s, p) for s, p in track.frames if stamp_ns - s <= self.max_age_ns]

    def _bound(self, track: _Track) -> None:
        del track.frames[: max(0, len(track.frames) - self.max_frames)]
        while len(track.frames) > 1 and track.points() > self.max_points:
            track.frames.pop(0)
        if track.points() > self.max_points:  # one frame alone is over the cap: a regular stride
            stamp, pts = track.frames[0]
            step = int(np.ceil(len(pts) / self.max_points))
            track.frames[0] = (stamp, pts[::step])

    def _evict(self) -> None:
        if len(self.tracks) > self.max_tracks:
            order = sorted(self.tracks, key=lambda k: self.tracks[k].last_ns)
            for key in order[: len(self.tracks) - self.max_tracks]:
                del self.tracks[key]

    def _associate(self, boxes: Boxes) -> list[str]:
        """A track key per box: its id, else the nearest free auto track within the gate, else a new one."""
        ids = [str(t) for t in boxes.track_id]
        keys: list[str | None] = [f"id:{t}" if t else None for t in ids]
        free = np.flatnonzero([k is None for k in keys])
        if len(free):
            taken = set(keys)
            auto = [k for k in self.tracks if k.startswith("auto:") and k not in taken]
            if auto:
                centres = np.stack([self.tracks[k].centre for k in auto])
                d = np.linalg.norm(np.asarray(boxes.center[free])[:, None, :] - centres[None], axis=-1)
                pairs = np.argwhere(d <= self.gate_m)
                used_box, used_track = set(), set()
                for b, t in pairs[np.argsort(d[pairs[:, 0], pairs[:, 1]], kind="stable")]:  # greedy, closest first
                    if b not in used_box and t not in used_track:
                        keys[free[b]] = auto[t]
                        used_box.add(b)
                        used_track.add(t)
            for i in free:
                if keys[i] is None:
                    keys[i] = f"auto:{self._next_auto}"
                    self._next_auto += 1
        return [str(k) for k in keys]
