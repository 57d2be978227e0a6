"""Reading a SynthCars root: a track's complete shape and the vehicle family of each track.

Plain file readers (numpy, json) apart from the generator, so evaluation and extraction read a
dataset without importing the simulator's ray caster (open3d).
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from pcc_ros.errors import DataError


def load_shape(root: str | Path, sequence: str | int, track_id: str | int) -> np.ndarray | None:
    """The complete canonical surface of a track, or ``None`` when the dataset has none.

    Raises :class:`DataError` for a file that exists but is not a float (M, 3) array.
    """
    seq = f"{int(sequence):04d}" if str(sequence).isdigit() else str(sequence)
    path = Path(root) / "shapes" / seq / f"{int(track_id)}.npy"
    if not path.exists():
        return None
    try:
        array = np.load(path, allow_pickle=False)
    except (OSError, ValueError, EOFError) as exc:
        raise DataError(f"{path}: unreadable shape file ({exc})") from exc
    if array.ndim != 2 or array.shape[1] != 3 or not np.issubdtype(array.dtype, np.floating):
        raise DataError(f"{path}: expected a float (M, 3) array, got {array.dtype} {array.shape}")
    if not np.isfinite(array).all():
        raise DataError(f"{path}: non-finite coordinates")
    return array.astype(np.float32, copy=False)


def load_families(root: str | Path) -> dict[tuple[str, str], str]:
    """``(sequence, track id) -> vehicle family`` (``sedan``, ``van``, ...) of a SynthCars root,
    read from its ``meta.json`` (per-family evaluation); empty when the root has no meta.json or
    it records no tracks (a hand-made root with splits only).

    Raises :class:`DataError` for a meta.json that exists but cannot be read."""
    path = Path(root) / "meta.json"
    if not path.is_file():
        return {}
    try:
        sequences = json.loads(path.read_text()).get("sequences", {})
        return {(str(seq), str(track)): str(info["name"]) for seq, entry in sequences.items()
                for track, info in entry.get("tracks", {}).items()}
    except (OSError, ValueError, KeyError, TypeError, AttributeError) as exc:
        raise DataError(f"{path}: unreadable SynthCars meta.json ({exc})") from exc
