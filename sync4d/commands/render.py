"""``python -m sync4d render RUN [--time ...] [--camera ...]``: render a run's checkpoint from
one of its stored cameras at chosen times (default: a sweep over [0, 1]) to PNGs and a GIF.

Cameras come from the checkpoint's header, so rendering needs no dataset."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
from PIL import Image

from sync4d.data.scene import Camera
from sync4d.errors import Sync4dError
from sync4d.options import add_backend, add_threads, frame_count, positive_float
from sync4d.progress import Progress
from sync4d.runs.names import RENDERS_DIR, render_frame, render_sweep

if TYPE_CHECKING:
    from sync4d.phase1.gaussians import DeformableGaussians

__all__ = [
    "add_arguments",
    "camera_from_record",
    "main",
    "pick_camera",
    "render_times",
    "save_gif",
]


def add_arguments(p: argparse.ArgumentParser) -> None:
    """The description and arguments of ``sync4d render`` (`sync4d.cli`)."""
    p.description = (
        "Render a run's checkpoint from one of its stored cameras at chosen times (default: a "
        "sweep over [0, 1]) to PNGs and a GIF."
    )
    p.add_argument("run", metavar="RUN", help="run folder (or a checkpoint file)")
    p.add_argument("--time", nargs="+", type=float, default=None, metavar="T", dest="times",
                   help="times in [0, 1], one PNG each (default: a --sweep)")
    p.add_argument("--sweep", type=frame_count, default=48, metavar="N", dest="frames",
                   help="frames of the default time sweep, evenly spaced over [0, 1] "
                   "(default 48)")
    p.add_argument("--camera", default=None, metavar="CAM",
                   help="test:K / train:K (K-th frame of that split), K (a test frame) or a "
                   "frame name such as cam10_000000.jpg; default test:0")
    p.add_argument("--out", default=None, metavar="DIR",
                   help="output folder (default RUN/renders)")
    p.add_argument("--fps", type=positive_float, default=15.0, help="GIF frame rate")
    p.add_argument("--no-gif", action="store_true", help="write PNGs only")
    add_threads(p)
    add_backend(p)


def camera_from_record(rec: dict) -> Camera:
    """A `Camera` from a checkpoint camera record (see `sync4d.runs.checkpoint.camera_records`)."""
    vm = np.asarray(rec["viewmat"], dtype=np.float64).reshape(4, 4)
    return Camera(
        vm, float(rec["fx"]), float(rec["fy"]), float(rec["cx"]), float(rec["cy"]),
        int(rec["width"]), int(rec["height"]),
    )  # fmt: skip


def pick_camera(records: list[dict], spec: str | None) -> dict:
    """The record chosen by `spec`: ``test:K`` / ``train:K`` (K-th frame of that split), a
    bare integer (a test camera), or a frame's file name; default the first test camera."""
    if not records:
        raise ValueError("the checkpoint stores no cameras (written by an older sync4d?)")
    by_split: dict[str, list[dict]] = {"train": [], "test": []}
    for r in records:
        by_split.setdefault(r["split"], []).append(r)
    if spec is None:
        return (by_split["test"] or by_split["train"])[0]
    split, _, index = spec.rpartition(":")
    if index.isdigit() and split in ("", "test", "train"):
        pool = by_split[split or "test"] or by_split["train"]
        k = int(index)
        if k >= len(pool):
            raise ValueError(f"--camera {spec}: only {len(pool)} {split or 'test'} cameras")
        return pool[k]
    for r in records:
        if r["name"] == spec or Path(r["name"]).stem == spec:
            return r
    raise ValueError(f"--camera {spec}: no camera with that name; use test:K, train:K or a name")


def render_times(
    model: DeformableGaussians,
    camera: Camera,
    times: list[float],
    background: list[float],
    threads: int | None = None,
) -> list[np.ndarray]:
    """uint8 RGB frames [H, W, 3] of `model` seen by `camera` at each time."""
    import torch

    with torch.no_grad():
        bg = torch.tensor(background, dtype=torch.float32)
        out = []
        bar = Progress(len(times), desc="render", log_every=max(1, len(times) // 4))
        for i, t in enumerate(times):
            img = model.render(camera, t, background=bg, threads=threads).features.clamp(0, 1)
            out.append((img.numpy() * 255.0 + 0.5).astype(np.uint8))
            bar.update(i + 1)
        bar.close()
    return out


def save_gif(frames: list[np.ndarray], path: Path, fps: float = 15.0) -> Path:
    """Write `frames` as a looping GIF."""
    images = [Image.fromarray(f) for f in frames]
    images[0].save(
        path, save_all=True, append_images=images[1:], duration=int(1000 / fps), loop=0
    )
    return path


def main(args: argparse.Namespace) -> int:
    """Run `render` with parsed `args`; the exit status."""
    import torch

    from sync4d.runs import load_run

    try:
        run = load_run(args.run)
        rec = pick_camera(run.cameras, args.camera)
    except (Sync4dError, ValueError) as e:  # ValueError: pick_camera's --camera
        print(f"render: {e}", file=sys.stderr)
        return 2
    if args.times:
        times = list(args.times)
    else:
        times = list(np.linspace(0.0, 1.0, args.frames))
    bad = [t for t in times if not 0.0 <= t <= 1.0]
    if bad:
        print(f"render: --time must lie in [0, 1], got {bad}", file=sys.stderr)
        return 2
    out_dir = Path(args.out) if args.out else run.path / RENDERS_DIR
    out_dir.mkdir(parents=True, exist_ok=True)
    if args.threads:
        torch.set_num_threads(args.threads)
    cam = camera_from_record(rec)
    frames = render_times(run.model, cam, times, run.background, args.threads)
    stem = Path(rec["name"]).stem
    for t, f in zip(times, frames, strict=True):
        Image.fromarray(f).save(out_dir / render_frame(stem, t))
    msg = f"render: {len(frames)} PNGs of camera {rec['split']}:{stem}"
    if len(frames) > 1 and not args.no_gif:
        gif = save_gif(frames, out_dir / render_sweep(stem), args.fps)
        msg += f" and {gif.name}"
    print(f"{msg} in {out_dir}")
    return 0
