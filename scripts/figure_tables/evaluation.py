"""docs/evaluation.md's completion figures: ``pcc eval --real --json`` on the shared KITTI frames (labelled
boxes, detector boxes, track memory) and ``pcc eval --data --json`` on a SynthCars cache (vehicle families)."""

from __future__ import annotations

from typing import Any

from .base import Figure, one, pct, table

#: Row order of the real-data tables: baselines, then each learned backend with its generated points alone.
ORDER = ("input", "mirror", "densify", "pointpncnet", "pointpncnet/generated", "trapcc", "trapcc/generated", "aml",
         "aml/generated", "aml_ml", "aml_ml/generated", "aggregated GT")
LEARNED = ("pointpncnet", "trapcc", "aml", "aml_ml")


def _rows(d: dict[str, Any]) -> list[tuple[str, dict[str, Any]]]:
    """``(name, result)`` of every backend row of a real-data run, in :data:`ORDER` (unknown ones last)."""
    backends = d["backends"]
    return [(n, backends[n]) for n in ORDER if n in backends] + [
        (n, r) for n, r in backends.items() if n not in ORDER]


def _m(value: float | None, digits: int = 3) -> str:
    return "-" if value is None else f"{value:.{digits}f}"


def render_real(d: dict[str, Any]) -> list[str]:
    """Overall means per backend (metres): how close the completion comes to the multi-view reference,
    how far its points stray, where they sit in the box."""
    columns = ("completeness", "fidelity", "fidelity_generated", "spacing", "side_cd", "inside_box", "bottom_gap",
               "top_gap", "lateral_offset")
    rows = []
    for name, r in _rows(d):
        o = r["overall"]
        label = f"**{name}** (published)" if name in LEARNED else name
        rows.append([label, *(_m(o.get(c), 4 if c == "side_cd" else 3) for c in columns),
                     f"{o['points']:.0f} ({o['points_min']:.0f}-{o['points_max']:.0f})"])
    header = ["backend (metres; completeness, fidelity: lower is better)", *columns, "points (min-max)"]
    return [*table(header, rows), "", *_closing(d)]


def _closing(d: dict[str, Any]) -> list[str]:
    """The run's bars per learned backend, as its closing lines print them."""
    lines = []
    for name, c in d["criteria"].items():
        lines.append(f"- {name}: completeness {pct(c['completeness_gain_vs_mirror'])} below mirror (bar 40 %: "
                     f"{'met' if c['completeness_ok'] else 'not met'}); generated points alone "
                     f"{pct(c['generated_gain_vs_mirror'])} (bar 40 %: {'met' if c['generated_ok'] else 'not met'}); "
                     "lateral "
                     f"balance {c['lateral_balance']:.3f} m (bar 0.1 m: {'met' if c['balance_ok'] else 'not met'}); "
                     f"generated points {c['fidelity_generated_over_spacing']:.2f}x the input spacing (bar 2x: "
                     f"{'met' if c['fidelity_ok'] else 'not met'})")
    return lines


def _lower_bound(band: str) -> float:
    """A band's lower edge, for ordering ``<50pts``, ``50-200pts``, ``1000+pts`` and ``0-20m``."""
    if band.startswith("<"):
        return -1.0
    digits = "".join(c for c in band.split("-")[0] if c.isdigit() or c == ".")
    return float(digits or 0)


def render_bands(d: dict[str, Any]) -> list[str]:
    """Completeness (metres, lower is better) overall and per distance and input-point band."""
    first = next(iter(d["backends"].values()))
    bands = [(group, b) for group in ("by_distance", "by_points") for b in sorted(first[group], key=_lower_bound)
             if first[group][b]["count"]]
    rows = [[name, _m(r["overall"]["completeness"]), *(_m(r[group].get(band, {}).get("completeness"))
                                                       for group, band in bands)]
            for name, r in _rows(d) if name != "aggregated GT"]
    counts = ", ".join(f"{band} {first[group][band]['count']}" for group, band in bands)
    return [f"Instances per band: {counts} ({d['instances']} in all; boxes: {d['boxes']}).", "",
            *table(["backend (completeness, m; lower is better)", "overall", *(band for _, band in bands)], rows)]


def render_bands_with_bars(d: dict[str, Any]) -> list[str]:
    """:func:`render_bands` and the run's bars."""
    return [*render_bands(d), "", *_closing(d)]


def render_summary(d: dict[str, Any]) -> list[str]:
    """The real-data summary: the far side, the symmetric reference, the balance and consistency."""
    rows = [[s["backend"], _m(s["completeness"]), _m(s["completeness_sym"]),
             f"{_m(s['generated_completeness'])} ({pct(s['generated_gain_vs_mirror'])})", _m(s["far_completeness"]),
             _m(s["far_completeness_sym"]), _m(s["lateral_balance"]), _m(s["consistency"])]
            for s in sorted(d["summary"], key=lambda s: ORDER.index(s["backend"]) if s["backend"] in ORDER else 99)]
    header = ["backend (metres, lower is better)", "completeness", "completeness, symmetric ref.",
              "generated-only completeness (below mirror)", "unseen half, generated",
              "unseen half, generated, symmetric ref.", "lateral balance, generated", "consistency, generated"]
    pairs = {s["consistency_pairs"] for s in d["summary"]}
    return [*table(header, rows), "", f"{d['instances']} observations; consistency over "
            f"{' / '.join(str(p) for p in sorted(pairs))} consecutive-frame pairs."]


FAMILY_TABLES = (("cd_l1", "CD-L1 by family"), ("lateral_offset", "lateral balance by family"),
                 ("far_coverage", "unseen half's coverage by family"))


def render_families(d: dict[str, Any]) -> list[str]:
    """Per vehicle family and backend (metres, lower is better): CD-L1, lateral balance, the unseen half."""
    names = sorted(d["backends"], key=lambda n: ORDER.index(n) if n in ORDER else len(ORDER))
    by_family = {backend: d["backends"][backend]["by_family"] for backend in names}
    first = next(iter(by_family.values()))
    families = sorted(first)
    if not families:  # the run could not read the SynthCars root's families: every table would be empty
        raise ValueError(f"{d['data']}: the stored run holds no per-family rows (pcc eval found no SynthCars "
                         "meta.json for the cache); rerun it from the repository root")
    out = [f"{d['instances']} test instances of `{d['data']}`, reference `{d['reference']}`"
           + (", the generated points alone" if not d.get("keep_input") else "") + ".", ""]
    for key, title in FAMILY_TABLES:
        rows = [[backend, *(_m(fam[f].get(key)) for f in families)] for backend, fam in by_family.items()]
        if key == "cd_l1":
            rows.insert(0, ["instances", *(str(first[f]["count"]) for f in families)])
        out += [*table([f"{title} (m, lower is better)", *families], rows), ""]
    overall = {n: d["backends"][n]["overall"] for n in names}
    out.append("Overall (m): " + "; ".join(
        f"{n} CD-L1 {_m(o.get('cd_l1'))}, unseen half {_m(o.get('far_coverage'))}, consistency "
        f"{_m(o.get('consistency'))}" for n, o in overall.items()) + ".")
    return out


def render_labels_against_detections(results: dict[str, dict[str, Any]]) -> list[str]:
    """docs/aml.md: published completeness with the labelled boxes and with the detector's, each against
    mirror on the same observations."""
    labels, detections = results["eval-real"], results["eval-real-detections"]

    def cells(d: dict[str, Any], name: str) -> list[str]:
        row, mirror = d["backends"].get(name), d["backends"]["mirror"]["overall"]["completeness"]
        if row is None:
            return ["-", ""]
        value = row["overall"]["completeness"]
        return [_m(value), "" if name == "mirror" else f"{100 * (value / mirror - 1):+.0f} %"]

    names = ("mirror", "pointpncnet", "trapcc", "aml", "aml/generated")
    rows = [[f"{n} (published)" if n in LEARNED else n, *cells(labels, n), *cells(detections, n)] for n in names]
    header = ["completeness (m, lower is better)", f"labelled boxes ({labels['instances']} obs.)", "vs mirror",
              f"detector boxes ({detections['instances']} matched obs.)", "vs mirror"]
    return table(header, rows)


def render_synthcars_test(d: dict[str, Any]) -> list[str]:
    """docs/aml.md: the SynthCars test split against the true shapes, the paper's accuracy / completeness."""
    names = sorted(d["backends"], key=lambda n: ORDER.index(n) if n in ORDER else len(ORDER))
    rows = []
    for n in names:
        r = d["backends"][n]
        o = r["overall"]
        rows.append([f"**{n}**" if n == "aml" else n, _m(o["cd_l1"], 4), _m(o["precision"]), _m(o["coverage"]),
                     _m(o["fscore"]), f"{r['completion_ms_per_instance']:.3g}"])
    header = ["backend (metres, lower is better; F-score higher)", "CD-L1", "accuracy (`precision`)",
              "completeness (`coverage`)", "F-score@1 %", "ms per car (this run)"]
    return [f"{d['instances']} test instances of `{d['data']}`, reference `{d['reference']}`.", "",
            *table(header, rows)]


def render_aml_against_ml(d: dict[str, Any]) -> list[str]:
    """docs/aml.md: AML against its maximum-likelihood baseline on the same instances, and the speed ratio."""
    aml, ml = d["backends"]["aml"], d["backends"]["aml_ml"]
    speed = ml["completion_ms_per_instance"] / aml["completion_ms_per_instance"]
    return [*render_synthcars_test(d), "",
            f"AML is {speed:.0f}x faster than the ML baseline here ({aml['completion_ms_per_instance']:.3g} against "
            f"{ml['completion_ms_per_instance']:.4g} ms per car)."]


FIGURES: dict[str, Figure] = {
    "eval-real": one("eval-real", render_real),
    "eval-real-bands": one("eval-real", render_bands),
    "eval-real-summary": one("eval-real-summary", render_summary),
    "eval-real-track-memory": one("eval-real-track-memory", render_summary),
    "eval-real-mirror": one("eval-real-mirror", render_summary),
    "eval-real-detections": one("eval-real-detections", render_bands_with_bars),
    "eval-real-matched-labels": one("eval-real-matched-labels", render_bands),
    "eval-families": one("eval-families", render_families),
    "eval-synthcars-test": one("eval-synthcars-test", render_synthcars_test),
    "eval-aml-vs-ml": one("eval-aml-vs-ml", render_aml_against_ml),
    "eval-real-labels-vs-detections": Figure(("eval-real", "eval-real-detections"), render_labels_against_detections),
}
