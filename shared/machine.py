"""The machine a figure was measured on, for every benchmark's provenance."""

from __future__ import annotations

import os
from pathlib import Path


def machine() -> dict[str, object]:
    """The CPU a figure was measured on: model name (as lscpu shows it), cores, and whether it has AMX and
    AVX-512 bf16 (the keyframe network's speed depends on both)."""
    model, flags = "unknown", set()
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            key, _, value = line.partition(":")
            if key.strip() == "model name" and model == "unknown":
                model = value.strip()
            elif key.strip() == "flags" and not flags:
                flags = set(value.split())
    except OSError:
        pass
    return {"cpu_model": model, "cpus": os.cpu_count(), "amx": "amx_bf16" in flags,
            "avx512_bf16": "avx512_bf16" in flags}
