"""The detection filter: is there really a car in this box?

Two rules (``FilterConfig.rule``):

``evidence`` (default) — one calibrated probability that a detection is false, from terms
measured in the scan itself (documented with their derivation in ``docs/filter.md``):

* ``density``: log of (returns in the box + 1) / (returns a car there would give + 1), the
  expectation being the sensor model's beams that hit the box (its visible cross-section at
  that range and bearing), times the share of the scan's rays towards the box that are not
  stopped in front of it (occlusion);
* ``free_space``: log-odds of the rays through the box's solid core that return from
  *beyond* it (the box is see-through: empty) against those that end inside it;
* ``through``: the rays through the core returning from beyond it, as a share of the returns
  a car there would give (0 for a car and for a box without rays: it grows with the evidence);
* ``ground_gap``: metres the box bottom floats above the local ground (cars stand on it);
* ``score``: the detector score as a logit, after the explicit ``score_mapping``;
* ``mismatch``: TraPCC's shape mismatch (below) against the completion of ``filter_backend``
  (0 weight unless calibrated with a car-constrained backend);
* ``above``, ``fill``, ``spill``, ``overlap``: where the returns lie in and around the box
  (returns over its top, the share of its silhouette they cover, returns spilling out of its
  sides, its footprint covered by a higher-scored box): :mod:`pcc_ros.pipeline.evidence_profile`.

``p_false = sigmoid(w_bias + sum_k w_k * term_k [+ trees(terms)])``; a detection is rejected
when ``p_false > reject_threshold``. Weights, trees (``trees``: boosted from the weighted sum,
:mod:`pcc_ros.pipeline.trees`) and threshold come from ``pcc calibrate-filter`` (logistic
regression, then boosting; presets in ``config/``), never set by hand. Every box is judged —
a sparse box is exactly where false detections hide.

``trapcc`` — TraPCC (paper §4.5, §5.2): each detection is completed; the mismatch between
the raw crop and its completion is measured by

* MCD (TraPCC Eq. 2): the mean squared distance from each raw point to its nearest
  completed point (canonical units, i.e. fractions of the box length), and
* 2D contour differences in the side (x-z), front (y-z) and top (x-y) views: the
  fraction of the raw crop's occupied silhouette cells that the completion's (slightly
  dilated) silhouette does not cover, averaged over the three views,

folded into one score in [0, 1): ``1 - exp(-(mcd / mcd_scale + contour / contour_scale))``.
A detection is rejected when its mismatch score is above ``match_threshold`` AND its
(mapped) detection score is below ``detection_threshold`` (0.3 / 0.5 on KITTI in the paper).

Detector scores are not always probabilities (PointRCNN gives logits): ``score_mapping``
makes the conversion explicit.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from functools import lru_cache

import numpy as np

from pcc_ros.errors import ConfigError
from pcc_ros.msg.typestore import from_template, new_message
from pcc_ros.pipeline.beam_model import AUTO, sensor_for
from pcc_ros.pipeline.evidence import (  # noqa: F401  (re-exported: the filter's public names)
    CORE_FRACTION,
    CORE_Z,
    EVIDENCE_GROUND,
    EXPECTED_COLUMNS,
    GROUND_REACH,
    SENSOR_PRESETS,
    Evidence,
    SensorModel,
    beside,
    evidence,
    local_ground,
)
from pcc_ros.pipeline.evidence_profile import PROFILE_TERMS, profile_terms
from pcc_ros.pipeline.trees import TermTrees, load_trees, trees_path
from pcc_ros.types import Boxes

SCORE_MAPPINGS = ("identity", "sigmoid")
RULES = ("evidence", "trapcc")
_log = logging.getLogger(__name__)
_VIEWS = ((0, 2), (1, 2), (0, 1))  # side (x-z), front (y-z), top (x-y)


@dataclass(frozen=True)
class FilterConfig:
    rule: str = "evidence"
    # evidence rule: logistic weights. Defaults = the sensor- and detector-agnostic rule written by
    # `pcc calibrate-filter --sim-sensors ...` into config/detection_filter.yaml (a test keeps the
    # two equal; docs/filter.md has the command): scan evidence only, no score term (an unknown
    # detector's score scale is unknown; the score must not reject a real car on its own).
    w_bias: float = 15.0197
    w_density: float = -0.5067
    w_free_space: float = 0.3988
    w_ground_gap: float = 4.7354
    w_score: float = 0.0
    w_mismatch: float = 0.0
    # profile terms (pcc_ros.pipeline.evidence_profile): where the returns lie in and around the box
    w_above: float = 3.9407
    w_fill: float = 0.0
    w_spill: float = 0.0
    w_overlap: float = 10.0857
    w_depth: float = 7.4519
    w_top: float = 0.0
    w_corner: float = -1.0125  # share of the mid-height returns in the box's four corner columns
    w_through: float = 0.0  # rays through the core returning from beyond it / a car's returns there
    w_cover: float = -18.5557  # share of the box's unhidden azimuth columns holding a return
    # the value a missing mismatch term takes (a detection whose shape was not completed): its
    # mean over the calibration detections, the first-order marginalisation of the term
    mismatch_mean: float = 0.0
    reject_threshold: float = 0.7357
    # per-sensor reject thresholds, "hdl64:0.531, vlp16:0.458, ..." (pcc calibrate-filter
    # --sensor-thresholds): the entry of the preset the beam model matches; reject_threshold when
    # it matches none (an unknown sensor), before the first estimate, or when "" (none given)
    sensor_thresholds: str = ("hdl64:0.4863, hdl32:0.4373, vlp16:0.5158, vlp32c:0.4333, vlp32c_x2:0.7357, "
                              "os1_64:0.4346, os1_128:0.4947, pandar64:0.6418")
    # boosted trees added to the weighted sum's logit (pcc_ros.pipeline.trees): "shipped" (the file
    # in pcc_ros/weights, boosted from the default weights), a path, or "" (the weighted sum alone)
    trees: str = "shipped"
    sensor: str = AUTO  # the beam model: "auto" (estimated from the scans) or a name of SENSOR_PRESETS
    filter_backend: str = ""  # completion backend of the mismatch term; "" = the pipeline's own
    # trapcc rule
    match_threshold: float = 0.3
    detection_threshold: float = 0.5
    score_mapping: str = "identity"
    mcd_scale: float = 0.0025  # canonical units squared: (5 % of the car length)^2
    contour_scale: float = 0.5
    grid_cells: int = 24
    grid_extent: float = 0.75  # canonical half-extent of the silhouette grid

    def __post_init__(self) -> None:
        if self.score_mapping not in SCORE_MAPPINGS:
            raise ConfigError(f"score_mapping must be one of {SCORE_MAPPINGS}, got {self.score_mapping!r}")
        if self.rule not in RULES:
            raise ConfigError(f"rule must be one of {RULES}, got {self.rule!r}")
        if self.sensor != AUTO and self.sensor not in SENSOR_PRESETS:
            raise ConfigError(f"sensor must be {AUTO!r} or one of {sorted(SENSOR_PRESETS)}, got {self.sensor!r}")
        if not (self.mcd_scale > 0 and self.contour_scale > 0 and self.grid_cells > 1):
            raise ConfigError("mcd_scale, contour_scale must be > 0 and grid_cells > 1")
        if not 0.0 <= self.mismatch_mean <= 1.0:
            raise ConfigError(f"mismatch_mean must be in [0, 1], got {self.mismatch_mean}")
        if not 0.0 < self.reject_threshold < 1.0:
            raise ConfigError(f"reject_threshold must be in (0, 1), got {self.reject_threshold}")
        parse_sensor_thresholds(self.sensor_thresholds)  # refuse a malformed table now, not per frame
        # the trees read and checked once, here (a missing / corrupt file, or other weights', refused now),
        # and kept with this config: the frames judged under it read no file (not a dataclass field:
        # not a parameter, not compared; replace() makes a new config that reads them again)
        object.__setattr__(self, "_term_trees", self._load_trees())

    def threshold_for(self, preset: str | None) -> float:
        """The reject threshold for a beam model matching ``preset`` (None: no preset matched):
        its ``sensor_thresholds`` entry, else ``reject_threshold``."""
        if preset is None:
            return self.reject_threshold
        return parse_sensor_thresholds(self.sensor_thresholds).get(preset, self.reject_threshold)

    @property
    def weights(self) -> np.ndarray:
        """``(len(TERMS),)`` weights in :data:`TERMS` order."""
        return np.array([getattr(self, f"w_{t}") for t in TERMS], dtype=np.float64)

    @property
    def term_trees(self) -> TermTrees | None:
        """The boosted trees of ``trees``, as read when this config was made (None: the sum alone)."""
        return self.__dict__["_term_trees"]

    def _load_trees(self) -> TermTrees | None:
        """The trees of ``trees`` (a file read once per version), checked against these weights."""
        path = trees_path(self.trees)
        if path is None:
            return None
        trees = _read_trees(str(path), *_file_version(path))
        trees.check_linear({"w_bias": self.w_bias, **{f"w_{t}": w for t, w in zip(TERMS, self.weights)}},
                           f"trees {path}")
        return trees

    @property
    def weighted_terms(self) -> tuple[str, ...]:
        """The terms of :data:`TERMS` the evidence rule reads: a non-zero weight, or a tree's."""
        trees = self.term_trees
        in_trees = set(trees.terms) if trees is not None else set()
        return tuple(t for t, w in zip(TERMS, self.weights) if w != 0.0 or t in in_trees)

    @property
    def uses_mismatch(self) -> bool:
        return self.rule == "trapcc" or self.w_mismatch != 0.0


def _file_version(path) -> tuple[int, int]:
    """(mtime in ns, size) of ``path``: a rewritten file is read again."""
    try:
        st = path.stat()
    except OSError as exc:
        raise ConfigError(f"trees {path}: cannot read ({exc.strerror})") from None
    return st.st_mtime_ns, st.st_size


@lru_cache(maxsize=8)
def _read_trees(path: str, mtime_ns: int, size: int) -> TermTrees:
    return load_trees(path, TERMS)


def map_scores(scores: np.ndarray, mapping: str) -> np.ndarray:
    """Detector scores -> probabilities in [0, 1] (``identity`` or ``sigmoid`` of logits)."""
    scores = np.asarray(scores, dtype=np.float64)
    if mapping == "identity":
        return scores
    if mapping == "sigmoid":
        return 1.0 / (1.0 + np.exp(-scores))
    raise ConfigError(f"unknown score_mapping {mapping!r}")


def _stack(clouds: list[np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
    """All clouds in one array, with the instance index of each point."""
    sizes = np.array([len(c) for c in clouds], dtype=np.int64)
    points = np.concatenate(clouds).astype(np.float64) if sizes.sum() else np.zeros((0, 3))
    return points, np.repeat(np.arange(len(clouds)), sizes)


def _silhouettes(points: np.ndarray, owner: np.ndarray, n: int, view: tuple[int, int], config: FilterConfig):
    """``(n, cells, cells)`` occupancy of every instance's cloud in one 2D view."""
    cells, extent = config.grid_cells, config.grid_extent
    ij = np.clip(np.floor((points[:, list(view)] + extent) / (2 * extent) * cells).astype(np.int64), 0, cells - 1)
    flat = (owner * cells + ij[:, 0]) * cells + ij[:, 1]
    grid = np.zeros(n * cells * cells, dtype=bool)
    grid[flat] = True
    return grid.reshape(n, cells, cells)


def _dilate(grid: np.ndarray) -> np.ndarray:
    """3x3 dilation of a batch of ``(n, cells, cells)`` occupancy grids."""
    cells = grid.shape[1]
    padded = np.pad(grid, ((0, 0), (1, 1), (1, 1)))
    out = np.zeros_like(grid)
    for di in range(3):
        for dj in range(3):
            out |= padded[:, di : di + cells, dj : dj + cells]
    return out


def contour_differences(partials: list[np.ndarray], completions: list[np.ndarray], config: FilterConfig) -> np.ndarray:
    """Per instance, the mean over the side / front / top views of the share of the crop's
    occupied silhouette cells that the (dilated) completion silhouette misses. One pass for all."""
    n = len(partials)
    p_points, p_owner = _stack(partials)
    c_points, c_owner = _stack(completions)
    misses = np.zeros(n)
    for view in _VIEWS:
        theirs = _silhouettes(c_points, c_owner, n, view, config)
        covered = _dilate(theirs).reshape(-1)
        mine = _silhouettes(p_points, p_owner, n, view, config)
        occupied = np.flatnonzero(mine.reshape(-1))  # each occupied cell once
        owner = occupied // (config.grid_cells**2)
        missed = np.bincount(owner, weights=~covered[occupied], minlength=n)
        total = np.bincount(owner, minlength=n)
        misses += np.divide(missed, total, out=np.zeros(n), where=total > 0)
    return misses / len(_VIEWS)


def mcd(partials: list[np.ndarray], completions: list[np.ndarray]) -> np.ndarray:
    """TraPCC's MCD (Eq. 2) per instance: the mean *squared* distance from each crop point to
    its nearest completed point, canonical units. Pairs with an empty side get ``inf``."""
    out = np.full(len(partials), np.inf)
    ok = [k for k, (p, c) in enumerate(zip(partials, completions)) if len(p) and len(c)]
    if ok:
        # imported here: the metrics package pulls in scipy.spatial / scipy.optimize (about half a
        # second of a node's start-up), and only the shape-mismatch term needs it
        from pcc_ros.metrics.chamfer import nearest_distances_batch

        distances = nearest_distances_batch([partials[k] for k in ok], [completions[k] for k in ok])
        out[ok] = [float(np.mean(d**2)) for d in distances]
    return out


def mismatch_terms(partial: np.ndarray, completion: np.ndarray, config: FilterConfig) -> tuple[float, float]:
    """(MCD, contour difference) of one canonical crop and its canonical completion (diagnostics)."""
    return float(mcd([partial], [completion])[0]), float(contour_differences([partial], [completion], config)[0])


def mismatch_scores(
    partials: list[np.ndarray], completions: list[np.ndarray], config: FilterConfig
) -> np.ndarray:
    """Mismatch score in [0, 1] for each (crop, completion) pair, both canonical (batched)."""
    if not partials:
        return np.zeros(0)
    terms = mcd(partials, completions) / config.mcd_scale  # inf where a side is empty: score 1
    terms += contour_differences(partials, completions, config) / config.contour_scale
    return 1.0 - np.exp(-terms)


def reject_mask(mismatch: np.ndarray, detection_scores: np.ndarray, config: FilterConfig) -> np.ndarray:
    """True where a detection is rejected: shape mismatch high AND detection score low.

    A detection with no mismatch score (NaN: too few points to judge) is kept — absence
    of evidence is not a reason to drop a detection.
    """
    probability = map_scores(detection_scores, config.score_mapping)
    mismatch = np.asarray(mismatch, dtype=np.float64)
    judged = np.isfinite(mismatch)
    return judged & (np.where(judged, mismatch, 0.0) > config.match_threshold) & (
        probability < config.detection_threshold
    )


def parse_named_values(text: str, param: str, form: str, example: str, low: float = 0.0, high: float = 1.0,
                       open_interval: bool = False, names=None) -> dict[str, float]:
    """``"A:0.6, B:0.3"`` -> ``{"A": 0.6, "B": 0.3}`` (``""`` -> ``{}``): a map in one string, as a
    ROS 2 parameter can carry it (parameters cannot be maps). ``names``: the allowed names (None: any).

    Raises :class:`ConfigError` naming ``param`` and the bad entry (no colon, not a number, outside
    [``low``, ``high``] (open with ``open_interval``), a name not among ``names``)."""
    out: dict[str, float] = {}
    interval = f"({low:g}, {high:g})" if open_interval else f"[{low:g}, {high:g}]"
    for entry in str(text).split(","):
        entry = entry.strip()
        if not entry:
            continue
        name, sep, value = entry.rpartition(":")
        name = name.strip()
        try:
            number = float(value)
        except ValueError:
            number = float("nan")
        inside = low < number < high if open_interval else low <= number <= high
        if not sep or not name or not inside:
            raise ConfigError(f"{param}: bad entry {entry!r}; expected {form!r} with a threshold in {interval}, "
                              f"entries separated by commas (e.g. {example!r})")
        if names is not None and name not in names:
            raise ConfigError(f"{param}: bad entry {entry!r}; unknown name {name!r} (have {', '.join(sorted(names))})")
        out[name] = number
    return out


@lru_cache(maxsize=64)
def parse_sensor_thresholds(text: str) -> dict[str, float]:
    """``sensor_thresholds``: ``"hdl64:0.531, vlp16:0.458"`` -> per beam-layout preset, its reject
    threshold in (0, 1); a name must be one of :data:`SENSOR_PRESETS` (cached: read every frame;
    do not modify the returned map)."""
    return parse_named_values(text, "sensor_thresholds", "sensor:threshold", "hdl64:0.53, vlp16:0.46",
                              open_interval=True, names=SENSOR_PRESETS)


def format_sensor_thresholds(table: dict[str, float]) -> str:
    """The ``sensor_thresholds`` string of a table (4 decimals, the order given)."""
    return ", ".join(f"{name}:{value:.4f}" for name, value in table.items())


# ============================================================================ physics evidence

#: The evidence terms, in the order of the logistic weights (:attr:`FilterConfig.weights`).
TERMS = ("density", "free_space", "ground_gap", "score", "mismatch", *PROFILE_TERMS, "through", "cover")

#: The term weights of the evidence rule: one calibrated whole (:func:`whole_rule`).
RULE_WEIGHTS = tuple(f"w_{t}" for t in TERMS)


def whole_rule(given) -> dict[str, float | str]:
    """The parts of the evidence rule a parameter set leaves out, when it names others.

    A calibrated rule is a whole: its weights were fitted together, and a term it never saw
    must not join it with the shipped rule's weight (a file written before a term existed
    would otherwise get that term, fitted beside other weights, added on top of its own rule).
    So a parameter set (a file and the overrides on it) that names any ``w_<term>`` gives
    every term it does not name weight 0, said in one INFO line; one that names none keeps the
    shipped rule whole. The per-layout thresholds belong to the weights they were set for: a
    set that names weights or a ``reject_threshold`` but no ``sensor_thresholds`` has none
    (its own threshold judges every sensor; a KITTI preset must not inherit the shipped rule's
    table). ``w_bias``, ``reject_threshold`` and ``mismatch_mean`` keep their defaults when
    missing (a file of an older rule has them too). A parameter changed on a running node
    changes that parameter only (the rest of its rule stays)."""
    named = [w for w in RULE_WEIGHTS if w in given]
    missing = [w for w in RULE_WEIGHTS if w not in given]
    left_out: dict[str, float | str] = {}
    if (named or "reject_threshold" in given) and "sensor_thresholds" not in given:
        _log.info("the parameters name their own filter rule but no sensor_thresholds: its reject_threshold "
                  "judges every sensor")
        left_out["sensor_thresholds"] = ""
    if named and "trees" not in given:
        left_out["trees"] = ""  # trees were boosted from the weights they came with, not these
    if named and missing:
        _log.info("the parameters name the filter weights %s but not %s: those are 0 (a calibrated rule is a "
                  "whole; pcc calibrate-filter writes every weight)", ", ".join(named), ", ".join(missing))
        left_out.update(dict.fromkeys(missing, 0.0))
    return left_out


# The measurements themselves (rays, expected returns, local ground) live in
# pcc_ros.pipeline.evidence; imported above and re-exported here.


def score_logit(scores: np.ndarray, mapping: str) -> np.ndarray:
    """The detector score as a logit: raw for ``sigmoid`` (already a logit), ``logit(p)`` for
    probabilities (clipped to [1e-4, 1 - 1e-4])."""
    scores = np.asarray(scores, dtype=np.float64)
    if mapping == "sigmoid":
        return scores
    p = np.clip(map_scores(scores, mapping), 1e-4, 1 - 1e-4)
    return np.log(p / (1 - p))


def term_matrix(terms: dict[str, np.ndarray], mismatch_fill: float = 0.0) -> np.ndarray:
    """``(N, len(TERMS))`` feature matrix. A missing mismatch (NaN: the shape was not completed,
    e.g. past ``max_instances`` or under ``min_points``) reads ``mismatch_fill`` (the rule's
    ``mismatch_mean``: the term marginalised to first order, so the other terms judge alone
    with the population's average shape evidence); any other missing term reads 0."""
    n = len(next(iter(terms.values())))
    cols = [np.nan_to_num(np.asarray(terms.get(t, np.zeros(n)), dtype=np.float64),
                          nan=mismatch_fill if t == "mismatch" else 0.0) for t in TERMS]
    return np.stack(cols, axis=1)


def rule_logit(x: np.ndarray, bias: float, weights: np.ndarray, trees: TermTrees | None) -> np.ndarray:
    """``w_bias + x @ w + trees(x)`` of a term matrix ``x (N, len(TERMS))`` (:func:`term_matrix`)."""
    z = bias + x @ weights
    if trees is not None:
        z = z + trees.margin(x[:, [TERMS.index(t) for t in trees.terms]])
    return z


def rule_probability(x: np.ndarray, config: FilterConfig) -> np.ndarray:
    """``sigmoid(`` :func:`rule_logit` ``)`` under ``config``'s weights and trees: the calibrated
    probability that each detection is false."""
    return 1.0 / (1.0 + np.exp(-rule_logit(x, config.w_bias, config.weights, config.term_trees)))


def false_probability(terms: dict[str, np.ndarray], config: FilterConfig) -> np.ndarray:
    """:func:`rule_probability` of measured terms (a missing mismatch term marginalised:
    :func:`term_matrix`)."""
    return rule_probability(term_matrix(terms, config.mismatch_mean), config)


#: The raw measurements of :func:`evidence`, each with the pass that makes them (its flag).
_EVIDENCE_KEYS = {"n_in": "rays", "n_stop": "rays", "n_pass": "rays", "n_occluded": "rays", "n_rays": "rays",
                  "expected": "expected", "ground_z": "ground"}


def filter_terms(
    points: np.ndarray, boxes: Boxes, config: FilterConfig, mismatch: np.ndarray | None = None, workers: int = 1,
    sensor: SensorModel | None = None, rings: np.ndarray | None = None, weighted_only: bool = False,
) -> dict[str, np.ndarray]:
    """Every term of the evidence rule for ``boxes`` in ``points`` (plus the raw counts);
    ``workers``: CPU threads measuring them (two or more: :func:`evidence`'s split, the footprint
    queries, the local ground and the profile pass, on a second thread beside the rays). ``sensor``: the beam model (a
    pipeline passes its :class:`~pcc_ros.pipeline.beam_model.BeamModel`'s); without one, the
    configured preset, or for ``sensor: auto`` this scan's own estimate (``rings``: its ring
    field, when it has one).

    ``weighted_only``: measure only the terms :attr:`FilterConfig.weighted_terms` names (the
    others are absent from the result, which :func:`term_matrix` reads as 0: the probability
    is the same, since their weight is 0), and the raw counts those need; a pass none of them
    needs (the rays, the expected returns, the local ground, the profile pass) is not run.
    Calibration and the evaluation tools measure every term (the default)."""
    sensor = sensor or sensor_for(config.sensor, points, rings)
    wanted = set(config.weighted_terms) if weighted_only else set(TERMS)
    rays = bool(wanted & {"density", "free_space", "through", "cover"})
    out: dict[str, np.ndarray] = {}
    measured = {"rays": rays, "expected": bool(wanted & {"density", "through"}), "ground": "ground_gap" in wanted}
    profile = wanted & set(PROFILE_TERMS)
    if any(measured.values()):
        # one call: the profile pass shares the local ground's index of the scan, and with two
        # threads both run on the second beside the rays (evidence's split)
        ev = evidence(points, boxes, sensor, workers=workers, columns="cover" in wanted, profile=profile, **measured)
        keep = {k for k, needs in _EVIDENCE_KEYS.items() if measured[needs]} | (wanted & set(ev.terms)) \
            | ({"n_filled", "n_seen"} & set(ev.terms))
        out = {k: v for k, v in ev.as_dict().items() if k in keep}
        out.update(ev.profile)
    elif profile:
        out.update(profile_terms(points, boxes, sensor, measure=profile))
    if "score" in wanted:
        out["score"] = score_logit(boxes.score, config.score_mapping)
    if "mismatch" in wanted or mismatch is not None:
        out["mismatch"] = np.full(len(boxes), np.nan) if mismatch is None else np.asarray(mismatch, dtype=np.float64)
    return out


# ============================================================================ visible decisions

#: class_id of the extra hypothesis carrying the filter's probability that a detection is false.
SCORE_CLASS_ID = "pcc_filter_score"
#: class_id prefix of the hypotheses carrying the terms behind it (``pcc_filter/density`` ...).
TERM_CLASS_PREFIX = "pcc_filter/"
#: class_id of the marker hypothesis (score 1.0) of a detection of a filtered class the filter
#: could not judge (a box failing the checks, e.g. NaN; a scan without a finite point; the
#: trapcc rule without a completion): published on ``detections_filtered``, counted as
#: ``detections_unjudged`` on /diagnostics.
UNJUDGED_CLASS_ID = "pcc_filter_unjudged"


def decision_texts(result) -> list[str] | None:
    """RViz text per detection: ``"Car 8.30 | p_false 0.02 kept"`` (evidence rule) or
    ``"Car 0.40 | mismatch 0.71 rejected"`` (trapcc rule); None when nothing was judged."""
    n = len(result.detections)
    if not n:
        return None
    score = result.filter_score if result.filter_score is not None else np.full(n, np.nan)
    out = []
    for i in range(n):  # one label per box
        head = f"{result.detections.label[i]} {result.detections.score[i]:.2f}"
        if np.isfinite(score[i]):
            out.append(f"{head} | p_false {score[i]:.2f} {result.status[i]}")
        elif np.isfinite(result.mismatch[i]):
            out.append(f"{head} | mismatch {result.mismatch[i]:.2f} {result.status[i]}")
        else:
            out.append(f"{head} | {result.status[i]}")
    return out


def annotate_detections(detections: list, result, index: np.ndarray, classes=None) -> list:
    """Copies of ``detections`` (``vision_msgs/Detection3D``, detection ``index[k]`` of
    ``result``) with the filter's decision appended to ``results``: one
    ``ObjectHypothesisWithPose`` ``class_id="pcc_filter_score"``, score = probability that the
    detection is false, then one ``pcc_filter/<term>`` per finite term (score = the term's
    value), all with the box pose. The detector's own hypotheses come first, untouched."""
    if (result.filter_score is None and not np.isfinite(result.mismatch).any()
            and not (result.status == "unjudged").any()):
        return list(detections)
    # Hypotheses are copies of one template (typestore.from_template: 11 us per hypothesis
    # constructed, about 3 us copied); a detection's filter hypotheses share one pose message,
    # the box pose.
    template = new_message("vision_msgs/msg/ObjectHypothesisWithPose", classes)
    out = []
    for det, i in zip(detections, index):  # a few dozen detections per frame
        values: list[tuple[str, float]] = []
        score = np.nan if result.filter_score is None else result.filter_score[i]
        if np.isfinite(score):
            values.append((SCORE_CLASS_ID, float(score)))
        for term in TERMS:
            v = result.filter_terms.get(term)
            if v is not None and np.isfinite(v[i]):
                values.append((TERM_CLASS_PREFIX + term, float(v[i])))
        if np.isfinite(result.mismatch[i]) and not any(k.endswith("/mismatch") for k, _ in values):
            values.append((TERM_CLASS_PREFIX + "mismatch", float(result.mismatch[i])))
        if result.status[i] == "unjudged":
            values.append((UNJUDGED_CLASS_ID, 1.0))
        pose = new_message("geometry_msgs/msg/PoseWithCovariance", classes, pose=det.bbox.center,
                           covariance=np.zeros(36, dtype=np.float64))
        extra = [from_template(template, pose=pose, hypothesis=new_message(
            "vision_msgs/msg/ObjectHypothesis", classes, class_id=k, score=v)) for k, v in values]
        out.append(from_template(det, results=[*det.results, *extra]))  # header, box and id as received
    return out


def mark_unjudged(detections: list, classes=None) -> list:
    """Copies of ``detections`` (``vision_msgs/Detection3D``) with the :data:`UNJUDGED_CLASS_ID`
    marker hypothesis appended (pose = the box pose as received)."""
    template = new_message("vision_msgs/msg/ObjectHypothesisWithPose", classes)
    out = []
    for det in detections:
        pose = new_message("geometry_msgs/msg/PoseWithCovariance", classes, pose=det.bbox.center,
                           covariance=np.zeros(36, dtype=np.float64))
        marker = from_template(template, pose=pose, hypothesis=new_message(
            "vision_msgs/msg/ObjectHypothesis", classes, class_id=UNJUDGED_CLASS_ID, score=1.0))
        out.append(from_template(det, results=[*det.results, marker]))
    return out


#: The decisions of a frame: judged (kept, rejected), not judged although of a filtered class
#: (unjudged, published with the marker), not the filter's business (skipped: another class).
DECISIONS = ("kept", "rejected", "unjudged", "skipped")


def decision_counts(status: np.ndarray, unjudged_extra: int = 0) -> dict[str, int]:
    """Counts of one frame's statuses per :data:`DECISIONS` (for /diagnostics);
    ``unjudged_extra``: detections dropped before the pipeline (boxes failing the checks)."""
    status = np.asarray(status, dtype=object)
    counts = {k: int((status == k).sum()) for k in DECISIONS}
    counts["unjudged"] += int(unjudged_extra)
    return counts
