"""``agg synth``: generate a synthetic driving clip with exact ground truth and write it as a scene bundle.

The bundle holds the (optionally corrupted) priors; ``BUNDLE/gt/`` holds the exact ground truth. See docs/SYNTH.md.
The flags ``--seed --frames --noise-translation --missed --false -o`` are a stable interface.
"""

from __future__ import annotations

import argparse
import sys


def add_parser(subparsers) -> None:
    p = subparsers.add_parser(
        "synth", help="generate a synthetic driving clip with exact ground truth (scene bundle + gt/)",
        description="Ray-cast a procedural driving scene (road, buildings, cars, pedestrians), corrupt its priors "
                    "with the given noise and write a scene bundle with the exact ground truth in BUNDLE/gt/.")
    p.add_argument("-o", "--output", required=True, metavar="BUNDLE", help="output bundle folder")
    p.add_argument("--seed", type=int, default=0, help="scene seed (default 0)")
    p.add_argument("--frames", type=int, default=24, help="number of frames (default 24)")
    p.add_argument("--fps", type=float, default=10.0, help="frame rate (default 10)")
    p.add_argument("--width", type=int, default=160, help="image width in pixels (default 160)")
    p.add_argument("--height", type=int, default=96, help="image height in pixels (default 96)")
    p.add_argument("--hfov", type=float, default=80.0, help="horizontal field of view in degrees (default 80)")
    p.add_argument("--sky", action=argparse.BooleanOptionalAction, default=True,
                   help="far-field sky gradient (--no-sky: black far field)")
    p.add_argument("--cars", type=int, default=3, help="moving cars (default 3)")
    p.add_argument("--parked", type=int, default=4, help="parked cars (default 4)")
    p.add_argument("--pedestrians", type=int, default=3, help="pedestrians (default 3)")
    p.add_argument("--ego-speed", type=float, default=8.0, help="ego speed in m/s (default 8)")
    g = p.add_argument_group("noise (the priors; the gt/ sidecar stays exact)")
    g.add_argument("--noise-seed", type=int, default=None, help="seed of the corruption (default: --seed)")
    g.add_argument("--noise-translation", type=float, default=0.0, metavar="M",
                   help="max camera translation noise in metres (uniform direction, |t| ~ U[0, M]; frame 0 exact)")
    g.add_argument("--noise-rotation-deg", type=float, default=0.0, metavar="A",
                   help="max camera rotation noise in degrees (uniform axis, angle ~ U[0, A]; frame 0 exact)")
    g.add_argument("--noise-agent", type=float, default=0.0, metavar="M",
                   help="max agent box-centre noise in metres per valid tracklet entry")
    g.add_argument("--noise-agent-yaw-deg", type=float, default=0.0, metavar="Y",
                   help="agent yaw noise ~ U[-Y, Y] degrees")
    g.add_argument("--boxes-follow-cameras", action="store_true",
                   help="lift the tracklet boxes through the noisy cameras (each carries its frame's camera error)")
    g.add_argument("--missed", type=int, default=0, metavar="K",
                   help="drop K agents from the priors (moving cars first, most visible first)")
    g.add_argument("--false", type=int, default=0, metavar="K", help="add K false agents to the priors")
    g.add_argument("--depth-noise", type=float, default=0.0, metavar="S",
                   help="relative depth noise std: d' = d (1 + S n), n ~ N(0, 1)")
    g.add_argument("--depth-keep", type=float, default=1.0, metavar="F",
                   help="fraction of valid depth pixels kept per frame (default 1)")
    g.add_argument("--depth-format", choices=("dense", "sparse", "none"), default="dense",
                   help="how the depth prior is stored (default dense)")
    g.add_argument("--feature-noise", type=float, default=0.0, metavar="S",
                   help="std of Gaussian noise added to every feature element")
    p.add_argument("--overwrite", action="store_true", help="replace an existing bundle folder")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from agg.synth.corrupt import NoiseConfig
    from agg.synth.scene import SceneConfig
    from agg.synth.suite import generate, write_bundle

    try:
        cfg = SceneConfig(seed=args.seed, frames=args.frames, fps=args.fps, width=args.width, height=args.height,
                          hfov_deg=args.hfov, sky=args.sky, moving_cars=args.cars, parked_cars=args.parked,
                          pedestrians=args.pedestrians, ego_speed=args.ego_speed)
        noise = NoiseConfig(seed=args.seed if args.noise_seed is None else args.noise_seed,
                            camera_translation_max=args.noise_translation,
                            camera_rotation_max_deg=args.noise_rotation_deg, agent_translation_max=args.noise_agent,
                            agent_yaw_max_deg=args.noise_agent_yaw_deg, missed=args.missed, false=args.false,
                            depth_rel_sigma=args.depth_noise, depth_keep_fraction=args.depth_keep,
                            feature_sigma=args.feature_noise, boxes_follow_cameras=args.boxes_follow_cameras)
        gt, priors = generate(cfg, noise)
        write_bundle(args.output, gt, priors, noise, depth_format=args.depth_format, overwrite=args.overwrite)
    except ValueError as exc:  # bad settings, or an existing bundle without --overwrite
        print(f"agg synth: error: {exc}", file=sys.stderr)
        return 2
    print(f"wrote {args.output}: {cfg.frames} frames {cfg.width}x{cfg.height}, {len(gt.agent_ids)} agents, "
          f"{len(priors.track_ids)} prior tracks (missed {priors.missed_ids}, false {priors.false_ids}); "
          f"ground truth in {args.output}/gt")
    return 0
