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
                spec = models.get_spec(name)
                path = models._bundled_path(spec) or models.cache_dir() / spec.file
                if not path.is_file():
                    mirror = next((m / spec.file for m in models.mirror_dirs() if (m / spec.file).is_file()), path)
                    path = mirror
                models.verify_file(spec, path)
            print(f"ok      {name:24} {path}")
        except TwohrError as exc:
            failed += 1
            print(f"FAILED  {name:24} {exc}", file=sys.stderr)
    return 1 if failed else 0


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("models", help="list, fetch or verify the registered models",
                       description="Models come from $TWOHR_MODEL_MIRROR (default ../shared/models) or their "
                       "official URL, into $TWOHR_CACHE/models, and are checked by sha256.")
    actions = p.add_subparsers(dest="action", metavar="ACTION", required=True)
    actions.add_parser("list", help="every registered model, its licence and whether it is cached")
    actions.add_parser("backends", help="the inference backends (CPU and GPU) this machine can run, and auto's pick")
    for action, text in (("fetch", "copy or download models into the cache and check them"),
                         ("verify", "check the sha256 of cached (or mirrored) models")):
        q = actions.add_parser(action, help=text, description=text)
        q.add_argument("names", nargs="*", metavar="NAME", help="model names (default: all)")
        if action == "fetch":
            q.add_argument("--force", action="store_true", help="fetch again even when cached")
    p.set_defaults(func=_models)
