"""``twohr-lab STUDY [options]``: the lab's stand-alone studies under one console script.

``twohr-lab vo_bench --repeats 3`` is ``python -m twohr_lab.tracking.vo_bench --repeats 3``; each study keeps
its own options (``twohr-lab STUDY --help``) and its own stamp. The lab's other commands (bench, features,
yolo, matcher) are subcommands of ``twohr``, added through the ``twohr.commands`` entry-point group.
"""

from __future__ import annotations

import importlib
import sys

#: Study name -> module whose ``main(argv)`` runs it.
STUDIES = {
    "accuracy": "twohr_lab.tracking.accuracy",
    "architecture": "twohr_lab.architecture",
    "consistency": "twohr_lab.tracking.consistency",
    "sensitivity": "twohr_lab.tracking.sensitivity",
    "vo_bench": "twohr_lab.tracking.vo_bench",
}


def usage() -> str:
    lines = ["usage: twohr-lab STUDY [options]   (twohr-lab STUDY --help for a study's options)", "", "studies:"]
    lines += [f"  {name:14} python -m {module}" for name, module in STUDIES.items()]
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    if not argv or argv[0] in ("-h", "--help"):
        print(usage())
        return 0 if argv else 2
    if argv[0] not in STUDIES:
        print(f"{usage()}\n\ntwohr-lab: error: unknown study {argv[0]!r}", file=sys.stderr)
        return 2
    return int(importlib.import_module(STUDIES[argv[0]]).main(argv[1:]) or 0)


if __name__ == "__main__":
    sys.exit(main())
