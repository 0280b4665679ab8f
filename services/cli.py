"""The ``twohr`` command line: a thin shell over the library, the service cores and the lab's studies.

Modules contribute subcommands through a ``register(subparsers)`` function: the pipeline, the launcher
and the camera here (:data:`COMMAND_MODULES`); other installed packages through the ``twohr.commands``
entry-point group (:data:`COMMAND_GROUP`), which is how the lab adds its offline studies (benches, feature
and mask evaluation, matcher training) without this module naming it. Handlers import their heavy
dependencies lazily so that ``twohr --help`` stays fast.
"""

from __future__ import annotations

import argparse
import importlib
import json
import logging
import sys
from collections.abc import Callable
from importlib.metadata import entry_points
from pathlib import Path

from twohr.errors import TwohrError
from twohr.paths import DEV_SEQUENCE

#: The command line's own modules that add subcommands, each under the order key that places it in ``--help``.
COMMAND_MODULES = {
    "10-run": "twohr_services.pipeline_cli",
    "15-maps": "twohr_services.maps_cli",
    "60-up": "twohr_services.launcher_cli",
    "70-camera": "twohr_services.camera_cli",
}

#: The entry-point group through which installed packages add subcommands. An entry's value is a
#: ``register(subparsers)`` function (``module:register``) or a module that has one; its name is the order key,
#: sorted together with those of :data:`COMMAND_MODULES` (the lab: 20-bench, 30-features, 40-yolo, 50-matcher).
COMMAND_GROUP = "twohr.commands"


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


def _eval(args: argparse.Namespace) -> int:
    from twohr.dataset import load_gt_extrinsic
    from twohr.evaluation import evaluate
    from twohr.plots import plot_trajectories
    from twohr.trajectory import read_tum

    name, left, right = load_gt_extrinsic(args.gt_extrinsic)
    gt = read_tum(args.gt).transformed(left, right)
    if Path(args.est).suffix == ".mcap":
        from .recorder.core import recorded_trajectory

        est = recorded_trajectory(args.est, args.robot)
    else:
        est = read_tum(args.est)
    try:
        report, arrays = evaluate(gt, est, align=args.align, max_dt=args.max_dt, gt_extrinsic=name)
    except ValueError as exc:
        raise TwohrError(str(exc)) from None
    print(format_report(report))
    if args.json:
        Path(args.json).parent.mkdir(parents=True, exist_ok=True)
        Path(args.json).write_text(report.model_dump_json(indent=2))
        print(f"report: {args.json}")
    if args.plot:
        plot_trajectories(args.plot, arrays["gt"], arrays["est"], arrays["ate"],
                          title=f"{Path(args.est).name} vs {Path(args.gt).name}")
        print(f"plot:   {args.plot}")
    return 0


def format_report(report) -> str:
    """A short human-readable block for an :class:`~twohr.evaluation.EvaluationReport`."""
    a, r1, rs = report.ate, report.rpe_frame, report.rpe_1s
    return "\n".join([
        f"ATE ({report.align}, max dt {report.max_dt} s, gt extrinsic {report.gt_extrinsic}): "
        f"RMSE {a.rmse:.4f} m  mean {a.mean:.4f}  median {a.median:.4f}  std {a.std:.4f}  max {a.max:.4f}",
        f"RPE trans: per frame RMSE {r1.rmse:.4f} m, over 1 s RMSE {rs.rmse:.4f} m"
        + (f"; jitter RMSE {report.jitter.rmse:.4f} m" if report.jitter is not None else "")
        + (f"; Sim(3) scale {report.sim3_scale:.4f}" if report.sim3_scale is not None else ""),
        f"paired {report.matched} of {report.estimate_poses} estimate poses; GT coverage {report.gt_coverage:.1f} %"
        + (f"; scale {report.scale:.4f}" if report.align == "sim3" else ""),
    ])


def _synth(args: argparse.Namespace) -> int:
    from twohr.synthetic import SyntheticSpec, generate

    spec = SyntheticSpec(frames=args.frames, width=args.width, height=args.height, occluders=args.occluders,
                         seed=args.seed)
    out = generate(args.out, spec)
    print(json.dumps({"sequence": str(out), "frames": spec.frames, "size": [spec.width, spec.height]}))
    return 0


def _version() -> str:
    from importlib.metadata import PackageNotFoundError, version

    try:
        return version("twohr")
    except PackageNotFoundError:  # run from a source tree that was never installed
        return "unknown"


def _registrar(target) -> Callable[[argparse._SubParsersAction], None]:
    """The ``register`` function itself, or the one of a module."""
    return target if callable(target) else target.register


def command_registrars() -> list[tuple[str, Callable[[argparse._SubParsersAction], None]]]:
    """(order key, ``register(subparsers)``) of every subcommand module, ours and the entry points', in order.

    An entry point whose package is not installed (e.g. an image without the lab) is left out."""
    found = [(key, _registrar(importlib.import_module(name))) for key, name in COMMAND_MODULES.items()]
    for entry in entry_points(group=COMMAND_GROUP):
        try:
            found.append((entry.name, _registrar(entry.load())))
        except ModuleNotFoundError as exc:
            if exc.name is None or not (entry.module == exc.name or entry.module.startswith(exc.name + ".")):
                raise  # a dependency of an installed module is missing: a real error
    return sorted(found, key=lambda item: item[0])


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="twohr",
        description="2HR-Net visual SLAM for dynamic scenes: run it, evaluate it, serve it on Zenoh.",
        formatter_class=argparse.RawDescriptionHelpFormatter,
        epilog=f"Start with `twohr run --sequence {DEV_SEQUENCE}`. "
        "Every subcommand has its own --help.",
    )
    parser.add_argument("-v", "--verbose", action="store_true", help="debug logging")
    parser.add_argument("--version", action="version", version=f"%(prog)s {_version()}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")

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

    p = sub.add_parser("eval", help="ATE/RPE of a trajectory against ground truth (TUM/evo conventions)",
                       description="ATE after Umeyama alignment and translational RPE, as evo_ape/evo_rpe "
                       "compute them. Trajectories are TUM text files; --est may also be a session recording "
                       "(.mcap), whose poses are scored.")
    p.add_argument("--gt", required=True, help="ground-truth trajectory (TUM format)")
    p.add_argument("--est", required=True, help="estimated trajectory (TUM format, or a twohr .mcap recording)")
    p.add_argument("--robot", default=None, help="with an .mcap holding several robots: whose poses to score")
    p.add_argument("--align", choices=["se3", "sim3", "none"], default="se3", help="alignment (default se3)")
    p.add_argument("--max-dt", type=float, default=0.02, help="association window in seconds (default 0.02)")
    p.add_argument("--gt-extrinsic", default="none",
                   help="fixed sensor extrinsic for the ground truth: none, bonn, or a 4x4 matrix file")
    p.add_argument("--json", help="write the report as JSON here")
    p.add_argument("--plot", help="write a PNG with top/side views and ATE over time here")
    p.set_defaults(func=_eval)

    p = sub.add_parser("synth", help="generate a synthetic RGB-D sequence with exact ground truth")
    p.add_argument("--out", required=True, help="output folder (TUM layout)")
    p.add_argument("--frames", type=int, default=60)
    p.add_argument("--width", type=int, default=320)
    p.add_argument("--height", type=int, default=240)
    p.add_argument("--occluders", type=int, default=1, help="moving boxes that play people")
    p.add_argument("--seed", type=int, default=0)
    p.set_defaults(func=_synth)

    for _, register in command_registrars():
        register(sub)
    return parser


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    args.argv = list(sys.argv[1:] if argv is None else argv)  # the exact command, for the studies' stamps
    logging.basicConfig(level=logging.DEBUG if args.verbose else logging.INFO,
                        format="%(levelname)s %(name)s: %(message)s")
    if not args.verbose:
        logging.getLogger("httpx").setLevel(logging.WARNING)  # one INFO line per request drowns the output
    if not getattr(args, "func", None):
        parser.print_help()
        return 2
    try:
        return int(args.func(args) or 0)
    except TwohrError as exc:
        print(f"twohr: error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("twohr: interrupted", file=sys.stderr)
        return 130
    except BrokenPipeError:  # e.g. `twohr eval … | head`
        sys.stderr.close()
        return 0


if __name__ == "__main__":
    sys.exit(main())
