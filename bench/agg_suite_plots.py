"""The PNG plots of ``bench/agg_suite.py`` runs in docs/: PSNR against camera noise (AGG and the baseline, per
preset), and the preset trade (PSNR against training time, marker size the Gaussian count)."""

from __future__ import annotations

from collections import defaultdict
from pathlib import Path

import numpy as np

from bench.agg_suite_report import synth_presets


def plots(runs: list[dict], docs: Path) -> list[str]:
    """Writes the plots the runs allow into ``docs``; returns their file names."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    made = []
    synth = [r for r in runs if r["kind"] == "synth" and r["variant"] in ("agg", "baseline")]
    if synth:
        fig, axes = plt.subplots(1, 2, figsize=(9, 3.4))
        for ax, key, title in ((axes[0], "psnr", "full image"), (axes[1], "psnr_agents", "agent regions")):
            for (v, preset), style in zip([(v, p) for p in synth_presets(synth) for v in ("agg", "baseline")],
                                          ("o-", "s--", "^-", "v--")):
                rows = defaultdict(list)
                for r in synth:
                    if (r["variant"], r["preset"]) == (v, preset) and r["metrics"].get(key) is not None:
                        rows[r["noise"]].append(r["metrics"][key])
                xs = sorted(rows)
                if xs:
                    ax.plot(xs, [np.mean(rows[x]) for x in xs], style,
                            label=f"{'AGG' if v == 'agg' else 'baseline'}, {preset}")
            ax.set_xlabel("camera pose noise bound (m)")
            ax.set_ylabel("NVS PSNR (dB)")
            ax.set_title(title)
            ax.grid(alpha=0.3)
            ax.legend()
        fig.tight_layout()
        fig.savefig(docs / "agg_noise.png", dpi=110)
        plt.close(fig)
        made.append("agg_noise.png")
    presets = [r for r in runs if r["kind"] == "preset"]
    if presets:
        fig, ax = plt.subplots(figsize=(4.5, 3.4))
        for r in presets:
            ax.scatter(r["summary"]["seconds_train"], r["metrics"]["psnr"], s=20 + r["metrics"]["n_gaussians"] / 1000)
            ax.annotate(r["preset"], (r["summary"]["seconds_train"], r["metrics"]["psnr"]))
        ax.set_xlabel("training time (s; one thread, beside one other run on 2 cores)")
        ax.set_ylabel("NVS PSNR (dB)")
        ax.set_title("presets (marker size: Gaussians)")
        ax.grid(alpha=0.3)
        fig.tight_layout()
        fig.savefig(docs / "agg_presets.png", dpi=110)
        plt.close(fig)
        made.append("agg_presets.png")
    return made
