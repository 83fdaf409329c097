"""The table of ``bench/agg_suite.py real`` runs: each variant on a real clip, over training seeds.

A real clip has no ground truth beyond its frames, so the table holds the held-out metrics (every 5th frame), and
the PSNR inside and outside the priors' own dynamic masks (``prior_masks``: the same pixels for every variant).
Training seeds (``--set seed=N``) give the spread a variant has on one clip; a Δ is AGG − variant over the seeds
both ran. Runs are compared only on the same bundle (the records' digest), so each bundle of a clip gets its own
table: priors estimated by other code differ. (The digests before 2026-12-04's thirty-fourth session also read the
priors' timings, so one clip's tables from then may hold one bundle under two digests.)
"""

from __future__ import annotations

from collections import defaultdict

import numpy as np

from bench.agg_suite_report import _fmt, _machines, _mean_per


def _seed(r: dict) -> int | None:
    """The training seed of a record whose only option is ``seed=N`` (0 without options); None for other options."""
    sets = r.get("set") or []
    if not sets:
        return 0
    if len(sets) == 1 and sets[0].startswith("seed="):
        return int(sets[0].split("=", 1)[1])
    return None


def _scores(r: dict) -> dict:
    """Full-image PSNR and the PSNR inside / outside the priors' masks (None where the record has none)."""
    pm = r.get("prior_masks") or {}
    return {"psnr": r["metrics"]["psnr"], "psnr_agents": pm.get("psnr_agents", r["metrics"]["psnr_agents"]),
            "psnr_background": pm.get("psnr_background")}


def _per(vals: list[float]) -> str:
    return _mean_per(vals) if vals else "–"


def real_tables(runs: list[dict]) -> list[str]:
    """Per clip and preset: each variant's PSNR / agent PSNR / SSIM over training seeds, and AGG − variant."""
    runs = [r for r in runs if r.get("kind") == "real" and _seed(r) is not None]
    if not runs:
        return []
    by = defaultdict(dict)  # (data, preset, bundle digest) -> {(variant, seed): record}
    for r in runs:
        by[(r["data"], r["preset"], r.get("bundle"))][(r["variant"], _seed(r))] = r
    out = ["### Real clips: each variant, over training seeds (`agg_suite.py real`)", "",
           "Held-out PSNR (every 5th frame), and inside / outside the priors' dynamic masks, in dB; mean (per "
           "training seed). Δ = AGG − variant over the seeds both ran.", ""]
    for (data, preset, bundle), rows in sorted(by.items(), key=lambda kv: tuple(map(str, kv[0]))):
        out += [f"`{data}`, `{preset}`, bundle `{bundle}`:", "",
                "| Variant | Seeds | PSNR | Agent PSNR | Background PSNR | SSIM | Gaussians | Agents | Wall (s) | "
                "Δ PSNR | Δ agent PSNR | Δ background PSNR |", "|" + "---|" * 12]
        agg = {s: _scores(r) for (v, s), r in rows.items() if v == "agg"}
        for variant in sorted({v for v, _ in rows}, key=lambda v: (v != "agg", v)):
            mine = {s: r for (v, s), r in rows.items() if v == variant}
            seeds = sorted(mine)
            m = [mine[s]["metrics"] for s in seeds]
            sc = {s: _scores(mine[s]) for s in seeds}
            both = [s for s in seeds if s in agg]
            d = [agg[s]["psnr"] - sc[s]["psnr"] for s in both]
            da = [agg[s]["psnr_agents"] - sc[s]["psnr_agents"] for s in both
                  if agg[s]["psnr_agents"] is not None and sc[s]["psnr_agents"] is not None]
            db = [agg[s]["psnr_background"] - sc[s]["psnr_background"] for s in both
                  if agg[s]["psnr_background"] is not None and sc[s]["psnr_background"] is not None]
            agents = [sc[s]["psnr_agents"] for s in seeds if sc[s]["psnr_agents"] is not None]
            bg = [sc[s]["psnr_background"] for s in seeds if sc[s]["psnr_background"] is not None]
            out.append(f"| {variant} | {','.join(map(str, seeds))} | {_per([x['psnr'] for x in m])} | {_per(agents)} | "
                       f"{_per(bg)} | {_fmt(float(np.mean([x['ssim'] for x in m])))} | "
                       f"{int(np.mean([x['n_gaussians'] for x in m]))} | "
                       f"{'/'.join(str(x['n_agents']) for x in m)} | "
                       f"{np.mean([mine[s]['wall_s'] for s in seeds]):.0f} | "
                       + " | ".join("–" if variant == "agg" else _per(x) for x in (d, da, db)) + " |")
        out += ["", _machines(list(rows.values())), ""]
    return out
