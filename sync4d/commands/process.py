"""``sync4d process VIDEO|IMAGE_DIR --out DATA``: recover the camera poses of your own video or
photos with COLMAP and write a dataset that ``sync4d fit DATA`` reads
(`sync4d.data.process`)."""

from __future__ import annotations

import argparse
import shlex
import sys

from sync4d.data import DatasetError
from sync4d.data.process import ProcessOptions, process_capture
from sync4d.progress import format_duration

__all__ = ["main"]

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
    except DatasetError as e:
        print(f"process: {e}", file=sys.stderr)
        return 2
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
