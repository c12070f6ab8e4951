"""The tables of ``vehicle-estimation validate`` (``validation.md``): each case's figures beside
its baseline's, and the honesty of each published variance."""

from __future__ import annotations

import math


def _rows_table(rows: list[dict]) -> list[str]:
    def num(x, spec=".3f"):
        return format(x, spec) if x is not None and math.isfinite(x) else "n/a"

    lines = ["| case | quantity | estimator | MAE | RMSE | baseline | baseline MAE | baseline RMSE | ratio |",
             "| --- | --- | --- | ---: | ---: | --- | ---: | ---: | ---: |"]
    for r in rows:
        case = r["case"] + ("" if r["independent"] else " (ours)")
        lines.append(f"| {case} | {r['quantity']} [{r['unit']}] | {r['estimator']} | {num(r['ours']['mae'])} | "
                     f"{num(r['ours']['rmse'])} | {r['baseline']} | {num(r['base']['mae'])} | "
                     f"{num(r['base']['rmse'])} | {num(r['ratio'], '.2f')} |")
    return lines


def format_table(result: dict) -> str:
    lines = _rows_table(result["rows"])
    lines.append("")
    lines.append("ratio = our RMSE / the baseline's (below 1: ours better); mass rows in % of the true mass, "
                 f"over the last half; other metrics after the first {result['warmup_s']:g} s; "
                 + ("methods" if result.get("layers") else "shipped methods") + ": "
                 + ", ".join(f"{k} {v}" for k, v in result["methods"].items()))
    if result.get("layers"):
        lines.append("params: estimation.yaml, then " + ", ".join(result["layers"]) + " in every case")
    if result.get("motion"):
        lines += ["", "The fusion's and the vehicle state's motion outputs against the raw sensors:", ""]
        lines += _rows_table(result["motion"])
    if result.get("consistency"):
        lines += ["", format_consistency(result["consistency"])]
    ensembles = ensemble_rows(result)
    if ensembles:
        lines += ["", format_ensembles(ensembles)]
    return "\n".join(lines)


def ensemble_rows(result: dict) -> list[dict]:
    """Per drive that ran with several noise draws (consistency rows with an ``ensemble``) and
    estimate: the drives' errors (each drive's MAE, from the rows of the same estimate) and
    their consistency taken together. Within one drive a lasting error (the bias the fusion
    has not learnt) is one draw, so a single drive's NEES says little; over the draws the
    mean NEES should be about 1."""
    groups: dict[tuple[str, str], list[dict]] = {}
    for r in result.get("consistency", []):
        if r.get("ensemble"):
            groups.setdefault((r["ensemble"], r["quantity"]), []).append(r)
    out = []
    for (ensemble, quantity), members in groups.items():
        cases = {r["case"] for r in members}
        errors = [r for r in result["rows"] if r["case"] in cases and r["quantity"].split(" (")[0] == quantity]
        mae = [r["ours"]["mae"] for r in errors if math.isfinite(r["ours"]["mae"])]
        nees = [r["nees"] for r in members if r.get("nees") is not None and math.isfinite(r["nees"])]
        within = [r["within_2sigma"] for r in members if r.get("within_2sigma") is not None]
        out.append({"ensemble": ensemble, "quantity": quantity, "drives": len(cases),
                    "unit": errors[0]["unit"] if errors else "",
                    "mae_rms": math.sqrt(sum(x * x for x in mae) / len(mae)) if mae else math.nan,
                    "mae_max": max(mae) if mae else math.nan,
                    "within_2sigma": sum(within) / len(within) if within else math.nan,
                    "nees": sum(nees) / len(nees) if nees else math.nan,
                    "nees_range": (min(nees), max(nees)) if nees else (math.nan, math.nan)})
    return out


def format_ensembles(rows: list[dict]) -> str:
    """The table of :func:`ensemble_rows`."""
    from vehicle_estimation.evaluation.consistency import format_share as pct

    lines = ["Over the noise draws of one drive (a lasting error is one draw per drive):", "",
             "| drive | estimate | drives | MAE over the drives, RMS (max) | within 2σ | NEES, mean (range) |",
             "| --- | --- | ---: | ---: | ---: | ---: |"]
    def num(x, spec):
        return format(x, spec) if x is not None and math.isfinite(x) else "n/a"

    for r in rows:
        low, high = r["nees_range"]
        mae = f"{num(r['mae_rms'], '.3f')} ({num(r['mae_max'], '.3f')}) {r['unit']}" if r["unit"] else "n/a"
        lines.append(f"| {r['ensemble']} | {r['quantity']} | {r['drives']} | {mae} | {pct(r['within_2sigma'])} | "
                     f"{num(r['nees'], '.2f')} ({num(low, '.2f')}–{num(high, '.2f')}) |")
    return "\n".join(lines)


def format_consistency(rows: list[dict]) -> str:
    """Honesty of the published variances: errors within 1/2/3 sigma, NEES, and the same over
    the samples flagged converged."""
    from vehicle_estimation.evaluation.consistency import format_share as pct

    def num(x):
        return "n/a" if x is None or not math.isfinite(x) else f"{x:.2f}"

    lines = ["| case | estimate | within 1σ | 2σ | 3σ | NEES | flagged converged | converged within 2σ | "
             "converged beyond 3σ | converged NEES |",
             "| --- | --- | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: |"]
    for r in rows:
        case = r["case"] + ("" if r["independent"] else " (ours)")
        lines.append(f"| {case} | {r['quantity']} | {pct(r['within_1sigma'])} | {pct(r['within_2sigma'])} | "
                     f"{pct(r['within_3sigma'])} | {num(r['nees'])} | {pct(r.get('converged_share'))} | "
                     f"{pct(r.get('converged_within_2sigma'))} | {pct(r.get('converged_beyond_3sigma'))} | "
                     f"{num(r.get('converged_nees'))} |")
    lines.append("")
    lines.append("An honest variance: 68 / 95 / 99.7 % of the errors within 1 / 2 / 3σ and NEES 1 (above 1: "
                 "the published variance is too small); mass over the last half, the rest after the warm-up.")
    return "\n".join(lines)
