"""``sync4d bench raster RUN``: the rasterizer on a trained run's own Gaussians.

The random-cloud grid of `sync4d.bench.raster` says how the op scales; this says what one
training step's compositing costs on a real scene. For each of ``--frames`` test frames of RUN
(evenly spread over its test split), the run's model is deformed to the frame's time, its
colours are evaluated at the frame's camera (full SH degree), and `sync4d.raster.rasterize`
is timed at that camera with the run's near plane and background: the forward under
``torch.no_grad`` and forward+backward (``loss = features.sum() + alpha.sum()``; gradients
w.r.t. means, quaternions, scales, opacities and colours), median of ``--repeats`` calls after
two warm-ups, in this process. Beside the times it records the op's work counters (visible
Gaussians, tile intersections, evaluated and blended pixel-splat pairs) and the stages of the
forward: projection alone, and the compositing that follows it (forward minus projection).

Every ``--variant NAME:KEY=VALUE,...`` times the same frames again with those keyword
arguments of `rasterize` (e.g. ``alpha_max=0.999``, ``backend=wgpu``), interleaved frame by
frame with the default so both see the same machine load.
"""

from __future__ import annotations

import datetime as _dt
import json
import os
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import torch
from torch import Tensor

import sync4d
from sync4d import raster
from sync4d.bench.measure import (
    METHOD_CLEAR_REFS,
    METHOD_SUBPROCESS,
    clear_refs_available,
    machine_info,
    measure,
)
from sync4d.errors import Sync4dError
from sync4d.report import align_table
from sync4d.runs import RunError
from sync4d.runs.folder import load_run

__all__ = ["RunFrame", "main", "parse_raster_variant", "run_frames"]

SCHEMA = "sync4d.bench.raster-run/1"
#: Keyword arguments of `sync4d.raster.rasterize` a variant may set, and their types.
VARIANT_KEYS: dict[str, type] = {
    "alpha_max": float,
    "eps2d": float,
    "antialiased": bool,
    "backend": str,
}


@dataclass(frozen=True)
class RunFrame:
    """One test frame of a run, ready to rasterize: the deformed Gaussians (means [N, 3],
    unit quaternions [N, 4], scales [N, 3], opacities [N], RGB colours [N, 3]) and the camera
    (view matrix [4, 4], intrinsics [3, 3], image size in pixels)."""

    name: str
    time: float
    means: Tensor
    quats: Tensor
    scales: Tensor
    opacities: Tensor
    colors: Tensor
    viewmat: Tensor
    K: Tensor
    width: int
    height: int
    near: float
    background: Tensor

    def gaussians(self) -> tuple[Tensor, Tensor, Tensor, Tensor, Tensor]:
        """``(means, quats, scales, opacities, colors)``, the differentiable inputs."""
        return self.means, self.quats, self.scales, self.opacities, self.colors


def parse_raster_variant(text: str) -> tuple[str, dict[str, Any]]:
    """``NAME[:KEY=VALUE,...]`` -> (NAME, rasterize keyword arguments); ValueError naming the
    allowed keys when malformed."""
    name, _, rest = text.partition(":")
    kwargs: dict[str, Any] = {}
    for item in (i.strip() for i in rest.split(",") if i.strip()):
        key, sep, value = item.partition("=")
        if not sep or key not in VARIANT_KEYS:
            raise ValueError(
                f"--variant {text!r}: expected NAME or NAME:KEY=VALUE[,...] with KEY one of "
                f"{', '.join(VARIANT_KEYS)}"
            )
        kind = VARIANT_KEYS[key]
        if kind is bool:
            if value.lower() not in ("true", "false", "1", "0"):
                raise ValueError(f"--variant {text!r}: {key} must be true or false")
            kwargs[key] = value.lower() in ("true", "1")
        else:
            try:
                kwargs[key] = kind(value)
            except ValueError:
                msg = f"--variant {text!r}: {key}={value!r} is no {kind.__name__}"
                raise ValueError(msg) from None
    if not name:
        raise ValueError(f"--variant {text!r}: the variant needs a name")
    return name, kwargs


@torch.no_grad()
def run_frames(run_dir: str | Path, frames: int = 3, data: str | None = None) -> list[RunFrame]:
    """`frames` test frames of the run in `run_dir`, evenly spread over its test split, each
    with the run's Gaussians deformed to the frame's time (static Gaussians as stored) and
    coloured at its camera. Raises `RunError` for a missing run or dataset, `CheckpointError`
    for a bad checkpoint and `DatasetError` for a bad dataset."""
    run = load_run(run_dir)
    scene = run.scene(data)
    if scene is None:
        raise RunError(
            f"{run.path}: the run's dataset ({run.settings.get('data')}) is not there any "
            "more; pass --data DIR"
        )
    test = scene.test or scene.train
    k = max(1, min(frames, len(test)))
    picks = sorted({round(i * (len(test) - 1) / max(1, k - 1)) for i in range(k)})
    model = run.model
    coeffs = torch.cat([model.sh_dc, model.sh_rest], dim=1)
    background = torch.tensor(run.background, dtype=torch.float32)
    out = []
    for i in picks:
        f = test[i]
        means, quats, scales = model.at_time(f.time)
        viewmat = torch.as_tensor(f.camera.viewmat, dtype=torch.float32)
        colors = raster.sh_features(means, coeffs, viewmat, model.sh_degree)
        out.append(RunFrame(
            name=f.name, time=float(f.time), means=means.contiguous(), quats=quats.contiguous(),
            scales=scales.contiguous(), opacities=torch.sigmoid(model.opacity_logits),
            colors=colors.contiguous(), viewmat=viewmat,
            K=torch.as_tensor(f.camera.K, dtype=torch.float32), width=f.camera.width,
            height=f.camera.height, near=model.near, background=background,
        ))  # fmt: skip
    return out


def time_frame(
    frame: RunFrame, threads: int, kwargs: dict[str, Any], repeats: int, warmup: int = 2
) -> dict[str, Any]:
    """Times (ms, medians and every call; `sync4d.bench.measure`) and peak RSS
    (MB; the process's lifetime peak where the high-water mark cannot be reset) of projection,
    forward and forward+backward of `frame` with `rasterize` keyword arguments `kwargs`, and
    the forward's work counters."""
    memory = METHOD_CLEAR_REFS if clear_refs_available() else METHOD_SUBPROCESS
    kw = {"near": frame.near, "background": frame.background, "threads": threads, **kwargs}
    cam = (frame.viewmat, frame.K, frame.width, frame.height)
    leaves = [t.detach().clone().requires_grad_(True) for t in frame.gaussians()]
    counters: dict[str, int] = {}
    proj_kw = {k: kw[k] for k in ("near", "threads", "eps2d", "antialiased") if k in kw}

    def project() -> None:
        with torch.no_grad():
            raster.project_gaussians(*frame.gaussians()[:4], *cam, **proj_kw)

    def forward() -> None:
        with torch.no_grad():
            out = raster.rasterize(*frame.gaussians(), *cam, **kw)
        counters.update({k: int(v) for k, v in out.counters.items()})

    def forward_backward() -> None:
        out = raster.rasterize(*leaves, *cam, **kw)
        torch.autograd.grad(out.features.sum() + out.alpha.sum(), leaves)

    result: dict[str, Any] = {}
    for name, fn in (("project", project), ("forward", forward),
                     ("forward_backward", forward_backward)):  # fmt: skip
        t = measure(fn, warmup, repeats, memory)
        result[name] = {"median_ms": t.median_ms, "times_ms": t.times_ms,
                        "rss_peak_mb": t.rss_peak_mb}  # fmt: skip
    fwd = result["forward"]["median_ms"]
    result["composite_ms"] = round(fwd - result["project"]["median_ms"], 3)
    result["backward_ms"] = round(
        result["forward_backward"]["median_ms"] - result["forward"]["median_ms"], 3
    )
    result["counters"] = counters
    return result


def format_table(rows: list[dict[str, Any]]) -> str:
    """One line per (frame, variant): times, the variant's fwd+bwd against the default's, and
    the work counters."""
    header = ["frame", "variant", "N", "res", "project ms", "fwd ms", "composite ms",
              "fwd+bwd ms", "vs default", "isects", "evaluated", "blended",
              "eval/blend"]  # fmt: skip
    lines = []
    base: dict[str, float] = {}
    for r in rows:
        fb = r["forward_backward"]["median_ms"]
        if r["variant"] == "default":
            base[r["frame"]] = fb
        c = r["counters"]
        ref = base.get(r["frame"])
        lines.append([
            r["frame"], r["variant"], f"{r['n']:,}", r["resolution"],
            f"{r['project']['median_ms']:.1f}", f"{r['forward']['median_ms']:.1f}",
            f"{r['composite_ms']:.1f}", f"{fb:.1f}",
            f"{ref / fb:.2f}x" if ref and r["variant"] != "default" else "-",
            f"{c.get('intersections', 0):,}", f"{c.get('evaluated', 0):,}",
            f"{c.get('blended', 0):,}",
            f"{c.get('evaluated', 0) / max(1, c.get('blended', 0)):.2f}",
        ])  # fmt: skip
    return align_table(header, lines, left=(0, 1))


def main(args: Any) -> int:
    """`bench raster RUN`: time the run's frames, print the table, write the JSON."""
    threads = (getattr(args, "threads", None) or [1])[0]
    repeats = getattr(args, "repeats", None) or 5
    try:
        variants = [parse_raster_variant(v) for v in getattr(args, "variant", None) or []]
    except ValueError as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    if any(name == "default" for name, _ in variants):
        print("error: --variant: 'default' is the name of the unchanged op", file=sys.stderr)
        return 2
    saved = torch.get_num_threads()
    torch.set_num_threads(threads)
    try:
        try:
            frames = run_frames(args.run, getattr(args, "frames", None) or 3,
                                getattr(args, "data", None))  # fmt: skip
        except Sync4dError as e:
            print(f"bench raster: {e}", file=sys.stderr)
            return e.exit_code
        out = Path(args.out or f"bench-raster-{Path(args.run).resolve().name}.json")
        print(f"sync4d {sync4d.__version__} bench raster {args.run}: {len(frames)} frames "
              f"x {1 + len(variants)} variants, {threads} thread(s), {repeats} timed calls each; "
              f"json: {out}", flush=True)  # fmt: skip
        rows: list[dict[str, Any]] = []
        t_start = time.monotonic()
        for frame in frames:
            for name, kwargs in [("default", {}), *variants]:
                t0 = time.monotonic()
                res = time_frame(frame, threads, kwargs, repeats)
                rows.append({"frame": frame.name, "time": frame.time, "variant": name,
                             "rasterize_kwargs": kwargs, "n": frame.means.shape[0],
                             "resolution": f"{frame.width}x{frame.height}", **res})  # fmt: skip
                print(f"  {frame.name} {name}: fwd {res['forward']['median_ms']:.1f} ms, "
                      f"fwd+bwd {res['forward_backward']['median_ms']:.1f} ms "
                      f"({time.monotonic() - t0:.1f} s)", flush=True)  # fmt: skip
    finally:
        torch.set_num_threads(saved)
    doc = {
        "schema": SCHEMA,
        "created": _dt.datetime.now(_dt.UTC).isoformat(timespec="seconds"),
        "command": [sys.executable, *sys.argv],
        "machine": machine_info(),
        "loadavg_at_start": list(os.getloadavg()) if hasattr(os, "getloadavg") else None,
        "run": str(Path(args.run).resolve()),
        "settings": {
            "threads": threads,
            "repeats": repeats,
            "warmup": 2,
            "loss": "features.sum() + alpha.sum()",
            "variants": {n: kw for n, kw in variants},
        },  # fmt: skip
        "results": rows,
        "total_seconds": round(time.monotonic() - t_start, 3),
    }
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(doc, indent=2) + "\n")
    print()
    print(format_table(rows))
    print(f"\nms: median wall time; composite = forward - projection; eval/blend: evaluated over "
          f"blended pixel-splat pairs.\nwrote {out}")  # fmt: skip
    return 0
