"""``sync4d process VIDEO|IMAGE_DIR --out DATA``: recover the camera poses of your own video or
photos with COLMAP and write a dataset that ``sync4d fit DATA`` reads
(`sync4d.data.process`)."""

from __future__ import annotations

import argparse
import shlex
import sys

from sync4d.data.process import CAMERA_MODELS, MATCHERS, ProcessOptions, process_capture
from sync4d.errors import Sync4dError
from sync4d.options import add_threads, positive_float, positive_int
from sync4d.progress import format_duration

__all__ = ["add_arguments", "main"]


def add_arguments(p: argparse.ArgumentParser) -> None:
    """The description and arguments of ``sync4d process`` (`sync4d.cli`); the choices and
    defaults are `sync4d.data.process`'s."""
    p.description = (
        "Extract frames from a video (PyAV) or read a folder of photos (sorted by name), "
        "recover one shared camera and every frame's pose with COLMAP (pycolmap: SIFT, "
        "matching, incremental mapping), undistort the frames to a pinhole camera and write a "
        "nerfstudio dataset (transforms.json with per-frame time, images/, sparse_pc.ply) that "
        "'fit DATA' reads. Frames COLMAP cannot register are left out and named."
    )
    default = ProcessOptions()
    p.add_argument("input", metavar="VIDEO|IMAGE_DIR",
                   help="a video file (mp4, mov, mkv, ...) or a folder of photos")
    p.add_argument("--out", required=True, metavar="DATA",
                   help="dataset folder to write (new or empty)")
    p.add_argument("--fps", type=positive_float, default=default.fps, metavar="F",
                   help="video frames to keep per second of video time (default: every "
                   "frame, then --max-frames)")  # fmt: skip
    p.add_argument("--max-frames", type=positive_int, default=default.max_frames, metavar="N",
                   help=f"keep at most N frames, evenly spaced (default {default.max_frames})")
    p.add_argument("--max-size", type=positive_int, default=default.max_size, metavar="PX",
                   help="downscale frames whose longest side exceeds PX pixels (default "
                   f"{default.max_size})")  # fmt: skip
    p.add_argument("--camera-model", choices=CAMERA_MODELS, default=default.camera_model,
                   help="COLMAP model of the one camera all frames share: SIMPLE_RADIAL "
                   "(default: focal + one radial term), OPENCV (two focals, k1, k2, p1, p2: "
                   "wide-angle lenses, needs large frames) or PINHOLE")  # fmt: skip
    p.add_argument("--matcher", choices=MATCHERS, default=default.matcher,
                   help="sequential (default: each frame with its neighbours in time; "
                   "videos) or exhaustive (every pair; unordered photos, slower)")
    add_threads(p, "COLMAP")
    p.add_argument("--force", action="store_true",
                   help="replace what an earlier 'process' wrote in DATA")
    p.add_argument("--verbose", action="store_true", help="show COLMAP's own log")

#: Frame names listed in full when COLMAP leaves frames out; more are counted.
LIST_DROPPED = 8


def main(args: argparse.Namespace) -> int:
    """Run `process` with parsed `args`; the exit status."""
    options = ProcessOptions(
        fps=args.fps,
        max_frames=args.max_frames,
        max_size=args.max_size,
        camera_model=args.camera_model,
        matcher=args.matcher,
        threads=args.threads,
        verbose=args.verbose,
    )
    try:
        result = process_capture(args.input, args.out, options, force=args.force)
    except Sync4dError as e:
        print(f"process: {e}", file=sys.stderr)
        return e.exit_code
    except KeyboardInterrupt:
        print("process: interrupted; nothing was kept", file=sys.stderr)
        return 130
    n, k = len(result.frames), len(result.registered)
    cam = result.camera
    print(
        f"process: {n} frames from {args.input} ({result.source_frames} in it); COLMAP "
        f"registered {k}, {result.points} points; pinhole camera {cam['w']}x{cam['h']}, "
        f"focal {cam['fl_x']:.1f} px"
    )
    if result.dropped:
        shown = ", ".join(result.dropped[:LIST_DROPPED])
        more = (
            f" and {len(result.dropped) - LIST_DROPPED} more"
            if len(result.dropped) > LIST_DROPPED
            else ""
        )
        print(f"process: {len(result.dropped)} frames left out (not registered): {shown}{more}")
    stages = ", ".join(f"{stage} {format_duration(s)}" for stage, s in result.seconds.items())
    print(f"process: {stages}; total {format_duration(sum(result.seconds.values()))}")
    data = shlex.quote(str(result.out))
    print(f"process: dataset in {result.out}; train on it with: sync4d fit {data}")
    return 0
