"""A sequence played backwards: the same frames in reverse order, timestamps mirrored (issue 41's held-out variant);
or played several times in a row (``--repeat N``: a long session that keeps coming back to the places it mapped).

``python -m twohr_lab.tracking.backwards --sequence ../shared/data/rgbd_bonn_crowd_dev --out runs/seq/backwards``

Every timestamp ``t`` becomes ``first + last - t`` (so the variant spans the same times and keeps the frame
spacing), ``rgb.txt``, ``depth.txt``, ``associations.txt`` and ``groundtruth.txt`` are rewritten in the new order,
the image folders are linked, not copied, and ``camera.yaml`` (if any) is copied. The output folder's name keeps
the source's (the camera preset is chosen from it, e.g. ``rgbd_bonn``) with ``_backwards`` appended.

With ``--repeat N`` the lists are written N times, each pass's timestamps after the one before by the sequence's
span plus one frame spacing, into ``<name>_x<N>``.
"""

from __future__ import annotations

import argparse
from pathlib import Path

LISTS = ("rgb.txt", "depth.txt", "groundtruth.txt", "associations.txt")


def _rows(path: Path) -> tuple[list[str], list[list[str]]]:
    header, rows = [], []
    for line in path.read_text().splitlines():
        (header if line.startswith("#") or not line.strip() else rows).append(line if line.startswith("#")
                                                                             else line.split())
    return [h for h in header if h], rows


def _linked(sequence: Path, target: Path) -> Path:
    """``target`` with the image folders of ``sequence`` linked and its camera file copied."""
    target.mkdir(parents=True, exist_ok=True)
    for folder in ("rgb", "depth"):
        link = target / folder
        if not link.exists():
            link.symlink_to(sequence / folder, target_is_directory=True)
    if (sequence / "camera.yaml").is_file():
        (target / "camera.yaml").write_text((sequence / "camera.yaml").read_text())
    return target


def _rewrite_lists(sequence: Path, target: Path, retime) -> None:
    """Write each list of ``sequence`` into ``target`` as ``retime(rows, stamp)`` orders and re-stamps its rows
    (``stamp(row, column, value)`` writes ``value`` into a stamp column at the original's precision)."""
    for name in LISTS:
        if not (sequence / name).is_file():
            continue
        header, rows = _rows(sequence / name)
        columns = (0, 2) if name == "associations.txt" else (0,)

        def stamp(row: list[str], to, columns: tuple[int, ...] = columns) -> list[str]:
            row = list(row)
            for column in columns:
                row[column] = f"{to(float(row[column])):.{len(row[column].partition('.')[2])}f}"
            return row

        (target / name).write_text("\n".join([*header, *(" ".join(row) for row in retime(rows, stamp))]) + "\n")


def backwards(sequence: Path, out: Path) -> Path:
    """Write the backwards variant of ``sequence`` into ``out / (<name>_backwards)`` and return that folder."""
    sequence = sequence.resolve()
    stamps = [float(r[0]) for r in _rows(sequence / "rgb.txt")[1]]
    mirror = min(stamps) + max(stamps)
    target = _linked(sequence, out / f"{sequence.name}_backwards")
    _rewrite_lists(sequence, target, lambda rows, stamp: sorted(
        (stamp(row, lambda t: mirror - t) for row in rows), key=lambda row: float(row[0])))
    return target


def repeated(sequence: Path, out: Path, times: int) -> Path:
    """Write ``sequence`` played ``times`` times in a row into ``out / (<name>_x<times>)`` and return that folder."""
    if times < 1:
        raise ValueError(f"--repeat needs at least 1 pass, not {times}")
    sequence = sequence.resolve()
    stamps = sorted(float(r[0]) for r in _rows(sequence / "rgb.txt")[1])
    spacing = (stamps[-1] - stamps[0]) / max(1, len(stamps) - 1)
    period = stamps[-1] - stamps[0] + spacing
    target = _linked(sequence, out / f"{sequence.name}_x{times}")
    _rewrite_lists(sequence, target, lambda rows, stamp: [
        stamp(row, lambda t, k=k: t + k * period) for k in range(times) for row in rows])
    return target


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m twohr_lab.tracking.backwards", description=__doc__.split("\n")[0])
    parser.add_argument("--sequence", required=True, help="TUM-layout RGB-D folder")
    parser.add_argument("--out", default="runs/sequences", help="parent folder of the variant")
    parser.add_argument("--repeat", type=int, default=None, metavar="N", help="play the sequence N times in a row "
                        "(forwards) instead of once backwards")
    args = parser.parse_args(argv)
    if args.repeat is not None:
        print(repeated(Path(args.sequence), Path(args.out), args.repeat))
    else:
        print(backwards(Path(args.sequence), Path(args.out)))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
