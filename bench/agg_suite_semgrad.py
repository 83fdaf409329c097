"""What Eq. 3 changes in the steps it joins: the gradient and the Adam step of each node group with and without it.

    python bench/agg_suite_semgrad.py SEED [--variants agg] [--noise 1.0] [--preset balanced]
                                      [--set NAME=VALUE ...] [--until N] [--work DIR]

Each variant trains the suite's synthetic bundle of SEED as ``bench/agg_suite.py probe`` would (same config, ``--set``
replacements included). In every step where the semantic loss is on (the Ticks and Tocks), after the trainer's own
backward pass (L_photo + L_sem), the frame is rendered once more and L_photo alone is back-propagated, so each
trainable parameter has g_photo and g_sem = g_total - g_photo. Then the training gradient is put back and the step
goes on as it would have. Per step and per group (``camera``, ``static``: background and sky, ``agents``; the
Gaussian means of the last two also alone, as ``static#means`` and ``agents#means``):

- ``cos``: the cosine between g_photo and g_sem over the group's elements: near 1, Eq. 3 pulls where L_photo does;
- ``ratio``: |g_sem| / |g_photo|;
- ``total_cos``: the cosine between g_total and g_photo, the gradient the step follows and the one it would follow
  without Eq. 3;
- ``pre_cos``: the same after each element is divided by Adam's running root mean square of its gradient
  (sqrt(v_hat) + eps, from the state before this step): Adam takes out a gradient's scale element by element, so
  this is how far Eq. 3 turns the step whatever its weight. Momentum is left out: it is the same in both.

One JSON line per step goes to WORK/semgrad/NAME.jsonl; the means over each Tick and Tock (with Tick-Tock ablated,
over each stretch of one attention map) are printed and written to WORK/semgrad/NAME.summary.json. ``--until`` stops
the run at that iteration. The extra render and backward pass leave the run as it is: on seed 0 (balanced, 1.0 m)
its 2,000 losses were the suite run's, bit for bit.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import torch

from agg_suite import probe_config, synth_bundle  # bench/ is the script's folder
from agg_suite_curve import add_scene_args, reconstruct_until, suite_runs

BETA2 = 0.999  # torch.optim.Adam's default, which the trainer uses
STATS = ("cos", "ratio", "total_cos", "pre_cos")


def _cos(a: torch.Tensor, b: torch.Tensor) -> float | None:
    na, nb = float(a.norm()), float(b.norm())
    return float(a @ b) / (na * nb) if na > 0 and nb > 0 else None


def rms(opt, p: torch.nn.Parameter, eps: float) -> torch.Tensor:
    """[numel] Adam's sqrt(v_hat) + eps of ``p`` before this step (1 where it has no state yet)."""
    st = opt.state.get(p)
    if not st or float(st["step"]) == 0:
        return torch.ones(p.numel(), device=p.device)
    return ((st["exp_avg_sq"] / (1 - BETA2 ** float(st["step"]))).sqrt() + eps).flatten()


def group_stats(opt, total: dict, photo: dict, means_only: bool) -> dict | None:
    """The STATS of one optimiser's parameters (those of its ``#means`` groups if ``means_only``); ``total`` and
    ``photo`` map each parameter to its gradient."""
    gt, gp, r = [], [], []
    for grp in opt.param_groups:
        if means_only and not grp["name"].endswith("#means"):
            continue
        for p in grp["params"]:
            if p not in total:
                continue
            gt.append(total[p].flatten())
            gp.append(photo[p].flatten())
            r.append(rms(opt, p, grp.get("eps", 1e-8)))
    if not gt:
        return None
    gt, gp, r = map(torch.cat, (gt, gp, r))
    gs, nphoto = gt - gp, float(gp.norm())
    return {"cos": _cos(gp, gs), "ratio": float(gs.norm()) / nphoto if nphoto > 0 else None,
            "total_cos": _cos(gt, gp), "pre_cos": _cos(gt / r, gp / r)}


def train_with_semgrad(bundle_path: Path, scene_dir: Path, cfg, ablate: str, until: int | None,
                       out_path: Path) -> list[dict]:
    from agg.train.losses import photometric_loss
    from agg.train.trainer import Trainer

    rows: list[dict] = []
    out_path.parent.mkdir(parents=True, exist_ok=True)
    fh = out_path.open("w")

    class Watched(Trainer):
        def forward_backward(self, frame: int, phase):
            loss, sem, out = super().forward_backward(frame, phase)
            if sem is None or not loss.requires_grad:
                return loss, sem, out
            params = [p for ps in self.group_params().values() for p in ps if p.requires_grad and p.grad is not None]
            total = {p: p.grad.detach().clone() for p in params}
            grad2d = None if out.meta.means2d.grad is None else out.meta.means2d.grad.clone()
            again = self.graph.render(frame)  # the same render, for L_photo alone
            photo = photometric_loss(again.color, self.data.images[frame], self.cfg.ssim_weight,
                                     self._static_weight(frame, phase))
            grads = torch.autograd.grad(photo, params, allow_unused=True)
            photo_g = {p: torch.zeros_like(p) if g is None else g.detach() for p, g in zip(params, grads)}
            row = {"iteration": self.iteration, "phase": phase.name, "attention": phase.attention}
            for name, opt in self.optimizers.items():
                for means_only in ((False, True) if name != "camera" else (False,)):
                    s = group_stats(opt, total, photo_g, means_only)
                    if s is not None:
                        row[name + ("#means" if means_only else "")] = {k: None if v is None else round(v, 5)
                                                                       for k, v in s.items()}
            for p in params:  # the training gradient stays what the trainer computed
                p.grad = total[p]
            out.meta.means2d.grad = grad2d
            rows.append(row)
            fh.write(json.dumps(row) + "\n")
            return loss, sem, out

    try:
        reconstruct_until(Watched, bundle_path, scene_dir, cfg, ablate, until)
    finally:
        fh.close()
    return rows


def phase_means(rows: list[dict]) -> list[dict]:
    """One row per run of consecutive steps in one phase with one attention map (M_bg or M_ag: with Tick-Tock
    ablated the phase is the joint one throughout and the map alternates): its first iteration, length and each
    group's mean STATS (over the steps where they are defined)."""
    out: list[dict] = []
    for row in rows:
        key = (row["phase"], row.get("attention"))
        if not out or (out[-1]["phase"], out[-1]["attention"]) != key:
            out.append({"phase": key[0], "attention": key[1], "from": row["iteration"], "steps": 0, "_acc": {}})
        seg = out[-1]
        seg["steps"] += 1
        for key, stats in row.items():
            if isinstance(stats, dict):
                for k, v in stats.items():
                    if v is not None:
                        acc = seg["_acc"].setdefault(key, {}).setdefault(k, [0.0, 0])
                        acc[0], acc[1] = acc[0] + v, acc[1] + 1
    for seg in out:
        for key, stats in sorted(seg.pop("_acc").items()):
            seg[key] = {k: round(s / n, 4) for k, (s, n) in stats.items()}
    return out


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    add_scene_args(p, "agg")
    p.add_argument("--until", type=int, default=None)
    args = p.parse_args(argv)
    work = Path(args.work)
    cfg, tag = probe_config(args.preset, args.set)
    bundle = synth_bundle(work, args.seed, args.noise, args.frames, args.width, args.height)
    for name, ablate in suite_runs(args, "semgrad", tag):
        rows = train_with_semgrad(bundle, work / "scenes" / name, cfg, ablate, args.until,
                                  work / "semgrad" / f"{name}.jsonl")
        summary = phase_means(rows)
        (work / "semgrad" / f"{name}.summary.json").write_text(json.dumps(summary, indent=1))
        print(name)
        for seg in summary:
            groups = "  ".join(f"{k} " + "/".join(f"{seg[k].get(s, float('nan')):.3f}" for s in STATS)
                               for k in seg if isinstance(seg[k], dict))
            print(f"  {seg['phase']:5s} M_{seg['attention']} from {seg['from']:5d} ({seg['steps']:3d} steps)  {groups}",
                  flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
