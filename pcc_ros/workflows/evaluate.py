"""Evaluate completion backends on the same instances of an instance cache (``pcc eval``).

Every backend (baselines included) completes exactly the same canonical partial clouds;
each completion is scored against a reference:

* ``ground_truth``: the SynthCars complete shape of the instance, when the cache has one
  for every selected instance;
* ``aggregated``: otherwise (real data), the multi-frame aggregate of the instance's track
  (all frames of the track registered in the canonical frame), the PointPnCNet KITTI
  protocol; TraPCC's ground-truth-free fidelity (L-I) and side-view CD (L-S) are the
  figures to read first then.

Metrics are computed in the canonical frame and converted to metres in the sensor frame
with each instance's box length (see ``pcc_ros/metrics/suite.py``); both are in the JSON,
and every printed table names its unit. Breakdowns: sensor distance bands (0-20, 20-40,
40+ m) and input point-count bands. The run is deterministic for a given ``--seed``.

Example::

    pcc eval --data cache/ --split test --backends input,densify,mirror,pointpncnet \\
        --checkpoint pointpncnet=runs/pnc.safetensors --json eval.json --plot eval.png
"""

from __future__ import annotations

import hashlib
import json
import logging
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from tqdm import tqdm

from pcc_ros import files
from pcc_ros.assignments import parse_assignments
from pcc_ros.data.gt_pools import PoolConfig, load_or_assign, load_or_build_pools
from pcc_ros.data.instance_cache import EvalShapes, InstanceCache
from pcc_ros.data.track_aggregate import aggregate_instances
from pcc_ros.errors import ConfigError, DataError
from pcc_ros.metrics import METRICS, instance_metrics, to_metres, unit_label
from pcc_ros.metrics.balance import track_consistency
from pcc_ros.models import backend_names, get_backend, load_completer
from pcc_ros.models.base import SceneContext
from pcc_ros.plotting import plot_examples
from pcc_ros.tables import metric_cell, print_table

log = logging.getLogger("pcc.eval")

DISTANCE_BANDS: tuple[tuple[str, float, float], ...] = (
    ("0-20m", 0.0, 20.0),
    ("20-40m", 20.0, 40.0),
    ("40m+", 40.0, np.inf),
)
POINT_BANDS: tuple[tuple[str, float, float], ...] = (
    ("<50pts", 0, 50),
    ("50-200pts", 50, 200),
    ("200-1000pts", 200, 1000),
    ("1000+pts", 1000, np.inf),
)
#: Metrics reported, in table order.
REPORTED = ("cd_l1", "cd_l2", "precision", "coverage", "fscore", "fscore_fixed", "emd", "fidelity", "side_cd",
            "l_g", "l_i", "l_s", "mean_cd", "far_coverage", "lateral_offset", "consistency")
#: Metrics of the per-family table (SynthCars: which vehicle shapes a backend completes well).
FAMILY_METRICS = ("cd_l1", "coverage", "far_coverage", "lateral_offset", "consistency")


@dataclass
class EvalInstance:
    """One instance as the evaluation sees it (canonical clouds, box length in metres)."""

    key: str
    partial: np.ndarray
    reference: np.ndarray
    length: float
    distance: float
    has_ground_truth: bool
    meta: dict[str, Any] = field(default_factory=dict)
    #: the other instances of the same frame (``SceneContext``), for backends that use them
    context: Any = None
    #: TraPCC's retrieved pseudo GT (``whole`` / ``front`` / ``back`` clouds) for L-G / L-S / meanCD
    pseudo_gt: dict[str, Any] | None = None
    #: box length, width, height in metres (``None``: unknown; backends then get no ``sizes``)
    size: np.ndarray | None = None

    @property
    def num_points(self) -> int:
        return len(self.partial)


# --------------------------------------------------------------------------- selection


def select_indices(n: int, max_instances: int | None, seed: int) -> np.ndarray:
    """Sorted seeded subset of ``range(n)`` (all when ``max_instances`` is None or >= n)."""
    if max_instances is None or max_instances >= n:
        return np.arange(n)
    if max_instances < 1:
        raise ConfigError(f"--max-instances must be >= 1, got {max_instances}")
    return np.sort(np.random.default_rng(seed).choice(n, max_instances, replace=False))


def instances_from_cache(
    cache: Any,
    split: str,
    max_instances: int | None,
    seed: int,
    reference: str = "auto",
    min_track_frames: int = 2,
    gt_free: bool = False,
) -> tuple[list[EvalInstance], str]:
    """Evaluation instances of an opened :class:`~pcc_ros.data.instance_cache.InstanceCache`.

    ``reference``: ``ground_truth`` uses the SynthCars shapes (``EvalShapes``, the only
    route to them) and keeps the instances that have one; ``aggregated`` uses the
    multi-frame aggregate of the instance's track, every observation of the track (this one
    included) concatenated in the common canonical frame of its boxes (``aggregate_instances``:
    no ego poses needed, moving cars included), keeping instances whose track
    has at least ``min_track_frames`` observations; ``auto`` = ``ground_truth`` when any
    instance of the split has a shape, else ``aggregated``. Skipped instances are logged
    with a count. ``max_instances`` then draws a seeded subset.

    Every instance carries its frame's :class:`~pcc_ros.models.base.SceneContext` (the
    other instances of the same frame in the cache), which context-using backends (TraPCC's
    scene graph) receive as they would online. ``gt_free``: also retrieve TraPCC's pseudo GT
    from the pools of the cache's ``train`` tracks (:mod:`pcc_ros.data.gt_pools`, cached
    under ``CACHE/trapcc_gt``) for L-G / L-S / meanCD.
    """
    if reference not in ("auto", "ground_truth", "aggregated"):
        raise ConfigError(f"--reference must be auto, ground_truth or aggregated, got {reference!r}")
    indices = cache.indices(split)
    meta = cache.meta
    if reference == "auto":
        reference = "ground_truth" if bool(np.any(meta["has_shape"][indices])) else "aggregated"
    keys = cache.track_keys()
    instances: list[EvalInstance] = []
    skipped = 0
    if reference == "ground_truth":
        shapes = EvalShapes.load(cache.root)
        usable = indices[meta["has_shape"][indices]]
        skipped += len(indices) - len(usable)
        usable = usable[select_indices(len(usable), max_instances, seed)]
        for i in usable:  # loop over instances: loading one shape each
            shape = shapes.for_instance(cache, int(i))
            if shape is None:
                skipped += 1
                continue
            instances.append(_eval_instance(cache, keys, int(i), np.asarray(shape, dtype=np.float32), True))
    else:
        tracks = cache.tracks(cache.indices(None))  # all observations of each track, any split
        usable = np.array(
            [i for i in indices if "/#" not in keys[i] and len(tracks.get(keys[i], ())) >= min_track_frames],
            dtype=np.int64,
        )
        skipped += len(indices) - len(usable)
        usable = usable[select_indices(len(usable), max_instances, seed)]
        aggregated: dict[str, np.ndarray] = {}
        for i in usable:
            key = str(keys[i])
            if key not in aggregated:  # one aggregate per track, shared by its observations
                aggregated[key] = aggregate_instances(cache, tracks[key])
            instances.append(_eval_instance(cache, keys, int(i), aggregated[key], False))
    if skipped:
        log.info("skipped %d instance(s) of split %r without a %s reference", skipped, split, reference)
    attach_families(cache, instances)
    attach_contexts(cache, instances)
    if gt_free:
        attach_pseudo_gt(cache, instances)
    return instances, reference


def attach_families(cache: Any, instances: Sequence[EvalInstance]) -> None:
    """Each instance's SynthCars vehicle family (``meta["family"]``), from the ``meta.json`` of the
    SynthCars root the cache was extracted from, for the per-family tables; nothing for other data."""
    root = (getattr(cache, "index", None) or {}).get("synthcars")
    if not root or not instances:
        return
    from pcc_ros.data.synthetic import load_families

    beside = Path(cache.root).parent / Path(root).name  # where it is when the two moved together
    families = load_families(root if Path(root).is_dir() or not beside.is_dir() else beside)
    if not families:
        log.warning("%s: the SynthCars root this cache was extracted from has no meta.json (moved?): no "
                    "per-family tables", root)
    for inst in instances:
        if name := families.get((inst.meta["sequence"], str(cache.meta["track"][inst.meta["index"]]))):
            inst.meta["family"] = name


def attach_contexts(cache: Any, instances: Sequence[EvalInstance]) -> None:
    """Give each instance the :class:`SceneContext` of its frame (all cache instances of that frame)."""
    if not instances:
        return
    wanted = {inst.meta["index"]: inst for inst in instances}
    all_boxes = cache.boxes
    for group in cache.frame_groups():  # loop over frames; only those holding an evaluated instance
        hits = [i for i in group if int(i) in wanted]
        if not hits:
            continue
        boxes = all_boxes[group]
        clouds = [cache.points(int(i)) for i in group]
        for row, i in enumerate(group):
            if int(i) in wanted:
                others = np.array([r for r in range(len(group)) if r != row], dtype=int)
                wanted[int(i)].context = SceneContext(boxes[np.array([row])], boxes[others],
                                                      [clouds[r] for r in others])


def attach_pseudo_gt(cache: Any, instances: Sequence[EvalInstance], pool_split: str = "train") -> None:
    """TraPCC's retrieved Whole- / Partial-GT of each instance (from the ``pool_split`` tracks)."""
    if not instances:
        return
    config = PoolConfig()
    pools, folder = load_or_build_pools([cache], pool_split, Path(cache.root) / "trapcc_gt", config, progress=False)
    if len(pools.whole) == 0:
        log.warning("no Whole-GT pool in the %r tracks of %s: L-G / L-S / meanCD not computed", pool_split, cache.root)
        return
    index = np.array([inst.meta["index"] for inst in instances], dtype=np.int64)
    found = load_or_assign(pools, folder, cache, index, "eval", config.size_candidates, progress=False)
    for r, inst in enumerate(instances):
        inst.pseudo_gt = {
            p: (pools.part(p).cloud(int(found[f"{p}_index"][r])) if found[f"{p}_index"][r] >= 0 else None)
            for p in ("whole", "front", "back")
        }


def _eval_instance(cache: Any, keys: np.ndarray, i: int, reference: np.ndarray, has_gt: bool) -> EvalInstance:
    meta = cache.meta
    return EvalInstance(
        key=f"{keys[i]}@{int(meta['frame'][i])}",
        partial=np.ascontiguousarray(cache.points(i), dtype=np.float32),
        reference=reference,
        length=float(meta["box_size"][i, 0]),
        distance=float(meta["distance"][i]),
        has_ground_truth=has_gt,
        meta={"index": i, "sequence": str(meta["sequence"][i]), "frame": int(meta["frame"][i]),
              "origin": np.asarray(meta["origin"][i], dtype=np.float64)},
        size=np.asarray(meta["box_size"][i], dtype=np.float64),
    )


def instance_sizes(instances: Sequence[EvalInstance]) -> np.ndarray | None:
    """``(B, 3)`` box sizes of ``instances`` for ``Completer.complete(sizes=...)``, or ``None``
    when any is unknown."""
    if not instances or any(inst.size is None for inst in instances):
        return None
    return np.stack([np.asarray(inst.size, dtype=np.float64) for inst in instances])


# --------------------------------------------------------------------------- scoring


def score_backend(
    completer: Any,
    instances: Sequence[EvalInstance],
    *,
    seed: int,
    chunk: int = 64,
    fixed_threshold_m: float = 0.05,
    emd_points: int = 1024,
    with_emd: bool = True,
    progress: bool = True,
    keep_input: bool = False,
) -> tuple[list[np.ndarray], list[dict[str, float]], float]:
    """Complete all instances with one backend and score each (canonical units).

    The boxes' sizes go with the clouds (a backend with a ``box_aspect`` uses them);
    ``keep_input`` scores the partial-preserving output (``Completer.complete(keep_input=True)``,
    what ``completion_node`` publishes) instead of the generated points alone.

    Returns the completions, one metric dict per instance, and the completion wall time.
    The EMD subsample seed depends on the instance index only, so every backend is
    compared against the same subsample of each reference.
    """
    name = getattr(completer, "name", type(completer).__name__)
    use_context = getattr(completer, "uses_context", False)
    completions: list[np.ndarray] = []
    seconds = 0.0
    with tqdm(total=len(instances), desc=f"complete {name}", unit="inst", disable=not progress, leave=False) as bar:
        for start in range(0, len(instances), chunk):
            part = instances[start : start + chunk]
            t0 = time.perf_counter()
            contexts = [inst.context for inst in part] if use_context else None
            completions.extend(completer.complete([inst.partial for inst in part], contexts,
                                                  sizes=instance_sizes(part), keep_input=keep_input))
            seconds += time.perf_counter() - t0
            bar.update(len(part))
    rows = []
    for i, (inst, out) in enumerate(
        tqdm(list(zip(instances, completions)), desc=f"score {name}", unit="inst", disable=not progress, leave=False)
    ):
        rows.append(
            instance_metrics(
                out,
                inst.reference,
                inst.partial,
                length=inst.length,
                fixed_threshold_m=fixed_threshold_m,
                with_emd=with_emd,
                emd_points=emd_points,
                seed=seed + i,
                pseudo_gt=inst.pseudo_gt,
                origin=inst.meta.get("origin"),
            )
        )
    steady = track_consistency([inst.key.rpartition("@")[0] for inst in instances],
                               [inst.meta.get("frame", 0) for inst in instances], completions)
    for row, value in zip(rows, steady):
        row["consistency"] = float(value)
    return completions, rows, seconds


def _mean_table(
    rows: Sequence[dict[str, float]], mask: np.ndarray, keys: Sequence[str]
) -> dict[str, float | int | None]:
    """Means over the masked rows; ``None`` (JSON null) for an empty band."""
    chosen = [r for r, m in zip(rows, mask) if m]
    out: dict[str, float | int | None] = {"count": len(chosen)}
    for key in keys:  # NaN-aware: a track's first frame has no consistency, a view from above no far half
        values = [r[key] for r in chosen if key in r and np.isfinite(r[key])]
        out[key] = float(np.mean(values)) if values else None
    return out


def summarise(instances: Sequence[EvalInstance], rows: Sequence[dict[str, float]]) -> dict[str, Any]:
    """Overall means and breakdowns, in metres (sensor frame) and canonical units."""
    keys = [k for k in REPORTED if rows and k in rows[0]]
    lengths = np.array([inst.length for inst in instances])
    metres = [{k: float(to_metres(k, r[k], length)) for k in keys} for r, length in zip(rows, lengths)]
    distance = np.array([inst.distance for inst in instances])
    points = np.array([inst.num_points for inst in instances])
    everything = np.ones(len(instances), dtype=bool)
    family = np.array([str(inst.meta.get("family", "")) for inst in instances])
    return {
        "by_family": {f: _mean_table(metres, family == f, keys) for f in sorted(set(family) - {""})},
        "overall": _mean_table(metres, everything, keys),
        "overall_canonical": _mean_table(rows, everything, keys),
        "by_distance": {
            label: _mean_table(metres, (distance >= lo) & (distance < hi), keys) for label, lo, hi in DISTANCE_BANDS
        },
        "by_points": {
            label: _mean_table(metres, (points >= lo) & (points < hi), keys) for label, lo, hi in POINT_BANDS
        },
    }


# --------------------------------------------------------------------------- output


def print_tables(results: dict[str, Any], reference: str) -> None:
    """One table per metric: backends x (overall, distance bands, point bands), in metres."""
    backends = results["backends"]
    if not backends:
        return
    first = next(iter(backends.values()))
    keys = [k for k in REPORTED if k in first["overall"]]
    columns = ["backend", "overall"] + [b[0] for b in DISTANCE_BANDS] + [b[0] for b in POINT_BANDS]
    for key in keys:
        rows = []
        for name, res in backends.items():
            row: dict[str, Any] = {"backend": name, "overall": res["overall"][key]}
            row.update({band: res["by_distance"][band][key] for band, _, _ in DISTANCE_BANDS})
            row.update({band: res["by_points"][band][key] for band, _, _ in POINT_BANDS})
            rows.append({k: metric_cell(v) for k, v in row.items()})
        better = "lower" if METRICS[key].lower_is_better else "higher"
        unit = unit_label(key, metres=True)
        unit_text = "dimensionless" if unit == "-" else f"{unit}, sensor frame"
        print_table(f"{key} [{unit_text}; {better} is better; reference: {reference}]", rows, columns)
    counts = {"backend": "instances", "overall": first["overall"]["count"]}
    counts.update({band: first["by_distance"][band]["count"] for band, _, _ in DISTANCE_BANDS})
    counts.update({band: first["by_points"][band]["count"] for band, _, _ in POINT_BANDS})
    print_table("instances per band", [counts], columns)
    families = sorted({f for res in backends.values() for f in res.get("by_family", {})})
    for key in (k for k in FAMILY_METRICS if k in keys and families):
        rows = [{"backend": name, **{f: metric_cell(res["by_family"][f][key]) for f in families if f in
                                     res.get("by_family", {})}} for name, res in backends.items()]
        print_table(f"{key} by vehicle family [{unit_label(key, metres=True)}; reference: {reference}; instances: "
                    + ", ".join(f"{f} {first['by_family'][f]['count']}" for f in families
                                if f in first.get("by_family", {})) + "]", rows, ["backend", *families])
    canon_rows = [
        {"backend": name,
         **{f"{k} [{unit_label(k, metres=False)}]": metric_cell(res["overall_canonical"][k]) for k in keys}}
        for name, res in backends.items()
    ]
    print_table("overall in canonical units (box length = 1)", canon_rows)


# --------------------------------------------------------------------------- command


def parse_checkpoints(items: Sequence[str]) -> dict[str, Path]:
    """``NAME=PATH`` pairs into a mapping."""
    return {name: Path(path) for name, path in parse_assignments(items, "--checkpoint", "NAME=PATH").items()}


def fingerprint(instances: Sequence[EvalInstance], settings: dict[str, Any]) -> str:
    """Hash of what a result depends on (instances, their point counts and families, settings).
    A re-run whose fingerprint matches the JSON already on disk reuses the backends finished
    there (resume after an interruption); a run that could not read the SynthCars families
    wrote no per-family tables, so one that reads them must not reuse it."""
    digest = hashlib.sha256(json.dumps(settings, sort_keys=True, default=str).encode())
    for inst in instances:
        digest.update(f"{inst.key}:{inst.num_points}:{len(inst.reference)}:{inst.length:.6f}:"
                      f"{inst.meta.get('family', '')};".encode())
    return digest.hexdigest()[:16]


def checkpoint_stamp(completer: Any) -> str | None:
    """What identifies the weights a learned backend runs with: the weights' sha256 and box aspect
    recorded in the checkpoint config it was loaded from (``None`` for a backend without weights)."""
    config = getattr(completer, "checkpoint_config", None)
    if config is None:
        return None
    aspect = config.get("box_aspect")
    return str(config.get("sha256")) + ("" if aspect is None else f":{json.dumps(aspect, sort_keys=True)}")


def evaluate(
    instances: Sequence[EvalInstance],
    reference: str,
    backends: Sequence[str],
    checkpoints: dict[str, Path] | None = None,
    *,
    device: str = "auto",
    batch_size: int = 32,
    seed: int = 0,
    fixed_threshold_m: float = 0.05,
    emd_points: int = 1024,
    with_emd: bool = True,
    progress: bool = True,
    previous: dict[str, Any] | None = None,
    keep: Sequence[int] = (),
    on_backend_done: Callable[[dict[str, Any]], None] | None = None,
    keep_input: bool = False,
    decode_density: int = 1,
) -> tuple[dict[str, Any], dict[str, dict[int, np.ndarray]]]:
    """Score every backend on ``instances``.

    Returns the results dict and, per backend, the completions of the instance indices in
    ``keep`` (for the example grid; all are scored, few are kept in memory). ``previous``:
    an earlier results dict; backends finished there under the same fingerprint are reused,
    only their ``keep`` completions are recomputed. ``on_backend_done(results)`` is called
    after each backend (the command writes the JSON there, so an interrupted run resumes).
    """
    checkpoints = dict(checkpoints or {})
    unused = sorted(set(checkpoints) - set(backends))
    if unused:
        raise ConfigError(f"--checkpoint given for backend(s) not evaluated: {unused}")
    settings = {
        "gt_free": any(inst.pseudo_gt is not None for inst in instances),
        "reference": reference,
        "seed": seed,
        "fixed_threshold_m": fixed_threshold_m,
        "emd_points": emd_points if with_emd else None,
        "keep_input": bool(keep_input),
        "decode_density": int(decode_density),
    }
    results: dict[str, Any] = {
        **settings,
        "instances": len(instances),
        "fingerprint": fingerprint(instances, settings),
        "units": {
            "overall": {k: unit_label(k, metres=True) for k in REPORTED},
            "overall_canonical": {k: unit_label(k, metres=False) for k in REPORTED},
            "note": "metres are sensor-frame distances; canonical units are fractions of the box length",
        },
        "definitions": {k: METRICS[k].description for k in REPORTED},
        "backends": {},
    }
    reusable = {}
    if previous and previous.get("fingerprint") == results["fingerprint"]:
        reusable = previous.get("backends", {})
    kept: dict[str, dict[int, np.ndarray]] = {}
    for name in backends:
        cls = get_backend(name)
        options = {"batch_size": batch_size, "decode_density": decode_density} if cls.learned else {}
        completer = load_completer(name, checkpoints.get(name), device=device, **options)
        stamp = checkpoint_stamp(completer) if cls.learned else None
        old = reusable.get(name)
        if old is not None and old.get("checkpoint_stamp") == stamp:
            log.info("%s: reusing the results already in the JSON (same instances and settings)", name)
            results["backends"][name] = old
            picks = list(keep)
            contexts = [instances[i].context for i in picks] if getattr(completer, "uses_context", False) else None
            chosen = [instances[i] for i in picks]
            outs = completer.complete([inst.partial for inst in chosen], contexts, sizes=instance_sizes(chosen),
                                      keep_input=keep_input) if picks else []
            kept[name] = dict(zip(picks, outs))
        else:
            completions, rows, seconds = score_backend(
                completer, instances, seed=seed, fixed_threshold_m=fixed_threshold_m,
                emd_points=emd_points, with_emd=with_emd, progress=progress, keep_input=keep_input,
            )
            summary = summarise(instances, rows)
            summary["completion_ms_per_instance"] = 1e3 * seconds / max(len(instances), 1)
            summary["output_points_mean"] = float(np.mean([len(c) for c in completions]))
            summary["checkpoint_stamp"] = stamp
            if cls.learned:
                ck = getattr(completer, "checkpoint_config", None) or {}
                summary["checkpoint"] = str(checkpoints.get(name, "default"))
                summary["checkpoint_git_revision"] = ck.get("git_revision")
            results["backends"][name] = summary
            kept[name] = {i: completions[i] for i in keep}
        if on_backend_done is not None:
            on_backend_done(results)
    return results, kept


def example_indices(instances: Sequence[EvalInstance], count: int) -> list[int]:
    """Instances for the example grid: evenly spread over the distance range."""
    if not instances or count < 1:
        return []
    order = np.argsort([inst.distance for inst in instances], kind="stable")
    count = min(count, len(instances))
    return [int(order[i]) for i in np.linspace(0, len(order) - 1, count).round().astype(int)]


def write_results(path: Path, results: dict[str, Any]) -> None:
    """An evaluation's results as JSON (``pcc eval``, ``pcc eval --real``): indented, NaN refused,
    numpy scalars as numbers; the folder made if needed, the file written atomically."""
    path.parent.mkdir(parents=True, exist_ok=True)
    files.write_json(path, results, indent=2, allow_nan=False, default=float)


def _previous_results(path: Path | None) -> dict[str, Any] | None:
    if path is None or not path.is_file():
        return None
    try:
        data = json.loads(path.read_text())
    except (OSError, json.JSONDecodeError):
        log.warning("%s exists but is not valid JSON; recomputing everything", path)
        return None
    return data if isinstance(data, dict) else None


@dataclass
class EvalConfig:
    """What ``pcc eval`` (on an instance cache) is told; the command builds it from its flags."""

    data: Path
    split: str = "test"
    backends: str | None = None  # comma-separated; None: the baselines input, densify, mirror
    checkpoints: dict[str, Path] = field(default_factory=dict)  # backend -> checkpoint (default: shipped)
    device: str = "auto"
    batch_size: int = 32
    json: Path | None = None
    plot: Path | None = None
    reference: str = "auto"  # auto | ground_truth | aggregated
    min_track_frames: int = 2
    max_instances: int | None = None
    seed: int = 0
    fixed_threshold: float = 0.05
    emd_points: int = 1024
    with_emd: bool = True
    examples: int = 4
    gt_free: bool = True
    resume: bool = True  # reuse --json's results for the same instances and settings
    keep_input: bool = False  # score the partial-preserving output (what completion_node publishes)
    decode_density: int = 1  # folding decoders decode this many times finer per grid axis


def evaluate_cache(opts: EvalConfig) -> tuple[dict[str, Any], str]:
    """Evaluate ``opts.backends`` on the instance cache; writes ``opts.json`` / ``opts.plot`` when
    given and returns the results and the kind of reference they were scored against."""
    backends = backend_names(opts.backends or "input,densify,mirror")  # checked before the cache loads
    if not opts.data.exists():
        raise DataError(f"{opts.data}: instance cache not found (write one with `pcc extract`)")
    instances, reference = instances_from_cache(
        InstanceCache.load(opts.data), opts.split, opts.max_instances, opts.seed, opts.reference,
        opts.min_track_frames, gt_free=opts.gt_free,
    )
    if not instances:
        raise DataError(f"{opts.data}: no usable instances in split {opts.split!r}")
    log.info("evaluating %d instance(s) of split %r against %s references", len(instances), opts.split, reference)
    picks = example_indices(instances, opts.examples) if opts.plot else []
    header = {"data": str(opts.data), "split": opts.split}

    def save(partial: dict[str, Any]) -> None:
        if opts.json:
            write_results(opts.json, {**header, **partial})

    results, kept = evaluate(
        instances, reference, backends, opts.checkpoints,
        device=opts.device, batch_size=opts.batch_size, seed=opts.seed,
        fixed_threshold_m=opts.fixed_threshold, emd_points=opts.emd_points, with_emd=opts.with_emd,
        previous=_previous_results(opts.json) if opts.resume else None, keep=picks, on_backend_done=save,
        keep_input=opts.keep_input, decode_density=opts.decode_density,
    )
    results = {**header, **results}
    if opts.plot:
        plot_examples(opts.plot, instances, kept, reference, picks)
        results["plot"] = {"path": str(opts.plot), "instances": [instances[i].key for i in picks]}
        log.info("wrote %s", opts.plot)
    if opts.json:
        write_results(opts.json, results)
        log.info("wrote %s", opts.json)
    return results, reference
