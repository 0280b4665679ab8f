"""``detector.model=auto``: time every network that meets the quality floor once per host and keep the fastest.
The choice is kept in a cache file (:func:`auto_choices_path`) under a lock, keyed by what it depends on, so every
later process on the host (replicas, ``twohr run`` and the services) reads it instead of timing again."""

from __future__ import annotations

import contextlib
import fcntl
import json
import logging
from collections.abc import Callable
from datetime import datetime, timezone
from pathlib import Path

import numpy as np
from pydantic import BaseModel, ValidationError

from twohr.config import DetectorConfig
from twohr.errors import ModelError
from twohr.files import write_atomic
from twohr.machine import machine
from twohr.models import auto_candidates, cache_dir, get_spec, resolve_backend

from .networks import R2D2Network, time_network

log = logging.getLogger("twohr.detector")

#: ``auto`` keeps the best-quality candidate within this factor of the fastest (timing noise on a shared machine)
AUTO_TIE = 1.05


def auto_choices_path() -> Path:
    """Where ``detector.model=auto`` keeps its choices on this host (``$TWOHR_CACHE/models/auto-choices.json``);
    delete it, or run ``twohr models auto --again``, to time the candidates again."""
    return cache_dir() / "auto-choices.json"


class AutoChoice(BaseModel):
    """One ``auto`` choice: the network kept, each candidate's timed latency and when it was timed."""

    model: str
    timings_ms: dict[str, float]
    timed_at: str


def auto_choice_key(conf: DetectorConfig, candidates: list[str], size: tuple[int, int]) -> str:
    """What an ``auto`` choice depends on: the CPU, the backend, precision and threads, the timing size, and each
    candidate's exact bytes (a new model version is timed again)."""
    cpu = machine()
    networks = ",".join(f"{name}@{get_spec(name).sha256[:12]}" for name in candidates)
    return (f"{cpu['cpu_model']} x{cpu['cpus']} | {resolve_backend(conf.backend)} {conf.precision} "
            f"threads={conf.threads} | {size[0]}x{size[1]} | {networks}")


def read_auto_choices(path: Path) -> dict[str, AutoChoice]:
    """The choices kept in ``path``; an absent, unreadable or malformed file holds none (they are timed again)."""
    try:
        raw = json.loads(path.read_text())
        return {key: AutoChoice.model_validate(value) for key, value in raw.items()}
    except FileNotFoundError:
        return {}
    except (OSError, ValueError, ValidationError, AttributeError) as exc:
        log.warning("detector.model=auto ignores %s (%s); it times the networks again", path, exc)
        return {}


@contextlib.contextmanager
def auto_choice_lock(path: Path):
    """Hold the host's ``auto`` lock: replicas that start together time one after the other (undisturbed by each
    other) and the later ones find the first one's choice. A cache without write access goes without the lock."""
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        handle = open(path.with_suffix(".lock"), "a")
    except OSError:
        yield
        return
    with handle:
        fcntl.flock(handle, fcntl.LOCK_EX)
        try:
            yield
        finally:
            fcntl.flock(handle, fcntl.LOCK_UN)


def keep_auto_choice(path: Path, key: str, choice: AutoChoice) -> None:
    """Add ``choice`` under ``key`` to ``path`` (atomically); a read-only cache only costs a warning."""
    choices = read_auto_choices(path)
    choices[key] = choice
    data = json.dumps({k: v.model_dump() for k, v in choices.items()}, indent=1).encode()
    try:
        write_atomic(path, data, durable=True, folder_mode=0o700)
    except OSError as exc:
        log.warning("detector.model=auto cannot keep its choice in %s (%s): every process times again", path, exc)



def choose_network(conf: DetectorConfig, path: Path, rgb: np.ndarray, size: tuple[int, int],
                   open_network: Callable[[str], R2D2Network]) -> tuple[AutoChoice, R2D2Network]:
    """The network kept in ``path`` on this host for ``size``, else time every candidate
    (:func:`twohr.models.auto_candidates`) on ``rgb`` at ``size``, keep the fastest and return it with its choice.
    ``open_network`` loads a network by name."""
    candidates = auto_candidates()
    key = auto_choice_key(conf, candidates, size)
    with auto_choice_lock(path):
        kept = read_auto_choices(path).get(key)
        if kept is not None and kept.model in candidates and kept.model in kept.timings_ms:
            try:
                network = open_network(kept.model)
            except (ModelError, OSError) as exc:
                log.warning("detector.model=auto cannot load %s, its choice on this host: %s", kept.model, exc)
            else:
                log.info("detector.model=auto uses %s, chosen on this host at %s (%s)", kept.model,
                         kept.timed_at, path)
                return kept, network
        choice, network = _time_candidates(candidates, rgb, size, open_network)
        if set(choice.timings_ms) == set(candidates):  # a choice made without some candidate is not kept
            keep_auto_choice(path, key, choice)
    return choice, network


def _time_candidates(candidates: list[str], rgb: np.ndarray, size: tuple[int, int],
                     open_network: Callable[[str], R2D2Network]) -> tuple[AutoChoice, R2D2Network]:
    networks = {}
    for name in candidates:
        try:
            networks[name] = open_network(name)
        except (ModelError, OSError) as exc:  # e.g. a mirror without that file, a read-only cache
            log.warning("detector.model=auto leaves out %s: %s", name, exc)
    if not networks:
        raise ModelError("detector.model=auto found no network it can load; run `twohr models fetch`")
    # kept for every later process on this host: worth a few more runs than one process's own scale choice
    timings_ms = {name: time_network(net, rgb, size, runs=5) for name, net in networks.items()}
    timed_at = datetime.now(timezone.utc).isoformat(timespec="seconds")
    fastest = min(timings_ms.values())
    # near-ties go to the earlier (better) network, so that timing noise does not flip the choice run to run
    model = next(n for n, ms in timings_ms.items() if ms <= AUTO_TIE * fastest)
    log.info("detector.model=auto chose %s (%s at %dx%d)", model,
             ", ".join(f"{n} {t:.0f} ms" for n, t in timings_ms.items()), *size)
    return AutoChoice(model=model, timings_ms=timings_ms, timed_at=timed_at), networks[model]
