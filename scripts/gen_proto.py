#!/usr/bin/env python
"""Generate the Python gRPC code for proto/agg/v1 into worker/_gen/ (git-ignored; never edit it by hand).

The worker also does this on first use; run this at image build time (or after editing a .proto) to do it
eagerly. ``--force`` regenerates even when the stamp says the code is current; ``--check`` only reports.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from worker import grpc_codegen  # noqa: E402


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--force", action="store_true", help="regenerate even when current")
    p.add_argument("--check", action="store_true", help="exit 1 when the generated code is missing or stale")
    args = p.parse_args()
    if args.check:
        ok = grpc_codegen.is_current()
        print("worker/_gen is current" if ok else "worker/_gen is missing or stale")
        return 0 if ok else 1
    out = grpc_codegen.generate() if args.force else grpc_codegen.ensure_generated()
    print(f"generated {sorted(f.name for f in out.glob('*.py'))} in {out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
