"""The README's main job (`agg demo`) runs end to end on the bundled clip and writes what it promises."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

from PIL import Image

ROOT = Path(__file__).resolve().parents[1]


def test_demo_fits_the_sample_frame(tmp_path):
    out = tmp_path / "demo"
    proc = subprocess.run(
        [sys.executable, "-m", "agg.cli", "demo", "--steps", "60", "--gaussians", "3000", "--width", "128",
         "--out", str(out)],
        cwd=ROOT, capture_output=True, text=True, timeout=300,
    )
    assert proc.returncode == 0, proc.stderr[-2000:]
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["backend"] == "cpu" and metrics["width"] == 128 and metrics["height"] == 72
    assert metrics["psnr_db"] > 25.0
    panel = Image.open(out / "fit.png")
    assert panel.size == (3 * 128, 72)
    assert "fitting 3000 Gaussians" in proc.stderr  # the progress bar
