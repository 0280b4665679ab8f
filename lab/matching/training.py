"""Training of the Siamese matcher on labelled real RGB-D pairs, and its ONNX export.

torch is imported here and in ``model.py`` only (the ``train`` extra); inference runs the exported
ONNX on onnxruntime. Training is seeded and single-threaded (1 torch thread), so the same command
gives the same weights on the same machine.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch
from pydantic import BaseModel, Field
from torch import nn

from .data import PairSet
from .model import SiameseMatcherNet


class TrainConfig(BaseModel):
    """Hyper-parameters of ``twohr matcher train``."""

    epochs: int = Field(4, ge=1)
    batch_size: int = Field(2048, ge=16)
    learning_rate: float = Field(3e-3, gt=0)
    weight_decay: float = Field(1e-4, ge=0)
    seed: int = 0
    threads: int = Field(1, ge=1, description="torch intra-op threads (1: on a shared 2-core machine, 2 OpenMP "
                         "threads measured 4x slower per step than 1)")
    channels: int = Field(8, ge=1, description="Conv1d channels of the branch")
    kernel_size: int = Field(5, ge=1)
    hidden: int = Field(64, ge=1, description="hidden units of the head MLP")
    dropout: float = Field(0.1, ge=0, lt=1)
    max_steps: int | None = Field(None, ge=1, description="stop after this many steps (smoke tests)")


@dataclass
class TrainResult:
    """The trained network (best validation loss) and per-epoch history."""

    model: SiameseMatcherNet
    history: list[dict] = field(default_factory=list)
    step_losses: list[float] = field(default_factory=list)
    best_epoch: int = 0
    seconds: float = 0.0


def classification_metrics(scores: np.ndarray, labels: np.ndarray, threshold: float = 0.5) -> dict[str, float]:
    """Accuracy, precision and recall of ``scores >= threshold`` against 0/1 labels."""
    predicted = scores >= threshold
    positive = labels > 0.5
    tp = int(np.count_nonzero(predicted & positive))
    fp = int(np.count_nonzero(predicted & ~positive))
    fn = int(np.count_nonzero(~predicted & positive))
    return {"accuracy": float(np.mean(predicted == positive)) if len(labels) else float("nan"),
            "precision": tp / (tp + fp) if tp + fp else float("nan"),
            "recall": tp / (tp + fn) if tp + fn else float("nan")}


def _batch(pairs: PairSet, rows: np.ndarray) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    desc_a = torch.from_numpy(pairs.bank[pairs.idx_a[rows]].astype(np.float32))
    desc_b = torch.from_numpy(pairs.bank[pairs.idx_b[rows]].astype(np.float32))
    return desc_a, desc_b, torch.from_numpy(pairs.label[rows])


@torch.no_grad()
def predict(model: SiameseMatcherNet, pairs: PairSet, batch_size: int = 16384) -> tuple[np.ndarray, float]:
    """Scores in [0, 1] for every pair of ``pairs`` and the mean binary cross-entropy."""
    model.eval()
    scores, total = [], 0.0
    loss_fn = nn.BCEWithLogitsLoss(reduction="sum")
    for start in range(0, len(pairs), batch_size):
        desc_a, desc_b, labels = _batch(pairs, np.arange(start, min(start + batch_size, len(pairs))))
        logits = model.logits(desc_a, desc_b)
        total += float(loss_fn(logits, labels))
        scores.append(torch.sigmoid(logits).numpy())
    return (np.concatenate(scores) if scores else np.zeros(0, np.float32)), total / max(len(pairs), 1)


def train_siamese(train: PairSet, val: PairSet, conf: TrainConfig | None = None,
                  progress: bool = True) -> TrainResult:
    """Train with binary cross-entropy and Adam; keep the weights of the epoch with the lowest validation loss."""
    from tqdm import tqdm

    conf = conf or TrainConfig()
    if len(train) == 0:
        raise ValueError("no training pairs: check the sequence, its ground truth and the keypoint cache")
    torch.manual_seed(conf.seed)
    torch.set_num_threads(conf.threads)
    rng = np.random.default_rng(conf.seed)
    model = SiameseMatcherNet(train.bank.shape[1], conf.channels, conf.kernel_size, conf.hidden, conf.dropout)
    optimiser = torch.optim.Adam(model.parameters(), lr=conf.learning_rate, weight_decay=conf.weight_decay)
    steps_per_epoch = int(np.ceil(len(train) / conf.batch_size))
    scheduler = torch.optim.lr_scheduler.CosineAnnealingLR(optimiser, T_max=conf.epochs * steps_per_epoch)
    loss_fn = nn.BCEWithLogitsLoss()
    result = TrainResult(model)
    best_loss, best_state = float("inf"), None
    start_time = time.perf_counter()
    step = 0
    for epoch in range(1, conf.epochs + 1):
        model.train()
        order = rng.permutation(len(train))
        epoch_loss = 0.0
        bar = tqdm(range(steps_per_epoch), desc=f"epoch {epoch}/{conf.epochs}", unit="step", disable=not progress,
                   leave=False)
        for i in bar:
            desc_a, desc_b, labels = _batch(train, order[i * conf.batch_size:(i + 1) * conf.batch_size])
            loss = loss_fn(model.logits(desc_a, desc_b), labels)
            optimiser.zero_grad()
            loss.backward()
            optimiser.step()
            scheduler.step()
            result.step_losses.append(loss.item())
            epoch_loss += loss.item() * len(labels)
            step += 1
            if conf.max_steps is not None and step >= conf.max_steps:
                break
        seen = min(len(train), (i + 1) * conf.batch_size)
        val_scores, val_loss = predict(model, val) if len(val) else (np.zeros(0), float("nan"))
        row = {"epoch": epoch, "train_loss": epoch_loss / seen, "val_loss": val_loss,
               **{f"val_{k}": v for k, v in classification_metrics(val_scores, val.label).items()}}
        result.history.append(row)
        if progress:
            tqdm.write(f"epoch {epoch}: train loss {row['train_loss']:.4f}  val loss {val_loss:.4f}  "
                       f"val acc {row['val_accuracy']:.3f} precision {row['val_precision']:.3f} "
                       f"recall {row['val_recall']:.3f}")
        if not np.isfinite(val_loss) or val_loss < best_loss:
            best_loss = val_loss
            best_state = {k: v.detach().clone() for k, v in model.state_dict().items()}
            result.best_epoch = epoch
        if conf.max_steps is not None and step >= conf.max_steps:
            break
    if best_state is not None:
        model.load_state_dict(best_state)
    model.eval()
    result.seconds = time.perf_counter() - start_time
    return result


def export_onnx(model: SiameseMatcherNet, path: str | Path, metadata: dict[str, str] | None = None) -> Path:
    """Write the inference graph (``desc_a``, ``desc_b``, ``idx_a``, ``idx_b`` -> ``scores``) with dynamic sizes."""
    import warnings

    import onnx

    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    model = model.eval()
    dim = model.descriptor_dim
    example = (torch.randn(5, dim), torch.randn(4, dim), torch.tensor([0, 1, 4]), torch.tensor([3, 0, 2]))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # the TorchScript exporter announces its deprecation
        torch.onnx.export(
            model, example, str(path), dynamo=False, opset_version=17,
            input_names=["desc_a", "desc_b", "idx_a", "idx_b"], output_names=["scores"],
            dynamic_axes={"desc_a": {0: "num_a"}, "desc_b": {0: "num_b"}, "idx_a": {0: "num_pairs"},
                          "idx_b": {0: "num_pairs"}, "scores": {0: "num_pairs"}},
        )
    proto = onnx.load(str(path))
    proto.producer_name = "twohr matcher train"
    for key, value in (metadata or {}).items():
        entry = proto.metadata_props.add()
        entry.key, entry.value = key, value
    onnx.checker.check_model(proto)
    onnx.save(proto, str(path))
    return path


def plot_training(result: TrainResult, path: str | Path) -> Path:
    """Loss curves (per step, smoothed, and per epoch with validation) and validation precision/recall."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig, axes = plt.subplots(1, 2, figsize=(11, 4))
    steps = np.asarray(result.step_losses)
    epochs = [r["epoch"] for r in result.history]
    steps_per_epoch = len(steps) / max(len(epochs), 1)
    window = max(1, len(steps) // 50)
    smooth = np.convolve(steps, np.ones(window) / window, mode="valid")
    axes[0].plot(np.arange(len(steps)) / steps_per_epoch, steps, color="0.8", lw=0.5, label="train (per step)")
    axes[0].plot((np.arange(len(smooth)) + window - 1) / steps_per_epoch, smooth, color="C0",
                 label=f"train (mean of {window} steps)")
    axes[0].plot(epochs, [r["train_loss"] for r in result.history], "o-", color="C0", ms=4, label="train (epoch)")
    axes[0].plot(epochs, [r["val_loss"] for r in result.history], "s-", color="C1", ms=4, label="validation")
    axes[0].axvline(result.best_epoch, color="C1", ls=":", lw=1, label=f"kept: epoch {result.best_epoch}")
    axes[0].set_xlabel("epoch")
    axes[0].set_ylabel("binary cross-entropy")
    axes[0].set_title("Siamese matcher: loss")
    axes[0].legend(fontsize=8)
    for key, colour in (("val_accuracy", "C2"), ("val_precision", "C3"), ("val_recall", "C4")):
        axes[1].plot(epochs, [r[key] for r in result.history], "o-", color=colour, ms=4, label=key[4:])
    axes[1].set_xlabel("epoch")
    axes[1].set_title("validation pairs, score >= 0.5")
    axes[1].set_ylim(0, 1)
    axes[1].grid(alpha=0.3)
    axes[1].legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path
