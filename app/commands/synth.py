"""``twohr synth``: a synthetic RGB-D sequence with exact ground truth (for fast tests and demos)."""

from __future__ import annotations

import argparse
import json


def _synth(args: argparse.Namespace) -> int:
    from twohr.synthetic import SyntheticSpec, generate

    spec = SyntheticSpec(frames=args.frames, width=args.width, height=args.height, occluders=args.occluders,
                         seed=args.seed)
    out = generate(args.out, spec)
    print(json.dumps({"sequence": str(out), "frames": spec.frames, "size": [spec.width, spec.height]}))
    return 0


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("synth", help="generate a synthetic RGB-D sequence with exact ground truth")
    p.add_argument("--out", required=True, help="output folder (TUM layout)")
    p.add_argument("--frames", type=int, default=60)
    p.add_argument("--width", type=int, default=320)
    p.add_argument("--height", type=int, default=240)
    p.add_argument("--occluders", type=int, default=1, help="moving boxes that play people")
    p.add_argument("--seed", type=int, default=0)
    p.set_defaults(func=_synth)
