"""``agg prototypes``: build a prototype bank (B_rigid, B_non-rigid, B_bg) from a labelled image folder.

The bank (.npz, raw descriptor space of the chosen backend) is what ``agg priors --prototypes BANK.npz`` takes.
Folder layouts and the Cityscapes label-id mapping: ``agg.priors.prototypes`` and docs/PRIORS.md.
"""

from __future__ import annotations

import argparse
import sys


def add_parser(subparsers) -> None:
    p = subparsers.add_parser(
        "prototypes", help="build a semantic prototype bank from a labelled folder (Cityscapes label ids)",
        description="Extract features (builtin or DINO) of every labelled image, group the feature cells by class "
                    "(Cityscapes ids: person/rider -> non-rigid; car, truck, bus, caravan, trailer, train, "
                    "motorcycle, bicycle -> rigid; other ids except 0-3 -> background) and write k-means "
                    "centroids per class as an .npz bank.")
    p.add_argument("folder", metavar="FOLDER",
                   help="X_leftImg8bit.png + X_gtFine_labelIds.png anywhere below it, or images/X.png + labels/X.png")
    p.add_argument("-o", "--output", required=True, metavar="BANK.npz", help="output bank file")
    p.add_argument("--backend", choices=("builtin", "dino"), default="builtin",
                   help="feature backend (default builtin)")
    p.add_argument("--weights", metavar="PATH", default=None,
                   help="dino: save_pretrained folder or weights file next to its config.json")
    p.add_argument("--device", default="cpu", help="dino: torch device (default cpu)")
    p.add_argument("--per-class", type=int, default=8, metavar="N", help="prototypes per class (default 8)")
    p.add_argument("--samples-per-class", type=int, default=20000, metavar="N",
                   help="feature cells per class clustered (default 20000)")
    p.add_argument("--max-images", type=int, default=None, metavar="N", help="use only the first N pairs")
    p.add_argument("--seed", type=int, default=0, help="sampling and k-means seed (default 0)")
    p.add_argument("--overwrite", action="store_true", help="replace an existing output file")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from pathlib import Path

    from agg.priors.features import FeatureConfig, make_extractor
    from agg.priors.prototypes import prototypes_from_labelled_folder, save_prototype_bank

    out = Path(args.output)
    try:
        if out.exists() and not args.overwrite:
            raise ValueError(f"{out} exists (use --overwrite)")
        if args.per_class < 1 or args.samples_per_class < 1:
            raise ValueError("--per-class and --samples-per-class must be >= 1")
        extractor = make_extractor(FeatureConfig(backend=args.backend, weights=args.weights, device=args.device))
        bank = prototypes_from_labelled_folder(args.folder, extractor, n_per_class=args.per_class, seed=args.seed,
                                               samples_per_class=args.samples_per_class, max_images=args.max_images)
        save_prototype_bank(out, bank)
    except ValueError as exc:  # bad folder, weights, bank or settings
        print(f"agg prototypes: error: {exc}", file=sys.stderr)
        return 2
    sizes = ", ".join(f"{k} {v.shape[0]}" for k, v in bank.items())
    print(f"wrote {out}: backend {bank.meta['backend']} (D_in {bank.meta['D_in']}), {bank.meta['n_images']} images, "
          f"prototypes {sizes}")
    return 0
