"""Tables and plots of ``bench/agg_suite.py`` runs: a section of docs/BENCHMARKS.md between markers, PNGs in docs/."""

from __future__ import annotations

import datetime
import json
from collections import defaultdict
from pathlib import Path

import numpy as np

START, END = "<!-- agg_suite:start -->", "<!-- agg_suite:end -->"


def _load(folder: Path) -> list[dict]:
    """The run records in ``folder`` (not its subfolders)."""
    return [json.loads(p.read_text()) for p in sorted(folder.glob("*.json"))]


def _fmt(v, nd=2) -> str:
    if v is None or (isinstance(v, float) and not np.isfinite(v)):
        return "–"
    return f"{v:.{nd}f}" if round(v, nd) != 0 else f"{0:.{nd}f}"  # no "-0.00"


def _psnr_pair(r: dict | None) -> str:
    """"full image / agents" PSNR of a run, "–" without one."""
    return f"{_fmt(r['metrics']['psnr'])} / {_fmt(r['metrics']['psnr_agents'])}" if r else "–"


def _mean(vals):
    vals = [v for v in vals if v is not None]
    return float(np.mean(vals)) if vals else None


def _paired(pa: dict, pv: dict, seeds: list[int], value) -> list[float]:
    """Per seed, ``value(pa[s])`` − ``value(pv[s])``, over the seeds where both are not None."""
    pairs = ((value(pa[s]), value(pv[s])) for s in seeds)
    return [a - b for a, b in pairs if a is not None and b is not None]


def _deltas(pa: dict, pv: dict, seeds: list[int]) -> tuple[list[float], list[float]]:
    """Per seed, ``pa`` − ``pv`` (seed -> metrics) on the full image, and on the agents where both have them."""
    return [pa[s]["psnr"] - pv[s]["psnr"] for s in seeds], _paired(pa, pv, seeds, lambda m: m["psnr_agents"])


def _mean_per(vals: list[float]) -> str:
    """"mean (v1, v2, ...)" of per-seed values."""
    return f"{_fmt(_mean(vals))} ({', '.join(_fmt(v) for v in vals)})"


def _interval(vals: list[float], level: float = 0.95) -> str:
    """"[lo, hi]": the Student-t interval of the mean of per-seed values (scenes as the sample; "–" under 3)."""
    if len(vals) < 3:
        return "–"
    from scipy.stats import t

    half = t.ppf(0.5 + level / 2, len(vals) - 1) * float(np.std(vals, ddof=1)) / np.sqrt(len(vals))
    return f"[{_fmt(_mean(vals) - half)}, {_fmt(_mean(vals) + half)}]"


def _background(r: dict) -> float | None:
    """A run's pooled PSNR outside the agent masks (None where the record has no regions)."""
    return (r.get("regions") or {}).get("psnr_background")


def synth_presets(runs: list[dict]) -> list[str]:
    """The presets the suite ran at, the acceptance preset (balanced) first."""
    return sorted({r["preset"] for r in runs if r["kind"] == "synth"}, key=lambda p: (p != "balanced", p))


def synth_tables(runs: list[dict], preset: str) -> list[str]:
    """The suite's tables at ``preset``: AGG against the baseline per pose noise, the ablations, topology and
    cameras; the acceptance preset (balanced) also gets where the error lies and the agents' poses."""
    synth = [r for r in runs if r["kind"] == "synth" and r["preset"] == preset]
    if not synth:
        return []
    detail = preset == "balanced"
    by = defaultdict(list)  # (noise, variant) -> runs
    for r in synth:
        by[(r["noise"], r["variant"])].append(r)
    noises = sorted({r["noise"] for r in synth})
    out = [f"### Synthetic suite at `{preset}`: AGG against the fixed-topology baseline",
           "",
           f"Preset `{preset}`; each cell is the mean over the seeds run (per-seed values in brackets); "
           "every scene has 1 missed moving car and 1 false agent in its priors. PSNR in dB on the held-out frames.",
           "",
           "| Pose noise | Seeds | AGG PSNR | Baseline PSNR | Δ | AGG agent PSNR | Baseline agent PSNR | Δ agents |",
           "|---|---|---|---|---|---|---|---|"]
    splatted = False  # a row whose runs splatted each coarse tracking level at its own size
    for n in noises:
        a, b = by.get((n, "agg"), []), by.get((n, "baseline"), [])
        seeds = sorted({r["seed"] for r in a} & {r["seed"] for r in b})
        if not seeds:
            continue
        pa = {r["seed"]: r["metrics"] for r in a}
        pb = {r["seed"]: r["metrics"] for r in b}
        d, dg = _deltas(pa, pb, seeds)
        mark = "" if all(_render_full(r) for r in a + b if r["seed"] in seeds) else " †"
        splatted = splatted or bool(mark)
        out.append(f"| {n:g} m{mark} | {','.join(map(str, seeds))} | {_fmt(_mean([pa[s]['psnr'] for s in seeds]))} | "
                   f"{_fmt(_mean([pb[s]['psnr'] for s in seeds]))} | {_mean_per(d)} | "
                   f"{_fmt(_mean([pa[s]['psnr_agents'] for s in seeds]))} | "
                   f"{_fmt(_mean([pb[s]['psnr_agents'] for s in seeds]))} | {_mean_per(dg)} |")
    if splatted:
        out += ["", "† Made before 2026-12-07 with each coarse tracking level splatted at its own size (the earlier "
                "default; `render_full` off); the other rows with `render_full`."]
    abl = [v for v in ("no-tick-tock", "no-semantic", "no-topology") if any(k[1] == v for k in by)]
    if abl:
        out += ["", "**Ablations** (each component switched off alone; Δ = AGG − ablation, same seeds):", "",
                "| Pose noise | Variant | Seeds | PSNR | Δ | Agent PSNR | Δ agents |", "|---|---|---|---|---|---|---|"]
        for n in noises:
            pa = {r["seed"]: r["metrics"] for r in by.get((n, "agg"), [])}
            for v in abl:
                pv = {r["seed"]: r["metrics"] for r in by.get((n, v), [])}
                seeds = sorted(set(pa) & set(pv))
                if not seeds:
                    continue
                d, dg = _deltas(pa, pv, seeds)
                out.append(f"| {n:g} m | {v} | {','.join(map(str, seeds))} | "
                           f"{_fmt(_mean([pv[s]['psnr'] for s in seeds]))} | {_mean_per(d)} | "
                           f"{_fmt(_mean([pv[s]['psnr_agents'] for s in seeds]))} | {_fmt(_mean(dg))} |")
    topo = [r for r in synth if r["variant"] in ("agg", "no-tick-tock", "no-semantic")]
    if topo:
        out += ["", "**Topology evolution** (runs with it on): the spawned agent nearest the missed car. *Within 1 m "
                "of visible*: the fraction of the frames in which the car is visible where the agent is valid and "
                "its centre lies within 1 m of the car's ground-truth centre (the acceptance measure); *within 1 m "
                "of valid*: the same over the agent's valid frames only; *after Sim(3)*: within 1 m of visible and "
                "the median error once the reconstruction is moved by the Sim(3) that aligns its refined training "
                "cameras to ground truth (fitted on the cameras alone; runs that record it); whether the planted "
                "false agent was pruned (or demoted).", "", "| Noise | Seed | Variant | Spawned ids | "
                "Within 1 m of visible | Within 1 m of valid | Median error (m) | After Sim(3): within 1 m / "
                "median (m) | Valid / visible frames | False agent pruned |",
                "|---|---|---|---|---|---|---|---|---|---|"]
        for r in sorted(topo, key=lambda r: (r["noise"], r["seed"], r["variant"])):
            t = r["topology"]
            m = t.get("missed_match") or {}
            out.append(f"| {r['noise']:g} | {r['seed']} | {r['variant']} | {t['spawned']} | "
                       f"{_fmt(m.get('within_1m_of_visible'))} | {_fmt(m.get('within_1m'))} | "
                       f"{_fmt(m.get('median_m'))} | "
                       + (f"{_fmt(m['within_1m_aligned'])} / {_fmt(m['median_aligned_m'])} | "
                          if "within_1m_aligned" in m else "– | ")
                       + f"{m.get('frames', '–')}/{m.get('visible_frames', '–')} | "
                       f"{'yes' if t['false_pruned'] == t['false_ids'] else 'no'} |")
    cams = [r for r in synth if r.get("cameras")]
    if cams:
        out += ["", "**Cameras** (runs that record them): camera-centre error against ground truth over the training "
                "frames, of the noisy priors and of the refined camera node (mean / max, then the mean after a "
                "Sim(3) alignment of the training cameras to ground truth, which takes out a drift of the whole "
                "trajectory with its map); the seconds spent in camera tracking.",
                "", "| Noise | Seed | Variant | Prior mean / max (m) | Refined mean / max (m) "
                "| Refined, Sim(3)-aligned mean (m) | Tracking (s) |", "|---|---|---|---|---|---|---|"]
        for r in sorted(cams, key=lambda r: (r["noise"], r["seed"], r["variant"])):
            c = r["cameras"]
            secs = sum(row["seconds"] for row in r["summary"].get("tracking") or [])
            out.append(f"| {r['noise']:g} | {r['seed']} | {r['variant']} | {_fmt(c['prior']['mean_m'], 3)} / "
                       f"{_fmt(c['prior']['max_m'], 3)} | {_fmt(c['refined']['mean_m'], 3)} / "
                       f"{_fmt(c['refined']['max_m'], 3)} | {_fmt(c['refined'].get('sim3_mean_m'), 3)} | "
                       f"{secs:.0f} |")
    regions = [r for r in synth if r.get("regions")] if detail else []
    if regions:
        out += ["", "**Where the error lies** (runs that record it): the PSNR of the pixels outside the agent masks "
                "(one MSE pooled over the test frames; *PSNR* is the per-frame mean, as above), the share of the test "
                "pixels that are agent pixels and the share of the squared error they carry. *Perfect agents*: "
                "what rendering the agent pixels without error, the rest left as it is, would add to the pooled "
                "PSNR, −10·log10(1 − agent share of error). It is no bound on what correcting the agents can "
                "add: wrong agent priors also spoil the background and the cameras (*Exact agent priors* below).",
                "",
                "| Noise | Seed | Variant | PSNR | Agent PSNR | Background PSNR | Agent pixels | Agent share of "
                "error | Perfect agents (dB) |", "|---|---|---|---|---|---|---|---|---|"]
        for r in sorted(regions, key=lambda r: (r["noise"], r["seed"], r["variant"])):
            g, m = r["regions"], r["metrics"]
            ceiling = -10 * np.log10(max(1.0 - g["agent_error_share"], 1e-12))
            out.append(f"| {r['noise']:g} | {r['seed']} | {r['variant']} | {_fmt(m['psnr'])} | "
                       f"{_fmt(m['psnr_agents'])} | {_fmt(g['psnr_background'])} | "
                       f"{100 * g['agent_pixel_share']:.1f} % | {100 * g['agent_error_share']:.1f} % | "
                       f"+{ceiling:.2f} |")
    poses = [r for r in synth if r.get("agent_poses")] if detail else []
    if poses:
        out += ["", "**Agents' refined poses** (runs that record them): for each true agent of the priors, the median "
                "box-centre and rotation error against ground truth over its valid frames; the median over agents.",
                "", "| Noise | Seed | Variant | Agents | Centre error (m) | Rotation error (°) |",
                "|---|---|---|---|---|---|"]
        for r in sorted(poses, key=lambda r: (r["noise"], r["seed"], r["variant"])):
            a = r["agent_poses"]
            out.append(f"| {r['noise']:g} | {r['seed']} | {r['variant']} | {len(a['per_agent'])} | "
                       f"{_fmt(a['translation_m'], 3)} | {_fmt(a['rotation_deg'], 1)} |")
    wall = [r["wall_s"] for r in synth]
    out += ["", f"Wall time per run: {min(wall):.0f}–{max(wall):.0f} s. {_machines(synth)}"]
    return out


def _machines(runs: list[dict]) -> str:
    """Which CPUs the runs ran on (records carry the model and AVX-512 from 2026-11-25 on): the same run on two
    CPUs need not give the same numbers, so a Δ between runs from different machines holds that difference too. A
    model recorded without AVX-512 is counted apart from the same model with it. Also how many runs had tracking
    rounds of each kind or none, and how many left the ego vehicle's pixels out of training and scores."""
    count: dict[str, int] = defaultdict(int)
    for r in runs:
        machine = r.get("machine") or {}
        no_avx512 = " without AVX-512" if machine.get("avx512") is False else ""
        count[machine.get("cpu", "not recorded") + no_avx512] += 1
    gate = sum(1 for r in runs if _tracking_option(r, "gate"))
    options = f" With the tracking gate: {gate} of {len(runs)} runs." if gate else ""
    tracked = [r for r in runs if (r.get("summary") or {}).get("tracking")]
    full = sum(1 for r in tracked if _render_full(r))
    if full:
        options += f" Coarse tracking levels rendered at full size (`render_full`): {full} of {len(runs)} runs."
    if len(tracked) > full:
        options += (f" Coarse tracking levels splatted at their own size (the default before 2026-12-07): "
                    f"{len(tracked) - full} of {len(runs)} runs.")
    if len(runs) > len(tracked):
        options += f" Without tracking rounds: {len(runs) - len(tracked)} of {len(runs)} runs."
    ego = [r["metrics"]["ego_pixel_share"] for r in runs if (r.get("metrics") or {}).get("ego_pixel_share")]
    if ego:
        options += (f" The ego vehicle's pixels ({100 * max(ego):.1f} % of the image) left out of training and "
                    f"scores: {len(ego)} of {len(runs)} runs.")
    return "Machines: " + ", ".join(f"{cpu} ({n} runs)" for cpu, n in sorted(count.items())) + "." + options


def _tracking_option(r: dict, key: str) -> bool:
    """Whether a run's camera-tracking rounds ran with ``TrackingConfig.gate`` or ``render_full``: its rounds'
    rows carry the key (``render_full`` from the forty-third session on), a probe's ``--set`` names it. A table
    whose runs differ in one compares two engines, so ``_machines`` counts them."""
    return (f"tracking.{key}=true" in (r.get("set") or [])
            or any(key in row for row in (r.get("summary") or {}).get("tracking") or []))


def _render_full(r: dict) -> bool:
    """Whether a run's coarse tracking levels rendered at full size: the default from 2026-12-07. Runs are paired
    only with runs of the same engine, the suite's earlier records (runs/superseded/before_render_full/) included."""
    return _tracking_option(r, "render_full")


def probe_table(runs: list[dict], title: str = "Probes: the same runs with training options replaced",
                plain_pool: list[dict] | None = None) -> list[str]:
    """Probe runs (a preset with options replaced) beside the plain run of the same seed, noise and variant, made
    with the same coarse tracking levels (from ``plain_pool``, default ``runs``)."""
    probes = [r for r in runs if r["kind"] == "probe" and not r.get("oracle_agents")]
    if not probes:
        return []
    plain = {(r["seed"], r["noise"], r["variant"], r["preset"], _render_full(r)): r
             for r in (plain_pool if plain_pool is not None else runs) if r["kind"] == "synth"}
    out = [f"### {title}", "",
           "| Seed | Noise | Variant | Options | PSNR | Agent PSNR | Gaussians | Wall (s) | Unchanged PSNR / agent "
           "PSNR |", "|---|---|---|---|---|---|---|---|---|"]
    for r in sorted(probes, key=lambda r: (r["seed"], r["noise"], " ".join(r["set"]), r["variant"])):
        a = r.get("agent_noise", 0.0)
        m, ref = r["metrics"], None if a else plain.get((r["seed"], r["noise"], r["variant"], r["preset"],
                                                           _render_full(r)))
        base = _psnr_pair(ref)
        opts = ", ".join(r["set"] + ([f"agent noise {a:g} m"] if a else []))
        out.append(f"| {r['seed']} | {r['noise']:g} m | {r['variant']} | {opts} | {_fmt(m['psnr'])} | "
                   f"{_fmt(m['psnr_agents'])} | {m['n_gaussians']} | {r['wall_s']:.0f} | {base} |")
    return out + [""]


def _default_options(r: dict) -> bool:
    """Whether a probe's ``--set`` options leave its preset as it is (they all equal the preset's own values)."""
    from agg.train.config import get_preset
    from agg_suite import probe_config  # bench/ is on the path: the report runs as ``agg_suite.py report``

    return probe_config(r["preset"], r["set"])[0] == get_preset(r["preset"])


def noisy_box_table(runs: list[dict]) -> list[str]:
    """The suite's comparison on noisy tracklet boxes too (probes with ``--agent-noise`` and the preset's own
    options): AGG against the baseline and against no-tick-tock, per seed, with the missed car's coverage."""
    rows = [r for r in runs if r["kind"] == "probe" and r.get("agent_noise") and _default_options(r)]
    by = defaultdict(dict)  # (preset, noise, agent noise) -> {(seed, variant): run}
    for r in rows:
        by[(r["preset"], r["noise"], r["agent_noise"])][(r["seed"], r["variant"])] = r
    out = []
    for (preset, noise, a), cell in sorted(by.items()):
        seeds = sorted({s for s, v in cell if v == "agg"})
        if not seeds:
            continue
        out += [f"### Noisy boxes at `{preset}`: cameras at {noise:g} m and tracklet box centres moved by up to "
                f"{a:g} m", "",
                "The suite's comparison with the agent priors wrong too (`probe --agent-noise`; the preset's own "
                "options). Full image / agent PSNR in dB; Δ = AGG − variant; *missed car*: the AGG run's spawned "
                "agent within 1 m of the missed car (of visible frames); *centre error*: the true agents' median "
                "refined box-centre error.", "",
                "| Seed | AGG | Baseline | Δ baseline | No-tick-tock | Δ no-tick-tock | Missed car within 1 m | "
                "False agent pruned | Centre error AGG / baseline / no-tick-tock (m) |",
                "|---|---|---|---|---|---|---|---|---|"]
        deltas = defaultdict(list)
        for s in seeds:
            ag = cell[(s, "agg")]
            cols, errs = [], [ag.get("agent_poses", {}).get("translation_m")]
            for v in ("baseline", "no-tick-tock"):
                r = cell.get((s, v))
                if r is None or (None not in (r.get("bundle"), ag.get("bundle")) and r["bundle"] != ag["bundle"]):
                    cols += ["–" if r is None else "another bundle", "–"]  # runs on different inputs: no Δ
                    errs.append(None)
                    continue
                d = (ag["metrics"]["psnr"] - r["metrics"]["psnr"],
                     ag["metrics"]["psnr_agents"] - r["metrics"]["psnr_agents"])
                deltas[v].append(d)
                cols += [_psnr_pair(r),
                         f"{d[0]:+.2f} / {d[1]:+.2f}"]
                errs.append(r.get("agent_poses", {}).get("translation_m"))
            t = ag["topology"]
            m = t.get("missed_match") or {}
            out.append(f"| {s} | {_psnr_pair(ag)} | "
                       + " | ".join(cols) + f" | {_fmt(m.get('within_1m_of_visible'))} | "
                       f"{'yes' if t['false_pruned'] == t['false_ids'] else 'no'} | "
                       + " / ".join(_fmt(e, 3) for e in errs) + " |")
        means = [f"{_mean([d[0] for d in deltas[v]]):+.2f} / {_mean([d[1] for d in deltas[v]]):+.2f} "
                 f"({len(deltas[v])} seeds)" if deltas[v] else "–" for v in ("baseline", "no-tick-tock")]
        out += [f"| mean | | | {means[0]} | | {means[1]} | | | |", ""]
    return out


def oracle_table(runs: list[dict]) -> list[str]:
    """What exact agent priors give (probes with ``--oracle-agents``: every agent in the priors, no false one, the
    suite's camera noise) beside the suite's runs of the same seed and noise: how much of the full-image PSNR is
    there to win by correcting the agents, measured by training rather than by rescoring pixels."""
    oracle = {(r["preset"], r["seed"], r["noise"], r["variant"]): r for r in runs
              if r["kind"] == "probe" and r.get("oracle_agents") and _default_options(r)}
    plain = {(r["preset"], r["seed"], r["noise"], r["variant"]): r for r in runs if r["kind"] == "synth"}
    cases = sorted({(p, s, n) for p, s, n, v in oracle if v == "baseline" and (p, s, n, "baseline") in plain},
                   key=lambda c: (c[0] != "balanced", c))  # each probe beside the suite's run at its own preset
    if not cases:
        return []

    out = ["### Exact agent priors: how much correcting the agents can add", "",
           "`probe --oracle-agents`: the same cameras (same noise draws) with every agent in the priors and no false "
           "one, so there is nothing for topology evolution to correct. Full image / agent PSNR in dB; *oracle "
           "gain* = oracle baseline − baseline, the full-image PSNR that perfect agent priors are worth to the "
           "fixed-topology baseline; AGG − baseline is the suite's Δ, and *recovered* its share of the oracle gain. "
           "Camera error: Sim(3)-aligned mean over the training frames.", "",
           "| Noise | Seed | Baseline | Oracle baseline | Oracle gain | AGG | AGG − baseline | Recovered | "
           "Oracle AGG | Camera error baseline / oracle baseline / AGG (m) |",
           "|---|---|---|---|---|---|---|---|---|---|"]
    gains, deltas = [], []
    for p, s, n in cases:
        b, ob, ag, oa = (plain[(p, s, n, "baseline")], oracle[(p, s, n, "baseline")], plain.get((p, s, n, "agg")),
                         oracle.get((p, s, n, "agg")))
        gain = ob["metrics"]["psnr"] - b["metrics"]["psnr"]
        gains.append(gain)
        delta = ag["metrics"]["psnr"] - b["metrics"]["psnr"] if ag else None
        deltas.append(delta)
        cams = " / ".join(_fmt((r or {}).get("cameras", {}).get("refined", {}).get("sim3_mean_m"), 3)
                          for r in (b, ob, ag))
        share = "–" if delta is None or gain <= 0 else f"{100 * delta / gain:.0f} %"
        out.append(f"| {n:g} m | {s} | {_psnr_pair(b)} | {_psnr_pair(ob)} | {gain:+.2f} | {_psnr_pair(ag)} | "
                   f"{'–' if delta is None else f'{delta:+.2f}'} | {share} | {_psnr_pair(oa)} | {cams} |")
    d = _mean(deltas)
    out += [f"| | mean | | | {_mean(gains):+.2f} | | {'–' if d is None else f'{d:+.2f}'} | | | |", "",
            _machines([r for key in cases for r in (plain[(*key, "baseline")], oracle[(*key, "baseline")],
                                                    plain.get((*key, "agg")), oracle.get((*key, "agg"))) if r]), ""]
    return out


def other_tables(runs: list[dict]) -> list[str]:
    out = []
    kitti = [r for r in runs if r["kind"] == "kitti"]
    if kitti:
        out += ["### kitti06_51 (fast preset, ≤ 320 px wide): estimated against ground-truth poses", "",
                "*Cameras*: the training cameras against KITTI's poses after a Sim(3) alignment, as the camera node "
                "starts (the priors' poses, or ground truth) and as training leaves it: mean centre error (m) / mean "
                "rotation error (°); runs that record it.", "",
                "| Poses | PSNR | SSIM | Gaussians | Cameras at the start | Cameras refined | Priors (s) | "
                "Training (s) | Whole command (s) |", "|---|---|---|---|---|---|---|---|---|"]
        for r in sorted(kitti, key=lambda r: r["gt_poses"]):
            s, m, c = r["summary"], r["metrics"], r.get("cameras") or {}
            cams = [f"{_fmt(c[k]['sim3_mean_m'], 3)} / {_fmt(c[k]['sim3_rotation_deg'], 3)}"
                    if "sim3_rotation_deg" in c.get(k, {}) else "–" for k in ("prior", "refined")]
            out.append(f"| {'ground truth' if r['gt_poses'] else 'estimated'} | {_fmt(m['psnr'])} | "
                       f"{_fmt(m['ssim'], 3)} | {m['n_gaussians']} | {cams[0]} | {cams[1]} | "
                       f"{s['seconds_priors']:.0f} | {s['seconds_train']:.0f} | {r['wall_s']:.0f} |")
        out += ["", _machines(kitti), ""]
    presets = [r for r in runs if r["kind"] == "preset"]
    if presets:
        out += ["### Preset trade (synthetic seed 0, 0.5 m pose noise, 1 missed + 1 false agent)", "",
                "| Preset | PSNR | Agent PSNR | Gaussians | Train (s) | Render FPS |", "|---|---|---|---|---|---|"]
        for r in sorted(presets, key=lambda r: r["wall_s"]):
            m, s = r["metrics"], r["summary"]
            out.append(f"| {r['preset']} | {_fmt(m['psnr'])} | {_fmt(m['psnr_agents'])} | {m['n_gaussians']} | "
                       f"{s['seconds_train']:.0f} | {_fmt(m['render_fps'], 1)} |")
        out += ["", _machines(presets), ""]
    return out


VARIANTS_MORE = ("agg", "baseline", "no-tick-tock", "no-semantic", "no-topology")


def more_scenes_table(runs: list[dict], extra: list[dict]) -> list[str]:
    """Scenes beyond the suite's seeds (records in runs/scenes/): per seed, AGG and each variant run there, and the
    Δ = AGG − variant over those seeds and over them together with the suite's seeds at the same preset and noise,
    made with the same coarse tracking levels (``runs`` may hold the suite's earlier records for that). Each engine
    gets its own tables: a scene's runs are paired only with runs of the same engine."""
    extra = [r for r in extra if r["kind"] == "synth"]
    if not extra:
        return []
    out = ["### More scenes (not the acceptance suite): AGG against each variant on further seeds", "",
           "Same generator, noise and preset as the suite, other seeds (`runs/scenes/`). Full image / agents, "
           "held-out PSNR in dB; Δ = AGG − variant. " + _machines(extra), ""]
    def table_of(r: dict) -> tuple:  # the runs of one table: one preset, noise and engine
        return r["preset"], r["noise"], _render_full(r)

    for key in sorted({table_of(r) for r in extra}, key=lambda k: (k[0], k[1], not k[2])):
        preset, noise, full = key
        cell = {(r["seed"], r["variant"]): r for r in extra if table_of(r) == key}
        suite = {(r["seed"], r["variant"]): r for r in runs if r["kind"] == "synth" and table_of(r) == key}
        variants = [v for v in VARIANTS_MORE if any(k[1] == v for k in cell)]
        levels = ("coarse tracking levels that blur the full-size render (the default)" if full else
                  "coarse tracking levels splatted at their own size (before 2026-12-07)")
        out += [f"`{preset}`, {noise:g} m of camera noise, {levels}:", "",
                "| Seed | " + " | ".join(variants)
                + " | Missed car within 1 m (share of its visible frames) / false agent pruned (AGG) |",
                "|---" * (len(variants) + 2) + "|"]
        for s in sorted({k[0] for k in cell}):
            agg = cell.get((s, "agg"))
            topo = (agg or {}).get("topology") or {}
            match = topo.get("missed_match") or {}
            t = (f"{_fmt(match.get('within_1m_of_visible'))} / {len(topo.get('false_pruned', []))} of "
                 f"{len(topo.get('false_ids', []))}") if topo else "–"
            out.append(f"| {s} | " + " | ".join(_psnr_pair(cell.get((s, v))) for v in variants) + f" | {t} |")
        out.append("")
        rows = []
        for v in variants[1:]:
            for name, pool in (("these seeds", cell), ("with the suite's", {**suite, **cell})):
                pa = {s: r["metrics"] for (s, w), r in pool.items() if w == "agg"}
                pv = {s: r["metrics"] for (s, w), r in pool.items() if w == v}
                seeds = sorted(set(pa) & set(pv))
                if not seeds:
                    continue
                d, dg = _deltas(pa, pv, seeds)
                bg = _paired({s: pool[s, "agg"] for s in seeds}, {s: pool[s, v] for s in seeds}, seeds, _background)
                rows.append(f"| {v} | {name} | {','.join(map(str, seeds))} | {_mean_per(d)} | {_interval(d)} | "
                            f"{_mean_per(dg)} | {_interval(dg)} | {_mean_per(bg)} |")
        out += ["| Variant | Seeds from | Seeds | Δ PSNR | 95 % interval | Δ agent PSNR | 95 % interval | "
                "Δ background PSNR |", "|---" * 8 + "|", *rows, "",
                "*Δ background*: the PSNR outside the agent masks (pooled over the held-out frames). "
                "The intervals treat the scenes as a sample (Student t over the per-seed Δ, 3 or more seeds). An "
                "interval whose upper end lies under 0.5 dB rules out a component worth 0.5 dB on average over "
                "scenes like these. A run's own spread (training seed only, seed 0) is 0.12–0.21 dB, so part of "
                "the scenes' spread is the runs'.", ""]
    return out


def write_report(work: Path, docs: Path, machine: str) -> None:
    from bench.agg_suite_plots import plots

    runs = _load(work / "runs")
    made = plots(runs, docs)
    lines = [START, "## AGG suite (`bench/agg_suite.py`)", "",
             f"Written {datetime.date.today().isoformat()} on the CI-class VM (2 vCPU, {machine}, torch 2.13 CPU, "
             "one OpenMP thread per run, two runs at a time).", ""]
    for preset in synth_presets(runs):
        lines += synth_tables(runs, preset) + [""]
    earlier = _load(work / "runs" / "superseded" / "before_render_full")  # the suite before render_full
    lines += probe_table(runs, plain_pool=runs + earlier) + oracle_table(runs) + noisy_box_table(runs)
    scenes = _load(work / "runs" / "scenes")  # the further seeds' earlier records are in its superseded/ too
    scenes += _load(work / "runs" / "scenes" / "superseded" / "before_render_full")
    lines += more_scenes_table(runs + earlier, scenes) + probe_table(scenes, "Probes on the further seeds")
    lines += other_tables(runs)
    from bench.agg_suite_real import real_tables

    lines += real_tables(_load(work / "runs" / "real"))
    lines += [f"![{m}]({m})" for m in made] + [END]
    path = docs / "BENCHMARKS.md"
    text = path.read_text() if path.is_file() else "# Benchmarks\n"
    block = "\n".join(lines)
    if START in text and END in text:
        text = text[: text.index(START)] + block + text[text.index(END) + len(END):]
    else:
        text = text.rstrip() + "\n\n" + block + "\n"
    path.write_text(text)
    print(f"wrote {path} ({len(runs)} runs) and {made}")
