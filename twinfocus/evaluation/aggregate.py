"""Aggregation of the evaluation's raw records: means and standard errors over the error draws per
condition and method, gains over no correction as ratios of paired means (the paper's +23.3 % =
0.74 / 0.60 - 1), the rows of the limits sweeps and where a method stops helping, the trade study's
means over scenes and its Pareto front. Plain functions over the records' dicts; no files, no
figures."""

from __future__ import annotations

import math

import numpy as np

#: The compared methods in the order the report lists them, and their names in its tables and figures.
METHOD_ORDER = ("none", "sharpness", "digital", "physical")
METHOD_NAMES = {
    "none": "no correction",
    "sharpness": "sharpness autofocus",
    "digital": "digital twin",
    "physical": "physical twin",
}
#: A method "stops helping" where its mean SSIM gain over no correction falls below this.
HELP_THRESHOLD = 0.01


def ok_records(records):
    """The records that ran and have an SSIM."""
    return [r for r in records if r.get("status", "ok") == "ok" and r.get("ssim") is not None]


def _draw_key(r) -> tuple:
    return (r["condition"], r["pair"], r["draw"])


def mean_sd(values: np.ndarray) -> tuple[float | None, float | None]:
    """(mean, standard deviation with ddof 0) of ``values``; None for the mean of none and the sd
    of fewer than two."""
    v = np.asarray(values, float)
    return (float(v.mean()) if v.size else None, float(v.std()) if v.size > 1 else None)


def method_stats(records: list[dict], condition: str) -> dict:
    """{method: {n, mean, sd, sem, hog, failed, improvement_pct, gain}} for one condition (sd: the
    samples' standard deviation, ddof 0; sem: the mean's standard error).

    improvement_pct = mean(method) / mean(none) - 1 over the draws where both ran (paired), in %;
    gain = the same as a difference of means.
    """
    rec = [r for r in records if r["condition"] == condition]
    none = {_draw_key(r): r["ssim"] for r in ok_records(rec) if r["method"] == "none"}
    out = {}
    for m in METHOD_ORDER:
        mr = [r for r in rec if r["method"] == m]
        if not mr:
            continue
        ok = ok_records(mr)
        vals = np.array([r["ssim"] for r in ok], float)
        hog = np.array([r["hog"] for r in ok if r.get("hog") is not None], float)
        paired = [(r["ssim"], none[_draw_key(r)]) for r in ok if _draw_key(r) in none]
        mean, sd = mean_sd(vals)
        e = {
            "n": len(ok),
            "failed": len(mr) - len(ok),
            "mean": mean,
            "sd": sd,
            "sem": float(vals.std(ddof=1) / math.sqrt(vals.size)) if vals.size > 1 else None,
            "hog": float(hog.mean()) if hog.size else None,
        }
        if paired and m != "none":
            a = np.array(paired)
            e["improvement_pct"] = float((a[:, 0].mean() / a[:, 1].mean() - 1) * 100)
            e["gain"] = float((a[:, 0] - a[:, 1]).mean())
            e["gain_sem"] = float((a[:, 0] - a[:, 1]).std(ddof=1) / math.sqrt(len(a))) if len(a) > 1 else None
        out[m] = e
    return out


def draw_values(records: list[dict], condition: str, field: str) -> np.ndarray:
    """A per-draw field's values over the condition's draws (each draw counted once): float (n,)."""
    seen = {}
    for r in records:
        if r["condition"] == condition and r.get(field) is not None:
            seen[_draw_key(r)] = r[field]
    return np.array(list(seen.values()), float)


def draw_means(records: list[dict], condition: str, field: str) -> float | None:
    """Mean over the condition's draws of a per-draw field (each draw counted once)."""
    return mean_sd(draw_values(records, condition, field))[0]


def method_mean(records: list[dict], condition: str, method: str, field: str) -> float | None:
    vals = [
        r[field]
        for r in ok_records(records)
        if r["condition"] == condition and r["method"] == method and r.get(field) is not None
    ]
    return float(np.mean(vals)) if vals else None


def pair_improvements(records: list[dict], method: str) -> dict[str, float]:
    """{pair: improvement % of ``method`` over no correction (paired means over its draws)}."""
    out: dict[str, float] = {}
    for pair in sorted({r["pair"] for r in records}):
        rec = [r for r in records if r["pair"] == pair]
        none = {_draw_key(r): r["ssim"] for r in ok_records(rec) if r["method"] == "none"}
        paired = [
            (r["ssim"], none[_draw_key(r)]) for r in ok_records(rec) if r["method"] == method and _draw_key(r) in none
        ]
        if paired:
            a = np.array(paired)
            out[pair] = float((a[:, 0].mean() / a[:, 1].mean() - 1) * 100)
    return out


def conditions_of(doc: dict) -> list[dict]:
    """The conditions of an experiment's raw result, in the order of its definition."""
    return doc["definition"]["conditions"]


def methods_in(records) -> list[str]:
    """The methods the records hold, in :data:`METHOD_ORDER`."""
    present = {r["method"] for r in records}
    return [m for m in METHOD_ORDER if m in present]


def limit_rows(doc: dict) -> list[dict]:
    """One row per condition of a limits sweep: method stats, ceiling gain, transfer floor,
    first-order prediction and bound, uncorrected phase error, transfer and estimation losses."""
    rec = doc["records"]
    rows = []
    far = doc["definition"]["name"] == "size_ratio"
    for c in conditions_of(doc):
        lab = c["label"]
        st = method_stats(rec, lab)
        none = st.get("none", {}).get("mean")
        ceil = draw_means(rec, lab, "ssim_oracle_transfer")
        rows.append(
            {
                "x": c["x"],
                "label": lab,
                "in_paper": c["in_paper"],
                "stats": st,
                "ceiling_gain": None if (ceil is None or none is None) else ceil - none,
                "floor": draw_means(rec, lab, "transfer_floor_far_rad" if far else "transfer_floor_rad"),
                "first_order": draw_means(
                    rec, lab, "transfer_first_order_far_rad" if far else "transfer_first_order_rad"
                ),
                "bound": draw_means(rec, lab, "transfer_bound_far_rad" if far else "transfer_bound_rad"),
                "uncorrected": draw_means(rec, lab, "phase_rms_uncorrected"),
                # SSIM lost to the transfer (perfect target phase vs perfect reference phase) and, per
                # twin, to the estimate on the reference (perfect reference phase vs the twin's).
                "transfer_loss": _diff(draw_means(rec, lab, "ssim_oracle_target"), ceil),
                "estimation_loss": {m: _diff(ceil, st[m].get("mean")) for m in st if m != "none"},
            }
        )
    return rows


def _diff(a, b):
    return None if a is None or b is None else a - b


def stops_helping(rows: list[dict], method: str) -> dict:
    """Where ``method``'s mean SSIM gain over no correction first falls below HELP_THRESHOLD:
    {"x": value or None, "label", "gain"} (None: it helps over the whole sweep)."""
    for r in rows:
        g = r["stats"].get(method, {}).get("gain")
        if g is not None and g < HELP_THRESHOLD:
            return {"x": r["x"], "label": r["label"], "gain": g}
    return {"x": None, "label": None, "gain": None}


def crossing(xs, ys, level: float):
    """First x where the piecewise-linear ys reaches ``level`` (None if never)."""
    for (x0, y0), (x1, y1) in zip(zip(xs, ys), zip(xs[1:], ys[1:])):
        if y0 is None or y1 is None:
            continue
        if y0 < level <= y1:
            return x0 + (level - y0) * (x1 - x0) / (y1 - y0)
    if ys and ys[0] is not None and ys[0] >= level:
        return xs[0]
    return None


def pareto_front(points: list[tuple[float, float]]) -> list[int]:
    """Indices of the points no other point beats in both time (lower) and SSIM (higher), by time."""
    order = sorted(range(len(points)), key=lambda i: (points[i][0], -points[i][1]))
    front, best = [], -np.inf
    for i in order:
        if points[i][1] > best:
            front.append(i)
            best = points[i][1]
    return front


def trade_means(rows: list[dict]) -> list[dict]:
    """Mean over scenes per (knob, label): time_s (reference basis + autofocus), autofocus_s, ssim, hog."""
    out: dict = {}
    for r in rows:
        if r.get("status", "ok") != "ok":
            continue
        e = out.setdefault(
            (r["knob"], r["label"]), {"knob": r["knob"], "label": r["label"], "value": r["value"], "rows": []}
        )
        e["rows"].append(r)
    res = []
    for e in out.values():
        rs = e["rows"]
        res.append(
            {
                "knob": e["knob"],
                "label": e["label"],
                "value": e["value"],
                "n": len(rs),
                "time_s": float(
                    np.mean([r["reference_basis_s"] + r["autofocus_s"] + r.get("template_s", 0.0) for r in rs])
                ),
                "reference_basis_s": float(np.mean([r["reference_basis_s"] for r in rs])),
                "autofocus_s": float(np.mean([r["autofocus_s"] for r in rs])),
                "template_s": float(np.mean([r["template_s"] for r in rs])) if "template_s" in rs[0] else None,
                "ssim": float(np.mean([r["ssim"] for r in rs])),
                "hog": float(np.mean([r["hog"] for r in rs])),
                "n_positions": rs[0].get("n_positions"),
            }
        )
    return res
