"""Runs bench/render.py over the standard matrix and prints a Markdown table for docs/BENCHMARKS.md.

    python bench/render_matrix.py [--backend cpu] [--device cpu] [--sizes 320x96,640x192] [--n 10000,50000,200000]
                                  [--sh 0,1]

Each configuration runs in its own process (so peak RSS is per configuration); scenes are generated once into
a temporary folder with ``render.py --generate``.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
from pathlib import Path

HERE = Path(__file__).resolve().parent


def run(args: list[str]) -> dict:
    out = subprocess.run([sys.executable, str(HERE / "render.py"), *args], check=True, capture_output=True, text=True)
    return json.loads(out.stdout.strip().splitlines()[-1])


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--backend", default="cpu", choices=["auto", "cpu", "cuda", "torch"])
    p.add_argument("--device", default="cpu", help="torch device (cpu, cuda, ...)")
    p.add_argument("--sizes", default="320x96,640x192")
    p.add_argument("--n", default="10000,50000,200000")
    p.add_argument("--sh", default="0,1")
    p.add_argument("--repeats", type=int, default=7)
    a = p.parse_args()
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for size in a.sizes.split(","):
            w, h = (int(v) for v in size.split("x"))
            for n in (int(v) for v in a.n.split(",")):
                for sh in (int(v) for v in a.sh.split(",")):
                    scene = os.path.join(tmp, f"s_{w}x{h}_{n}_{sh}.npz")
                    run(["--generate", scene, "--width", str(w), "--height", str(h), "--n", str(n), "--sh", str(sh)])
                    r = run(["--scene", scene, "--backend", a.backend, "--device", a.device,
                             "--repeats", str(a.repeats)])
                    rows.append(r)
                    print(json.dumps(r), file=sys.stderr, flush=True)
    gpu = a.device.startswith("cuda")
    print("| resolution | Gaussians | SH | backend | forward ms | forward+backward ms | peak RSS MB |"
          + (" peak GPU MB |" if gpu else ""))
    print("|---|---:|---:|---|---:|---:|---:|" + ("---:|" if gpu else ""))
    for r in rows:
        print(f"| {r['width']}×{r['height']} | {r['n']:,} | {r['sh_degree']} | {r['backend']} | {r['forward_ms']} "
              f"| {r['forward_backward_ms']} | {r['peak_rss_mb']} |" + (f" {r['peak_gpu_mb']} |" if gpu else ""))
    return 0


if __name__ == "__main__":
    sys.exit(main())
