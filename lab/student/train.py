"""Distil the student keyframe network (:mod:`.model`) from the faster2d2 teacher.

``python -m twohr_lab.student.train --images ../shared/images --out runs/student/run1 --steps N``

Data: every image under ``--images`` except the held-out last 200 frames of ``7scenes/`` (never the
evaluation sequence). Each sample is a pair of views of one image:

* view A: a random rescale (the network sees keyframes at 0.45-0.8 of 640x480) and a random square crop;
* view B: view A through a random homography (rotation +-20 deg, scale 0.8-1.25, each corner moved by up
  to 10 % of the crop, a shift of up to 10 %), warped from the rescaled image;
* each view gets its own photometric jitter (brightness, contrast, gamma, Gaussian noise, sometimes blur).

The teacher (faster2d2's ONNX on onnxruntime, one thread) runs on view A only. Losses (weights in
:class:`TrainConfig`):

* ``desc``: mean over pixels of ``1 - cos(student, teacher)`` descriptors on view A;
* ``rel``: L1 between reliability maps on view A;
* ``rep``: L1 between repeatability maps on view A, weighted by ``1 + 4 * teacher`` so the peaks count;
* ``cons``: descriptor consistency across the homography: at a grid of view-A pixels p, the student's
  view-B descriptor at H(p) is pulled towards the teacher's view-A descriptor at p and the student's own
  view-A descriptor (``1 - cos``, half each), plus L1 of the student's repeatability at H(p) against the
  teacher's at p.

The run resumes from ``<out>/checkpoint.pt`` (model, optimiser, step, loss history), writes one JSON line
per step to ``<out>/log.jsonl``, and at the end exports ``<out>/student.onnx`` (the faster2d2 contract),
compares it with the teacher on held-out images and writes ``<out>/model_card.md`` with ``loss.png``.
Single-threaded on purpose (a shared 2-core machine): run it under ``nice -n 19`` with ``OMP_NUM_THREADS=1``.
"""

from __future__ import annotations

import argparse
import json
import math
import signal
import sys
import time
from dataclasses import asdict, dataclass
from pathlib import Path

import cv2
import numpy as np
import torch
import torch.nn.functional as F

from twohr.files import AS_OPEN, replacing

from .data import IMAGENET_MEAN, IMAGENET_STD, images_dir, list_images, models_dir, read_rgb, split, spread
from .model import FASTER2D2_MACS_PER_PIXEL, StudentNet, export_onnx, macs_per_pixel, parameter_count

TEACHER = models_dir() / "faster2d2_WASF_N16.onnx"


@dataclass
class TrainConfig:
    batch: int = 4
    crop: int = 192
    lr: float = 2e-3
    weight_decay: float = 1e-4
    w_desc: float = 1.0
    w_rel: float = 1.0
    w_rep: float = 2.0
    w_cons: float = 0.5
    cons_stride: int = 4
    seed: int = 0
    save_every: int = 100
    threads: int = 1


# ----------------------------------------------------------------------------- data


def random_homography(rng: np.random.Generator, size: int) -> np.ndarray:
    """A 3x3 homography mapping view-A pixels to view-B pixels of a ``size`` x ``size`` crop."""
    s = float(size)
    src = np.array([[0, 0], [s, 0], [s, s], [0, s]], np.float32)
    centre = np.array([s / 2, s / 2], np.float32)
    angle = np.deg2rad(rng.uniform(-20, 20))
    scale = np.exp(rng.uniform(np.log(0.8), np.log(1.25)))
    rot = scale * np.array([[np.cos(angle), -np.sin(angle)], [np.sin(angle), np.cos(angle)]], np.float32)
    dst = (src - centre) @ rot.T + centre
    dst += rng.uniform(-0.1 * s, 0.1 * s, (4, 2)).astype(np.float32)
    dst += rng.uniform(-0.1 * s, 0.1 * s, (1, 2)).astype(np.float32)
    return cv2.getPerspectiveTransform(src, dst.astype(np.float32)).astype(np.float64)


def photometric(rng: np.random.Generator, rgb: np.ndarray) -> np.ndarray:
    """Random brightness, contrast, gamma, noise and (sometimes) blur, on uint8 RGB; returns uint8."""
    x = rgb.astype(np.float32) / 255.0
    x = np.clip((x - 0.5) * rng.uniform(0.7, 1.3) + 0.5 + rng.uniform(-0.15, 0.15), 0, 1)
    x = x ** rng.uniform(0.7, 1.4)
    if rng.random() < 0.25:
        k = int(rng.choice([3, 5]))
        x = cv2.GaussianBlur(x, (k, k), 0)
    x = x + rng.normal(0, rng.uniform(0, 0.03), x.shape).astype(np.float32)
    return (np.clip(x, 0, 1) * 255).round().astype(np.uint8)


def to_input(rgb: np.ndarray) -> np.ndarray:
    return ((rgb.astype(np.float32) / 255.0 - IMAGENET_MEAN) / IMAGENET_STD).transpose(2, 0, 1)


def sample_pair(rng: np.random.Generator, path: Path, crop: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(view A, view B) as float32 [3, crop, crop] network inputs, and H mapping A pixels to B pixels."""
    rgb = read_rgb(path)
    h, w = rgb.shape[:2]
    scale = rng.uniform(0.45, 0.8) if min(h, w) >= 400 else rng.uniform(0.8, 1.0)
    scale = max(scale, (crop + 2) / min(h, w))
    rgb = cv2.resize(rgb, (round(w * scale), round(h * scale)), interpolation=cv2.INTER_AREA)
    h, w = rgb.shape[:2]
    x0, y0 = int(rng.integers(0, w - crop + 1)), int(rng.integers(0, h - crop + 1))
    view_a = rgb[y0:y0 + crop, x0:x0 + crop]
    hom = random_homography(rng, crop)
    shift = np.array([[1, 0, -x0], [0, 1, -y0], [0, 0, 1]], np.float64)
    view_b = cv2.warpPerspective(rgb, hom @ shift, (crop, crop), flags=cv2.INTER_LINEAR,
                                 borderMode=cv2.BORDER_CONSTANT, borderValue=0)
    return to_input(photometric(rng, view_a)), to_input(photometric(rng, view_b)), hom


class Teacher:
    """The teacher network on onnxruntime (one thread, batch 1 per call, as the ONNX is [1,3,H,W])."""

    def __init__(self, path: str | Path = TEACHER, threads: int = 1) -> None:
        import onnxruntime as ort

        options = ort.SessionOptions()
        options.intra_op_num_threads = threads
        options.inter_op_num_threads = 1
        self.session = ort.InferenceSession(str(path), options, providers=["CPUExecutionProvider"])

    def __call__(self, batch: np.ndarray) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        outs = [self.session.run(["descriptors", "reliability", "repeatability"], {"image": x[None]})
                for x in batch]
        return tuple(torch.from_numpy(np.concatenate([o[i] for o in outs])) for i in range(3))


# ----------------------------------------------------------------------------- losses


def sample_at(maps: torch.Tensor, xy: torch.Tensor, size: int) -> torch.Tensor:
    """Bilinear samples [B, C, N] of [B, C, S, S] maps at pixel coordinates xy [B, N, 2]."""
    grid = (xy + 0.5) / size * 2 - 1
    return F.grid_sample(maps, grid[:, :, None, :], mode="bilinear", align_corners=False)[..., 0]


def consistency_points(homs: np.ndarray, size: int, stride: int) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Grid pixels p of view A, their images q = H(p) in view B, and the mask of q inside view B."""
    ys, xs = np.mgrid[stride // 2:size:stride, stride // 2:size:stride]
    p = np.stack([xs.ravel(), ys.ravel(), np.ones(xs.size)], 0).astype(np.float64)
    q = np.einsum("bij,jn->bin", homs, p)
    q = (q[:, :2] / q[:, 2:3]).transpose(0, 2, 1)
    valid = (q >= 0).all(-1) & (q <= size - 1).all(-1)
    p_xy = np.broadcast_to(p[:2].T, q.shape)
    return (torch.from_numpy(np.ascontiguousarray(p_xy, np.float32)), torch.from_numpy(q.astype(np.float32)),
            torch.from_numpy(valid))


def losses(model: StudentNet, teacher: Teacher, view_a: np.ndarray, view_b: np.ndarray, homs: np.ndarray,
           conf: TrainConfig) -> dict[str, torch.Tensor]:
    n, size = len(view_a), view_a.shape[-1]
    t_desc, t_rel, t_rep = teacher(view_a)
    desc, rel, rep = model(torch.from_numpy(np.concatenate([view_a, view_b])))
    s_desc, s_rel, s_rep = desc[:n], rel[:n], rep[:n]
    out = {
        "desc": (1 - (s_desc * t_desc).sum(1)).mean(),
        "rel": (s_rel - t_rel).abs().mean(),
    }
    weight = 1 + 4 * t_rep
    out["rep"] = ((s_rep - t_rep).abs() * weight).sum() / weight.sum()
    p, q, valid = consistency_points(homs, size, conf.cons_stride)
    if valid.any():
        b_desc = F.normalize(sample_at(desc[n:], q, size), dim=1)          # [n, 128, N]
        a_teacher = sample_at(t_desc, p, size)
        a_student = sample_at(s_desc, p, size)
        cos_t = (b_desc * a_teacher).sum(1)
        cos_s = (b_desc * a_student).sum(1)
        rep_b = sample_at(rep[n:], q, size)[:, 0]
        rep_t = sample_at(t_rep, p, size)[:, 0]
        out["cons"] = (0.5 * (1 - cos_t) + 0.5 * (1 - cos_s) + (rep_b - rep_t).abs())[valid].mean()
    else:
        out["cons"] = torch.zeros(())
    out["total"] = (conf.w_desc * out["desc"] + conf.w_rel * out["rel"] + conf.w_rep * out["rep"]
                    + conf.w_cons * out["cons"])
    return out


def learning_rate(step: int, steps: int, base: float) -> float:
    """Linear warm-up over min(100, steps/10) steps, then cosine decay to 5 % of ``base`` at ``steps``."""
    warm = max(1, min(100, steps // 10))
    if step < warm:
        return base * (step + 1) / warm
    t = min(1.0, (step - warm) / max(1, steps - warm))
    return base * (0.05 + 0.95 * 0.5 * (1 + math.cos(math.pi * t)))


# ----------------------------------------------------------------------------- the run


def _save(path: Path, model, optimiser, step: int, history: list[dict], conf: TrainConfig) -> None:
    with replacing(path, AS_OPEN) as out:
        torch.save({"model": model.state_dict(), "optimiser": optimiser.state_dict(), "step": step,
                    "history": history, "config": asdict(conf)}, out)


def train(images_dir: str | Path, out_dir: str | Path, steps: int, teacher: str | Path = TEACHER,
          conf: TrainConfig | None = None, eval_images: int = 10, measure_latency: bool = True,
          progress: bool = True) -> dict:
    """Distil for ``steps`` steps in total (resuming from ``out_dir/checkpoint.pt``), then export the ONNX,
    evaluate it against the teacher and write the model card. Returns a summary dict (also ``summary.json``)."""
    from tqdm import tqdm

    conf = conf or TrainConfig()
    torch.set_num_threads(conf.threads)
    cv2.setNumThreads(1)
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    train_paths, held = split(list_images(images_dir))
    torch.manual_seed(conf.seed)
    model = StudentNet()
    optimiser = torch.optim.AdamW(model.parameters(), lr=conf.lr, weight_decay=conf.weight_decay)
    ckpt_path = out / "checkpoint.pt"
    step, history = 0, []
    if ckpt_path.exists():
        state = torch.load(ckpt_path, map_location="cpu", weights_only=False)
        model.load_state_dict(state["model"])
        optimiser.load_state_dict(state["optimiser"])
        step, history = state["step"], state["history"]
        print(f"resumed from {ckpt_path} at step {step}", file=sys.stderr)
    net = Teacher(teacher, conf.threads)

    stop = {"now": False}

    def _on_term(signum, frame):  # finish the current step, save, exit
        stop["now"] = True

    previous = signal.signal(signal.SIGTERM, _on_term)
    model.train()
    bar = tqdm(total=steps, initial=step, disable=not progress, desc="distil", dynamic_ncols=True, mininterval=5)
    log = (out / "log.jsonl").open("a")
    try:
        while step < steps and not stop["now"]:
            rng = np.random.default_rng([conf.seed, step])
            picks = rng.integers(0, len(train_paths), conf.batch)
            pairs = [sample_pair(rng, train_paths[i], conf.crop) for i in picks]
            view_a = np.stack([a for a, _, _ in pairs])
            view_b = np.stack([b for _, b, _ in pairs])
            homs = np.stack([h for _, _, h in pairs])
            lr = learning_rate(step, steps, conf.lr)
            for group in optimiser.param_groups:
                group["lr"] = lr
            start = time.perf_counter()
            parts = losses(model, net, view_a, view_b, homs, conf)
            optimiser.zero_grad(set_to_none=True)
            parts["total"].backward()
            torch.nn.utils.clip_grad_norm_(model.parameters(), 5.0)
            optimiser.step()
            step += 1
            record = {"step": step, "lr": lr, "seconds": round(time.perf_counter() - start, 3),
                      **{k: round(v.item(), 6) for k, v in parts.items()}}
            history.append(record)
            log.write(json.dumps(record) + "\n")
            log.flush()
            bar.update(1)
            bar.set_postfix(loss=f"{record['total']:.4f}", desc=f"{record['desc']:.3f}")
            if step % conf.save_every == 0:
                _save(ckpt_path, model, optimiser, step, history, conf)
    finally:
        bar.close()
        log.close()
        signal.signal(signal.SIGTERM, previous)
    _save(ckpt_path, model, optimiser, step, history, conf)
    summary = finish(model, out, images_dir, train_paths, held, history, conf, teacher, eval_images,
                     measure_latency, complete=step >= steps)
    return summary


def snapshot(images_dir: str | Path, out_dir: str | Path, teacher: str | Path = TEACHER, eval_images: int = 10,
             measure_latency: bool = False) -> dict:
    """Model card of the last checkpoint in ``out_dir`` while a run goes on (no training step; the running
    process overwrites the card and the ONNX when it ends). Pause the run meanwhile on a shared machine."""
    torch.set_num_threads(1)
    out = Path(out_dir)
    state = torch.load(out / "checkpoint.pt", map_location="cpu", weights_only=False)
    model = StudentNet()
    model.load_state_dict(state["model"])
    conf = TrainConfig(**state["config"])
    train_paths, held = split(list_images(images_dir))
    return finish(model, out, images_dir, train_paths, held, state["history"], conf, teacher, eval_images,
                  measure_latency, complete=False)


def finish(model: StudentNet, out: Path, images_dir, train_paths: list[Path], held: list[Path], history: list[dict],
           conf: TrainConfig, teacher: str | Path, eval_images: int, measure_latency: bool, complete: bool) -> dict:
    """Export ``student.onnx``, compare it with the teacher, plot the losses, write the model card."""
    from .int8 import compare, cpu_model, latency

    model.eval()
    onnx_path = out / "student.onnx"
    export_onnx(model, onnx_path)
    check = spread(held or train_paths, eval_images)
    summary: dict = {
        "steps": history[-1]["step"] if history else 0, "complete": complete,
        "parameters": parameter_count(model), "macs_per_pixel": macs_per_pixel(model),
        "teacher_macs_per_pixel": FASTER2D2_MACS_PER_PIXEL, "onnx": str(onnx_path),
        "checkpoint": str(out / "checkpoint.pt"), "config": asdict(conf), "images_dir": str(images_dir),
        "train_images": len(train_paths), "held_out_images": len(held), "eval_images": len(check),
    }
    if check:
        summary["vs_teacher_480x360"] = compare(teacher, onnx_path, check)
    if measure_latency:
        summary["cpu"] = cpu_model()
        summary["latency_teacher_480x360"] = latency(teacher)
        summary["latency_student_480x360"] = latency(onnx_path)
    if history:
        summary["first_losses"] = history[0]
        summary["last_losses_mean50"] = {k: float(np.mean([h[k] for h in history[-50:]]))
                                         for k in ("total", "desc", "rel", "rep", "cons")}
        plot_losses(history, out / "loss.png")
    (out / "summary.json").write_text(json.dumps(summary, indent=1))
    (out / "model_card.md").write_text(model_card(summary))
    return summary


def plot_losses(history: list[dict], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    steps = np.array([h["step"] for h in history])
    fig, ax = plt.subplots(figsize=(7, 4))
    window = max(1, min(25, len(history) // 10))
    for key in ("total", "desc", "rel", "rep", "cons"):
        values = np.array([h[key] for h in history])
        smooth = np.convolve(values, np.ones(window) / window, mode="valid")
        ax.plot(steps[window - 1:], smooth, label=key)
    ax.set_yscale("log")
    ax.set_xlabel("step")
    ax.set_ylabel(f"loss (mean of {window} steps)")
    ax.legend()
    ax.grid(alpha=0.3)
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


def model_card(s: dict) -> str:
    c = s["config"]
    lines = [
        "# Student keyframe network (issue 41)", "",
        f"Distilled from faster2d2_WASF_N16 for {s['steps']} steps"
        f"{'' if s['complete'] else ' (not the end of the run: it resumes from the checkpoint)'}. ONNX: `{s['onnx']}`; "
        f"checkpoint: `{s['checkpoint']}`.",
        "Licence: derived from the faster2d2 teacher (CC BY-NC-SA 3.0, non-commercial); internal research use.", "",
        "## Network", "",
        f"- {s['parameters']:,} parameters (faster2d2: 484,387); {s['macs_per_pixel'] / 1e3:.1f} k multiply-adds per "
        f"input pixel against {s['teacher_macs_per_pixel'] / 1e3:.1f} k "
        f"({s['teacher_macs_per_pixel'] / s['macs_per_pixel']:.2f}x fewer). Design and shapes: "
        "`lab/student/model.py`.",
        "- Contract as faster2d2: input `image` [1,3,H,W] (ImageNet-normalised RGB, H and W even); outputs "
        "`descriptors` [1,128,H,W] (L2-normalised, after a 2x bilinear upsample, so the detector's sparse path "
        "applies), `reliability` and `repeatability` [1,1,H,W] in [0,1].", "",
        "## Data", "",
        f"- `{s['images_dir']}`: {s['train_images']} training images; "
        + (f"{s['held_out_images']} held out (the last 200 frames of 7scenes)" if s["held_out_images"]
           else "none held out (too few 7scenes frames)") + "; never the evaluation sequence.",
        f"- Pairs of {c['crop']}x{c['crop']} crops, batch {c['batch']}: view A a random rescale and crop; view B "
        "view A through a random homography (rotation +-20 deg, scale 0.8-1.25, corners +-10 %); independent "
        "photometric jitter (brightness, contrast, gamma, noise, blur).", "",
        "## Losses", "",
        f"- total = {c['w_desc']} desc + {c['w_rel']} rel + {c['w_rep']} rep + {c['w_cons']} cons; AdamW lr {c['lr']} "
        "(warm-up, cosine), weight decay "
        f"{c['weight_decay']}, one thread.",
        "- desc: 1 - cosine to the teacher's descriptors (view A); rel: L1 to the teacher's reliability; rep: L1 to "
        "the teacher's repeatability weighted by 1 + 4 x teacher; cons: at a grid of view-A pixels, 1 - cosine of "
        "the student's view-B descriptor at H(p) to the teacher's and the student's view-A descriptor (half each), "
        "plus L1 of the student's view-B repeatability at H(p) to the teacher's at p.",
    ]
    if "first_losses" in s:
        f, last = s["first_losses"], s["last_losses_mean50"]
        lines += ["", "| loss | first step | mean of the last 50 steps |", "|---|---|---|"]
        lines += [f"| {k} | {f[k]:.4f} | {last[k]:.4f} |" for k in ("total", "desc", "rel", "rep", "cons")]
        lines += ["", "![losses](loss.png)"]
    if "vs_teacher_480x360" in s:
        v = s["vs_teacher_480x360"]
        which = "held-out" if s["held_out_images"] else "training"
        lines += ["", f"## Against the teacher ({v['images']} {which} images, 480x360)", "",
                  f"- descriptor cosine, mean over pixels: {v['descriptor_cosine_mean']:.4f} "
                  f"(worst image {v['descriptor_cosine_min_image']:.4f})",
                  f"- reliability |diff|: mean {v['reliability_absdiff_mean']:.4f}, max "
                  f"{v['reliability_absdiff_max']:.3f}",
                  f"- repeatability |diff|: mean {v['repeatability_absdiff_mean']:.4f}, max "
                  f"{v['repeatability_absdiff_max']:.3f}",
                  f"- R2D2 keypoints (3x3 NMS, both maps >= 0.7): teacher {v['keypoints_reference_mean']:.0f}, "
                  f"student {v['keypoints_candidate_mean']:.0f} per image; "
                  f"{100 * v['reference_keypoints_within_1px']:.1f} % of the teacher's within 1 px of a student's",
                  f"- non-finite pixels: {v['nonfinite_pixels']}"]
    if "latency_student_480x360" in s:
        t, u = s["latency_teacher_480x360"]["median_ms"], s["latency_student_480x360"]["median_ms"]
        lines += ["", "## Latency", "",
                  f"onnxruntime, 1 thread, 480x360, median of 5 runs of 20 inferences, {s['cpu']} (a shared machine): "
                  f"teacher {t:.1f} ms, student {u:.1f} ms ({t / u:.2f}x)."]
    lines += ["", "Not yet measured: tracking accuracy (ATE) and `twohr features` %Rep/%Prec with this network; "
              "register the ONNX in `shared/models.yaml` to run them.", ""]
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m twohr_lab.student.train", description=__doc__.split("\n")[0])
    parser.add_argument("--images", default=str(images_dir()), help="training images (never the eval data)")
    parser.add_argument("--out", required=True, help="run folder: checkpoint, log, ONNX, model card")
    parser.add_argument("--steps", type=int, default=0, help="total steps (a resumed run continues to this)")
    parser.add_argument("--teacher", default=str(TEACHER), help="teacher ONNX (faster2d2 or r2d2 contract)")
    parser.add_argument("--batch", type=int, default=TrainConfig.batch)
    parser.add_argument("--crop", type=int, default=TrainConfig.crop, help="crop side (even)")
    parser.add_argument("--lr", type=float, default=TrainConfig.lr)
    parser.add_argument("--seed", type=int, default=TrainConfig.seed)
    parser.add_argument("--save-every", type=int, default=TrainConfig.save_every)
    parser.add_argument("--threads", type=int, default=TrainConfig.threads,
                        help="torch and teacher threads (1 on a shared machine)")
    parser.add_argument("--eval-images", type=int, default=10)
    parser.add_argument("--no-latency", action="store_true", help="skip the latency measurement at the end")
    parser.add_argument("--snapshot", action="store_true",
                        help="no training: export and describe the last checkpoint in --out (an interim model card)")
    args = parser.parse_args(argv)
    if args.snapshot:
        summary = snapshot(args.images, args.out, args.teacher, args.eval_images, not args.no_latency)
        print(json.dumps({k: v for k, v in summary.items() if k != "config"}, indent=1))
        return 0
    if args.steps <= 0:
        parser.error("--steps must be positive (or use --snapshot)")
    if args.crop % 2:
        parser.error("--crop must be even")
    conf = TrainConfig(batch=args.batch, crop=args.crop, lr=args.lr, seed=args.seed, save_every=args.save_every,
                       threads=args.threads)
    summary = train(args.images, args.out, args.steps, args.teacher, conf, args.eval_images, not args.no_latency)
    print(json.dumps({k: v for k, v in summary.items() if k != "config"}, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
