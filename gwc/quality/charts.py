"""The control charts as `gwc spc --json` and the web's SPC page show them: one per machine, recipe and
feature measured, from the points the quality store reads and the arithmetic of gwc.quality.spc."""

from __future__ import annotations

from typing import Any

from gwc.quality import spc, store


def charts(read: store.Reader, cfg: Any, machine: str | None, feature: str | None) -> list[dict[str, Any]]:
    """One chart per machine, recipe and feature measured: limits, rules broken, Cp, Cpk, the points."""
    rules, baseline, window = spc.settings(cfg)
    pts = store.points(read, machine_id=machine, feature=feature, limit=window)
    out = []
    for key in sorted({(p.machine_id, p.recipe_id, p.feature) for p in pts}):
        series = [p for p in pts if (p.machine_id, p.recipe_id, p.feature) == key]
        last = series[-1]
        c = spc.chart(
            key[2], [p.value for p in series], last.nominal - last.tol, last.nominal + last.tol, rules, baseline
        )
        out.append(
            {
                "machine_id": key[0],
                "recipe_id": key[1],
                "feature": key[2],
                "nominal": last.nominal,
                "tol": last.tol,
                "points": len(series),
                "center": c.limits.center if c.limits else None,
                "sigma": c.limits.sigma if c.limits else None,
                "ucl": c.limits.ucl if c.limits else None,
                "lcl": c.limits.lcl if c.limits else None,
                "cp": c.cp,
                "cpk": c.cpk,
                "out_of_tolerance": sum(1 for p in series if abs(p.value - p.nominal) > p.tol),
                "violations": [
                    {"part": v.index + 1, "rule": v.rule, "run": series[v.index].machine_run_id, "text": v.text}
                    for v in c.violations
                ],
                "values": [p.value for p in series],
                "offsets": [p.offset for p in series],
                "drawing": spc.drawing(c),
            }
        )
    return out
