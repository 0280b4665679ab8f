"""``twohr bench --view-tls`` (``twohr bench view_tls``): frames per second one viewer receives from the live view on
ws:// and on wss:// with a token, and the CPU per frame at 30 Hz. bench.json: ``view_tls``."""

from __future__ import annotations

import argparse

NAME = "view_tls"
HELP = "frames per second one viewer gets from the live view on ws:// and wss://, and the CPU per frame at 30 Hz"


def add_arguments(p: argparse.ArgumentParser, legacy: bool = False) -> None:
    if legacy:
        p.add_argument("--view-tls", action="store_true", help="frames per second one viewer receives from the live "
                       "view on ws:// and on wss:// with a token (the fleet's TLS), the sequence's JPEG frames sent as "
                       "fast as the viewer takes them (--frames, default 2000; --runs pairs), and the CPU per frame "
                       "at 30 Hz")


def picked(args: argparse.Namespace) -> bool:
    return args.view_tls


def run(args: argparse.Namespace, config, sequence, out) -> dict:
    from .steps.view_tls import view_tls_fps

    result = view_tls_fps(sequence, frames=args.frames or 2000, runs=args.runs)
    fps, camera = result["fps_median"], result["camera_rate"]
    print(f"live view, {result['frames']} frames x {result['runs']} runs ({result['image_kb_mean']} kB JPEG "
          f"each), one viewer: {fps['ws']} FPS on ws://, {fps['wss']} FPS on wss:// with a token "
          f"({result['tls_fps_change_percent']} %); at {camera['hz']:g} Hz CPU ms/frame: server "
          f"{camera['server_cpu_ms_per_frame']}, viewer {camera['viewer_cpu_ms_per_frame']}; "
          f"{result['machine']['cpu_model']}")
    return {"view_tls": result}
