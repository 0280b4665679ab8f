"""``twohr vocab train | list | eval``: the place-recognition vocabulary that loop closing searches with.

``train`` clusters the 2HR descriptors of a sequence's frames (k-means) into a vocabulary, writes it with its
model card under ``--out`` and installs it where sessions find it by name (``loop_closing.vocabulary``).
``eval`` scores place recognition on frames the vocabulary was not trained on: for every query frame, is the
most similar frame at least ``--min-gap`` frames away really the same place (ground truth within 0.3 m and 15°)?
Keypoints come from the matcher study's cache (``runs/matcher_cache``), so each frame is detected once.
"""

from __future__ import annotations

import argparse
import json
import shutil
import time
from pathlib import Path

from twohr.config import SAME_PLACE_DEG, SAME_PLACE_M
from twohr.paths import DEV_SEQUENCE

from ..stamp import provenance


def _frames(args: argparse.Namespace) -> list[int]:
    """The --start, --frames (a count) and --step frames of --sequence."""
    from twohr.dataset import RGBDSequence
    from twohr.errors import ConfigError

    length = len(RGBDSequence(args.sequence))
    frames = list(range(args.start, min(length, args.start + args.frames), max(1, args.step)))
    if not frames or args.step < 1:
        raise ConfigError(f"--start {args.start} --frames {args.frames} --step {args.step} hold no frame of the "
                          f"{length} in {args.sequence}")
    return frames


def _cache(args: argparse.Namespace, frames: list[int]):
    """The sequence's keypoint cache (the matcher study's), filled for ``frames``."""
    from twohr.config import load_config

    from ..matching.cli import open_cache

    return open_cache(args.sequence, load_config(None, args.set).detector, args.cache, frames)


def _train(args: argparse.Namespace) -> int:
    from twohr.places import Vocabulary, vocabulary_dir, vocabulary_path

    frames = _frames(args)
    cache = _cache(args, frames)
    t0 = time.perf_counter()
    descriptors = [cache.load(i).keypoints.descriptors for i in frames]
    card = {"name": args.name, "sequence": str(Path(args.sequence).resolve().name),
            "frames": f"{frames[0]}-{frames[-1]}",
            "step": args.step, "detector": cache.detector_conf.model_dump(mode="json"), "seed": args.seed,
            "provenance": provenance(), "licence": "derived from R2D2 descriptors (CC BY-NC-SA 3.0): non-commercial"}
    vocabulary = Vocabulary.train(descriptors, args.words, seed=args.seed, card=card)
    vocabulary.card["training_s"] = round(time.perf_counter() - t0, 2)
    out = Path(args.out)
    vocabulary.save(out / f"{args.name}.npz")
    (out / f"{args.name}.md").write_text(model_card(vocabulary.card))
    print(f"vocabulary {args.name}: {vocabulary.size} words from {vocabulary.card['descriptors']} descriptors of "
          f"{len(frames)} frames in {vocabulary.card['training_s']} s -> {out / (args.name + '.npz')}")
    if args.install:
        target = vocabulary_path(args.name)
        target.parent.mkdir(parents=True, exist_ok=True)
        shutil.copyfile(out / f"{args.name}.npz", target)
        shutil.copyfile(out / f"{args.name}.md", target.with_suffix(".md"))
        print(f"installed in {vocabulary_dir()}: sessions use it with --set loop_closing.vocabulary={args.name}")
    return 0


def model_card(card: dict) -> str:
    """The vocabulary's model card, in Markdown."""
    stamp = card.get("provenance", {})
    return "\n".join([
        f"# Vocabulary `{card['name']}`", "",
        "A bag-of-words vocabulary for twohr's place recognition (loop closing, relocalisation candidates): "
        "k-means centres of 2HR (R2D2) descriptors, with each word's inverse document frequency over the "
        "training frames.", "",
        f"- words: {card['words']}, descriptor dimension {card['dimension']}",
        f"- training data: `{card['sequence']}` frames {card['frames']}, step {card['step']} "
        f"({card['documents']} frames, {card['descriptors']} descriptors)",
        f"- detector: `{card['detector']['model']}`, precision {card['detector'].get('precision')}",
        f"- k-means seed {card['seed']}; trained in {card.get('training_s', '?')} s",
        f"- command: `{stamp.get('command', '?')}` at commit `{stamp.get('commit', '?')}`",
        f"- machine: {stamp.get('machine', {}).get('cpu_model', '?')}",
        f"- licence: {card['licence']}", "",
        "Report place-recognition figures only on frames outside the training range (`twohr vocab eval`).", ""])


def _list(args: argparse.Namespace) -> int:
    from twohr.places import Vocabulary, VocabularyError, vocabulary_dir

    print(f"{'name':28} {'words':>6} {'frames':>10}  trained on")
    for path in sorted(vocabulary_dir().glob("*.npz")):
        try:
            card = Vocabulary.load(path).card
        except VocabularyError as exc:
            print(f"{path.stem:28} UNREADABLE: {exc}")
            continue
        print(f"{path.stem:28} {card.get('words', '?'):>6} {card.get('frames', '?'):>10}  {card.get('sequence', '?')}")
    return 0


def _eval(args: argparse.Namespace) -> int:
    import numpy as np

    from twohr.places import Vocabulary, vocabulary_path
    from twohr.pose import pose_difference

    vocabulary = Vocabulary.load(vocabulary_path(args.name))
    frames = _frames(args)
    cache = _cache(args, frames)
    loaded = [cache.load(i) for i in frames]
    loaded = [f for f in loaded if f.pose is not None]
    vectors = np.stack([vocabulary.vector(f.keypoints.descriptors) for f in loaded])
    similarity = vectors @ vectors.T
    rows = []
    for q, frame in enumerate(loaded):
        far = np.array([abs(other.index - frame.index) >= args.min_gap for other in loaded])
        if not far.any():
            continue
        best = int(np.flatnonzero(far)[np.argmax(similarity[q, far])])
        metres, degrees = pose_difference(frame.pose, loaded[best].pose)
        revisits = [j for j in np.flatnonzero(far) if _same(pose_difference(frame.pose, loaded[j].pose))]
        correct = _same((metres, degrees))
        rows.append({"query": frame.index, "best": loaded[best].index, "score": round(float(similarity[q, best]), 4),
                     "distance_m": round(metres, 3), "angle_deg": round(degrees, 2), "same_place": bool(correct),
                     "revisits_available": len(revisits)})
    with_revisit = [r for r in rows if r["revisits_available"]]
    report = {"vocabulary": args.name, "trained_on": vocabulary.card.get("frames"),
              "evaluated_on": f"{frames[0]}-{frames[-1]}",
              "step": args.step, "min_gap": args.min_gap, "queries": len(rows),
              "queries_with_a_revisit": len(with_revisit),
              "top1_same_place": sum(r["same_place"] for r in with_revisit),
              "top1_precision": round(sum(r["same_place"] for r in with_revisit) / max(1, len(with_revisit)), 3),
              "provenance": provenance(), "queries_detail": rows}
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    (out / "place_recognition.json").write_text(json.dumps(report, indent=1))
    print(f"{report['queries_with_a_revisit']} of {report['queries']} query frames have a revisit "
          f">= {args.min_gap} frames away; the top-1 frame is the same place for {report['top1_same_place']} "
          f"(precision {report['top1_precision']}) -> {out / 'place_recognition.json'}")
    return 0


def _same(difference: tuple[float, float]) -> bool:
    return difference[0] <= SAME_PLACE_M and difference[1] <= SAME_PLACE_DEG


def register(sub: argparse._SubParsersAction) -> None:
    vocab = sub.add_parser("vocab", help="train, list and evaluate place-recognition vocabularies",
                           description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    actions = vocab.add_subparsers(dest="vocab_command", metavar="ACTION", required=True)

    def data(p: argparse.ArgumentParser, start: int) -> None:
        p.add_argument("--sequence", default=DEV_SEQUENCE, help="TUM-layout RGB-D folder")
        p.add_argument("--start", type=int, default=start, help="first frame")
        p.add_argument("--frames", type=int, default=280, help="how many frames from --start")
        p.add_argument("--step", type=int, default=2, help="every n-th frame of them")
        p.add_argument("--cache", default="runs/matcher_cache", help="the keypoint cache folder")
        p.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                       help="detector config overrides (must match the sessions that will use it)")

    p = actions.add_parser("train", help="k-means of 2HR descriptors into a vocabulary, with its model card",
                           formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    data(p, 0)
    p.add_argument("--words", type=int, default=512, help="vocabulary size (k of k-means)")
    p.add_argument("--name", default="bonn-crowd-0-279", help="the name sessions use it by")
    p.add_argument("--out", default="runs/vocab", help="folder for <name>.npz and its model card <name>.md")
    p.add_argument("--no-install", dest="install", action="store_false",
                   help="do not copy it into the vocabulary folder ($TWOHR_CACHE/vocabularies)")
    p.add_argument("--seed", type=int, default=0)
    p.set_defaults(func=_train)
    p = actions.add_parser("list", help="the installed vocabularies")
    p.set_defaults(func=_list)
    p = actions.add_parser("eval", help="top-1 place recognition on frames it was not trained on",
                           formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    data(p, 280)
    p.add_argument("--name", default="bonn-crowd-0-279", help="an installed vocabulary")
    p.add_argument("--min-gap", type=int, default=60, help="a match must be this many frames away from its query")
    p.add_argument("--out", default="runs/vocab/eval", help="folder for place_recognition.json")
    p.set_defaults(func=_eval)
