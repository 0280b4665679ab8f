"""``twohr models``: list, fetch or verify the registered models, and the inference backends this machine runs."""

from __future__ import annotations

import argparse
import sys

from twohr.errors import TwohrError


def _models(args: argparse.Namespace) -> int:
    from twohr import models

    if args.action == "backends":
        available = models.available_backends()
        for backend in models.BACKENDS[1:]:
            state = "available" if backend in available else f"not here: needs {models.WHAT_IT_NEEDS[backend]}"
            print(f"{backend:13} {state}")
        print(f"auto = {available[0] if available else 'none'}")
        return 0
    if args.action == "auto":
        return _auto(args)
    if args.action == "list":
        print(f"{'name':24} {'kind':10} {'file':26} {'status':10} licence")
        for name, spec in models.registry().items():
            status = "cached" if (models.cache_dir() / spec.file).is_file() or spec.bundled else "-"
            print(f"{name:24} {spec.kind:10} {spec.file:26} {status:10} {spec.licence}")
        return 0
    names = getattr(args, "names", None) or list(models.registry())
    failed = 0
    for name in names:
        try:
            path = models.fetch(name, force=args.force) if args.action == "fetch" else None
            if args.action == "verify":
                path = models.local_file(name)
                models.verify_file(models.get_spec(name), path)
            print(f"ok      {name:24} {path}")
        except TwohrError as exc:
            failed += 1
            print(f"FAILED  {name:24} {exc}", file=sys.stderr)
    return 1 if failed else 0


def _auto(args: argparse.Namespace) -> int:
    """Which network ``detector.model=auto`` uses on this host for VGA frames, timing the candidates if no choice is
    kept (or ``--again``)."""
    from twohr.config import DetectorConfig
    from twohr_services.detector.auto import auto_choices_path
    from twohr_services.detector.core import R2D2Detector

    path = auto_choices_path()
    if args.again:
        path.unlink(missing_ok=True)
    try:
        detector = R2D2Detector(DetectorConfig(model="auto", precision=args.precision))
        chosen = detector.network.model  # reads the kept choice, or times every candidate and keeps the fastest
    except TwohrError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 1
    print(f"detector.model=auto uses {chosen} on this host (precision {args.precision}, timed "
          f"{detector.model_timed_at}; kept in {path})")
    for name, ms in detector.model_timings_ms.items():
        print(f"  {name:24} {ms:7.1f} ms{'  <- chosen' if name == chosen else ''}")
    return 0


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("models", help="list, fetch or verify the registered models",
                       description="Models come from $TWOHR_MODEL_MIRROR (default ../shared/models) or their "
                       "official URL, into $TWOHR_CACHE/models, and are checked by sha256.")
    actions = p.add_subparsers(dest="action", metavar="ACTION", required=True)
    actions.add_parser("list", help="every registered model, its licence and whether it is cached")
    q = actions.add_parser("auto", help="which keyframe network detector.model=auto uses on this host, and why",
                           description="auto times every keyframe network that meets the quality floor once per "
                           "host (CPU, backend, precision, threads, size, model versions) and keeps the fastest in "
                           "$TWOHR_CACHE/models/auto-choices.json; every later process uses that choice.")
    q.add_argument("--again", action="store_true", help="forget the kept choices and time the networks again")
    q.add_argument("--precision", default="auto", choices=("auto", "f32", "bf16"),
                   help="the detector.precision to choose for (default: auto)")
    actions.add_parser("backends", help="the inference backends (CPU and GPU) this machine can run, and auto's pick")
    for action, text in (("fetch", "copy or download models into the cache and check them"),
                         ("verify", "check the sha256 of cached (or mirrored) models")):
        q = actions.add_parser(action, help=text, description=text)
        q.add_argument("names", nargs="*", metavar="NAME", help="model names (default: all)")
        if action == "fetch":
            q.add_argument("--force", action="store_true", help="fetch again even when cached")
    p.set_defaults(func=_models)
