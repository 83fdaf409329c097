"""How large Adam's steps are in each phase of a suite run: the mean normalised step |m_hat| / sqrt(v_hat) of each
node group, read off the optimiser state after every training step.

    python bench/agg_suite_moments.py SEED [--variants agg,no-semantic] [--noise 1.0] [--preset balanced]
                                      [--set NAME=VALUE ...] [--until N] [--work DIR]

Adam's update of an element is lr x m_hat / (sqrt(v_hat) + eps): the normalised step is the share of the learning
rate that an element moves by. It is about 1 when the gradient is steady and falls when the gradient is noisy, or
when it shrinks faster than the second moment (decay 0.999) forgets. Each variant trains the suite's synthetic
bundle of SEED as ``bench/agg_suite.py probe`` would (same config, ``--set`` replacements included), and the
statistic is read between steps without touching the training state. Per step: the mean over the elements of the
Gaussian means (``static``: background and sky, ``agents``: every agent node) and over every camera parameter
(``camera``). Written to WORK/moments/NAME.jsonl (one line per step); the per-phase means (each Tick, Tock, the
warm-up and the joint phase) are printed and written to WORK/moments/NAME.summary.json. ``--until`` stops the run
at that iteration (the steps up to it are the full run's).
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from agg_suite import probe_config, synth_bundle  # bench/ is the script's folder
from agg_suite_curve import add_scene_args, reconstruct_until, suite_runs

BETA1, BETA2 = 0.9, 0.999  # torch.optim.Adam's defaults, which the trainer uses


def normalised_step(opt, means_only: bool) -> float | None:
    """Mean |m_hat| / sqrt(v_hat) over the elements with Adam state (the ``#means`` groups if ``means_only``)."""
    total, count = 0.0, 0
    for grp in opt.param_groups:
        if means_only and not grp["name"].endswith("#means"):
            continue
        eps = grp.get("eps", 1e-8)
        for p in grp["params"]:
            st = opt.state.get(p)
            if not st:
                continue
            t = float(st["step"])
            m = st["exp_avg"] / (1 - BETA1 ** t)
            v = st["exp_avg_sq"] / (1 - BETA2 ** t)
            r = m.abs() / (v.sqrt() + eps)
            total, count = total + float(r.sum()), count + r.numel()
    return total / count if count else None


def phase_means(rows: list[dict]) -> list[dict]:
    """One row per run of consecutive steps in one phase: its first iteration, length and the groups' means."""
    out: list[dict] = []
    for row in rows:
        if not out or out[-1]["phase"] != row["phase"]:
            out.append({"phase": row["phase"], "from": row["iteration"], "steps": 0, "_sums": {}, "_n": {}})
        seg = out[-1]
        seg["steps"] += 1
        for g in ("camera", "static", "agents"):
            if row.get(g) is not None:
                seg["_sums"][g] = seg["_sums"].get(g, 0.0) + row[g]
                seg["_n"][g] = seg["_n"].get(g, 0) + 1
    for seg in out:
        sums, n = seg.pop("_sums"), seg.pop("_n")
        for g in ("camera", "static", "agents"):
            seg[g] = round(sums[g] / n[g], 4) if n.get(g) else None
    return out


def train_with_moments(bundle_path: Path, scene_dir: Path, cfg, ablate: str, until: int | None,
                       out_path: Path) -> list[dict]:
    from agg.train.trainer import Trainer

    rows: list[dict] = []
    out_path.parent.mkdir(parents=True, exist_ok=True)
    fh = out_path.open("w")

    class Watched(Trainer):
        def step(self) -> dict:
            row = super().step()
            stats = {g: normalised_step(self.optimizers[g], g != "camera") if g in self.optimizers else None
                     for g in ("camera", "static", "agents")}
            rows.append({"iteration": row["iteration"], "phase": row["phase"],
                         **{g: None if v is None else round(v, 5) for g, v in stats.items()}})
            fh.write(json.dumps(rows[-1]) + "\n")
            return row

    try:
        reconstruct_until(Watched, bundle_path, scene_dir, cfg, ablate, until)
    finally:
        fh.close()
    return rows


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    add_scene_args(p, "agg,no-semantic")
    p.add_argument("--until", type=int, default=None)
    args = p.parse_args(argv)
    work = Path(args.work)
    cfg, tag = probe_config(args.preset, args.set)
    bundle = synth_bundle(work, args.seed, args.noise, args.frames, args.width, args.height)
    for name, ablate in suite_runs(args, "moments", tag):
        rows = train_with_moments(bundle, work / "scenes" / name, cfg, ablate, args.until,
                                  work / "moments" / f"{name}.jsonl")
        summary = phase_means(rows)
        (work / "moments" / f"{name}.summary.json").write_text(json.dumps(summary, indent=1))
        print(name)
        for seg in summary:
            print(f"  {seg['phase']:7s} from {seg['from']:5d} ({seg['steps']:4d} steps)  camera {seg['camera']}  "
                  f"static {seg['static']}  agents {seg['agents']}", flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
