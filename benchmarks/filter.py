"""The evidence filter's measurements per frame against those of main at 93cd59e, interleaved.

The filter's scan-side work (:func:`pcc_ros.pipeline.filter.evidence`: the rays towards every box and
their free-space / occlusion counts, the sensor model's expected returns, the local ground
under each box) on the frames of ``pcc bench pipeline`` (a SynthCars scan resized to
``--points``, cars 1 / 5 / 20 / 50 / 100) and on a real KITTI scan (its labelled boxes, then
car-sized boxes on random returns, as ``pcc bench crop``), against the same function as it
was at 93cd59e (``benchmarks._reference.evidence``), timed call by call, interleaved, after
a warm-up (min / median / max of ``--repeat`` calls each), ours also with ``workers=2`` (the
ground and the expected returns on a second thread, as the pipeline runs it with ``workers`` >= 2).
Every output (raw counts, expected returns, ground heights, the derived terms), of both thread
settings, is checked bit-identical first, with 93cd59e's fixed ground reach on both sides
(``reach=GROUND_REACH``: the timed comparison) and with the reach the pipeline uses (the beam
model's, :func:`pcc_ros.pipeline.evidence.ground_reach`) on both sides. The profile terms
(:func:`pcc_ros.pipeline.evidence_profile.profile_terms`, newer than 93cd59e) are timed beside
them (``profile_ms``), and the rays with the azimuth columns of ``cover`` (``cover_ms``: the
other outputs checked unchanged by them). Last of the interleaved calls, the whole measurement of the filter
(:func:`pcc_ros.pipeline.filter.filter_terms`, one thread) of every term (``all_terms_ms``:
calibration's) and of only those the shipped rule weighs (``rule_terms_ms``: ``weighted_only``,
the pipeline's; a term of weight 0 and a pass only it needs are skipped; the profile pass then
shares the local ground's index of the scan). The machine's load
average is recorded before and after. Last, the thread grain: the same numpy work on one thread
and split over two (a pool thread beside the calling one), interleaved, in calls of the filter's
grain (250 ``np.multiply`` of 50k doubles per half, about 15 us each) and in large calls (3
``np.sort`` of 100k doubles per half): whether two Python threads issuing such calls run in
parallel on this machine (``workers=2`` can gain only if the small calls do). The filter's share
of the completion stage (target <= 25 % at 20 cars, issue #19) is measured by ``pcc bench pipeline``.
"""

from __future__ import annotations

import argparse
import os

import numpy as np

from benchmarks.common import interleaved, load_average, print_table, summary_ms


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--cars", default="1,5,20,50,100", help="car counts of the SynthCars frames")
    parser.add_argument("--points", type=int, default=120_000, help="points of the SynthCars frames (default 120000)")
    parser.add_argument("--kitti-boxes", default="5,30", help="box counts on the real KITTI scan ('' = none)")
    parser.add_argument("--repeat", type=int, default=30, help="timed calls of each (interleaved)")
    parser.add_argument("--grain-repeat", type=int, default=40, help="timed calls of the thread-grain check (0: skip)")


def _frames(args: argparse.Namespace):
    from benchmarks.crop import DEFAULT_SCAN, box_set, load_scan
    from benchmarks.pipeline import base_frame, frame_messages
    from pcc_ros.msg.detections import decode_detection_array
    from pcc_ros.msg.pointcloud2 import read_xyz

    base = base_frame(args.seed)
    for cars in [int(c) for c in args.cars.split(",") if c.strip()]:
        cloud, dets = frame_messages(base, cars, args.points, args.seed)[:2]
        yield "synthcars", read_xyz(cloud), decode_detection_array(dets, skip_invalid=True)[0]
    counts = [int(c) for c in args.kitti_boxes.split(",") if c.strip()]
    if counts:
        points, labelled = load_scan(DEFAULT_SCAN, 0)
        rng = np.random.default_rng(args.seed)
        for n in counts:
            yield "kitti 0000/0", points[:, :3], box_set(points, labelled, n, rng)


def check_equal(ours: dict[str, np.ndarray], theirs: dict[str, np.ndarray], reference: str = "the 93cd59e reference"
                ) -> None:
    """Every measurement and term bit-identical (NaN where NaN); raises SystemExit otherwise."""
    for key in theirs:
        if not np.array_equal(ours[key], theirs[key], equal_nan=True):
            worst = float(np.nanmax(np.abs(ours[key] - theirs[key])))
            raise SystemExit(f"evidence differs from {reference} in {key!r} (max |diff| {worst:.3g})")


def thread_grain(repeat: int) -> list[dict]:
    """Milliseconds of the same numpy work on one thread and split over two, in small calls (the
    filter's grain) and in large ones, interleaved (min / median)."""
    from concurrent.futures import ThreadPoolExecutor

    rng = np.random.default_rng(0)
    small = [[rng.normal(size=50_000) for _ in range(3)] for _ in range(2)]
    large = [rng.normal(size=100_000) for _ in range(2)]

    def many_small(arrays):  # 250 calls of about 15 us
        a, b, out = arrays
        for _ in range(250):
            np.multiply(a, b, out=out)

    def few_large(values):  # 3 calls of a few ms (np.sort copies)
        for _ in range(3):
            np.sort(values)

    rows = []
    with ThreadPoolExecutor(max_workers=1) as pool:
        for grain, fn, halves in (("250 calls of ~15 us", many_small, small), ("3 calls of ~3 ms", few_large, large)):
            def one_thread(fn=fn, halves=halves):
                fn(halves[0])
                fn(halves[1])

            def two_threads(fn=fn, halves=halves):
                other = pool.submit(fn, halves[1])
                fn(halves[0])
                other.result()

            times = interleaved({"one": one_thread, "two": two_threads}, repeat=repeat, warmup=2)
            one, two = summary_ms(times["one"]), summary_ms(times["two"])
            rows.append({"grain": grain, "one_min": one["min_ms"], "one_ms": one["median_ms"],
                         "two_min": two["min_ms"], "two_ms": two["median_ms"],
                         "gain_min": one["min_ms"] / two["min_ms"]})
    return rows


def run(args: argparse.Namespace) -> dict:
    from benchmarks._reference import evidence as reference_evidence
    from benchmarks._reference_profile import profile_terms as reference_profile
    from pcc_ros.pipeline.evidence_profile import PROFILE_TERMS, profile_terms
    from pcc_ros.pipeline.filter import GROUND_REACH, SENSOR_PRESETS, FilterConfig, evidence, filter_terms

    load_before = load_average()
    sensor = SENSOR_PRESETS["hdl64"]
    fixed = GROUND_REACH  # 93cd59e's ground reach: the outputs compared bit for bit
    rule = FilterConfig(sensor="hdl64")  # the shipped rule
    rule_profile = set(rule.weighted_terms) & set(PROFILE_TERMS)

    def rule_terms_24858c5(points, boxes):
        """filter_terms(weighted_only=True, workers=2) as at 24858c5: the evidence on two threads
        (what the shipped rule weighs: rays, expected returns, ground), then its profile pass."""
        evidence(points, boxes, sensor, workers=2)
        return reference_profile(points, boxes, sensor, measure=rule_profile)
    rows = []
    for scan, points, boxes in _frames(args):
        check_equal(evidence(points, boxes, sensor).as_dict(), reference_evidence(points, boxes, sensor).as_dict())
        reference = reference_evidence(points, boxes, sensor, reach=fixed).as_dict()
        check_equal(evidence(points, boxes, sensor, reach=fixed).as_dict(), reference)
        check_equal(evidence(points, boxes, sensor, workers=2, reach=fixed).as_dict(), reference)
        with_columns = evidence(points, boxes, sensor, reach=fixed, columns=True).as_dict()
        check_equal({k: with_columns[k] for k in reference}, reference, "the rays with the azimuth columns")
        check_equal(filter_terms(points, boxes, rule, sensor=sensor, weighted_only=True, workers=2),
                    filter_terms(points, boxes, rule, sensor=sensor, weighted_only=True), "one thread's filter_terms")
        for measure in (None, rule_profile):  # every profile term, and those the shipped rule weighs
            check_equal(profile_terms(points, boxes, sensor, measure=measure),
                        reference_profile(points, boxes, sensor, measure=measure), "24858c5's profile pass")
        times = interleaved({"ours": lambda p=points, b=boxes: evidence(p, b, sensor, reach=fixed),
                             "ours_2": lambda p=points, b=boxes: evidence(p, b, sensor, workers=2, reach=fixed),
                             "ours_beams": lambda p=points, b=boxes: evidence(p, b, sensor),
                             "ours_cover": lambda p=points, b=boxes: evidence(p, b, sensor, reach=fixed, columns=True),
                             "profile": lambda p=points, b=boxes: profile_terms(p, b, sensor),
                             "profile_rule": lambda p=points, b=boxes: profile_terms(p, b, sensor,
                                                                                     measure=rule_profile),
                             "profile_24858c5": lambda p=points, b=boxes: reference_profile(p, b, sensor,
                                                                                             measure=rule_profile),
                             "93cd59e": lambda p=points, b=boxes: reference_evidence(p, b, sensor, reach=fixed),
                             "terms_all": lambda p=points, b=boxes: filter_terms(p, b, rule, sensor=sensor),
                             "terms_rule": lambda p=points, b=boxes: filter_terms(p, b, rule, sensor=sensor,
                                                                                  weighted_only=True),
                             "terms_rule_2": lambda p=points, b=boxes: filter_terms(p, b, rule, sensor=sensor,
                                                                                    weighted_only=True, workers=2),
                             "terms_rule_24858c5_2": lambda p=points, b=boxes: rule_terms_24858c5(p, b)},
                            repeat=args.repeat, warmup=3)
        ours, two, ref = (summary_ms(times[k]) for k in ("ours", "ours_2", "93cd59e"))
        beams, profile = summary_ms(times["ours_beams"]), summary_ms(times["profile"])
        profile_rule, profile_before = summary_ms(times["profile_rule"]), summary_ms(times["profile_24858c5"])
        every, weighted = summary_ms(times["terms_all"]), summary_ms(times["terms_rule"])
        rows.append({"scan": scan, "points": len(points), "boxes": len(boxes),
                     "ours_min": ours["min_ms"], "ours_ms": ours["median_ms"], "ours_max": ours["max_ms"],
                     "ours2_min": two["min_ms"], "ours2_ms": two["median_ms"], "beams_ms": beams["median_ms"],
                     "cover_ms": summary_ms(times["ours_cover"])["median_ms"],
                     "profile_ms": profile["median_ms"], "profile_rule_ms": profile_rule["median_ms"],
                     "profile_24858c5_ms": profile_before["median_ms"], "all_terms_ms": every["median_ms"],
                     "rule_terms_ms": weighted["median_ms"],
                     "rule_terms_2_ms": summary_ms(times["terms_rule_2"])["median_ms"],
                     "rule_terms_24858c5_2_ms": summary_ms(times["terms_rule_24858c5_2"])["median_ms"],
                     "ref_min": ref["min_ms"], "ref_ms": ref["median_ms"], "ref_max": ref["max_ms"],
                     "speedup": ref["median_ms"] / ours["median_ms"], "outputs": "identical"})
    print_table(f"evidence filter measurements, ms ({args.repeat} interleaved calls each: min / median / max); "
                "ours = one thread, ours2 = workers 2 (ground and expected returns on a second thread, as the "
                "pipeline's workers >= 2), both with 93cd59e's fixed ground reach; beams = one thread, the ground "
                "reach the pipeline uses (widened with the beam model's ring spacing); cover = ours with the "
                "azimuth columns of the cover term (the rays' pass marking each box's columns); profile = the "
                "profile terms (above, fill, spill, overlap, depth, top: one more pass, no 93cd59e counterpart, "
                "not compared), "
                "which the pipeline adds to beams; profile_rule = those the shipped rule weighs, profile_24858c5 = "
                "the same by the profile pass of 24858c5 (pair arrays first; outputs checked identical); ref = main "
                "at 93cd59e; all_terms = every term of the rule "
                "(filter_terms, one thread: calibration's measurement), rule_terms = only those the shipped rule "
                "weighs (weighted_only: what the pipeline measures), rule_terms_2 = the same on two threads (the "
                "ground and the profile pass, over one index of the scan, on the second beside the rays, as the "
                "pipeline's workers >= 2; outputs checked identical), "
                "rule_terms_24858c5_2 = the same work as 24858c5 did it (the evidence on two threads, then its "
                "profile pass)", rows)
    grain = thread_grain(args.grain_repeat) if args.grain_repeat > 0 else []
    if grain:
        print_table(f"thread grain: the same numpy work on one thread and split over two, ms ({args.grain_repeat} "
                    "interleaved calls each: min / median; gain = one / two, minima)", grain)
    load_after = load_average()
    print(f"load average (1 min) before / after: {load_before[0]:.2f} / {load_after[0]:.2f} on {os.cpu_count()} cores")
    return {"rows": rows, "thread_grain": grain, "cpu_count": os.cpu_count(), "load_average_before": load_before,
            "load_average_after": load_after}
