"""Render a seeded random Gaussian scene with sync4d.raster.rasterize and save it as a PNG.

    python examples/render_random_scene.py --out runs/random_scene.png --n 2000 --size 320x240

Needs the extension built (`make setup`). The PNG writer below uses only zlib, so the example
has no imaging dependency.
"""

from __future__ import annotations

import argparse
import math
import struct
import time
import zlib
from pathlib import Path

import numpy as np
import torch

from sync4d.raster import rasterize


def random_scene(n: int, seed: int) -> dict[str, torch.Tensor]:
    """N Gaussians in a 2x2x2 box centred on the origin, with RGB features in [0, 1]."""
    g = torch.Generator().manual_seed(seed)
    means = (torch.rand(n, 3, generator=g) * 2.0 - 1.0).float()
    quats = torch.randn(n, 4, generator=g)  # unnormalised (w, x, y, z); the op normalises
    scales = torch.exp(torch.empty(n, 3).uniform_(math.log(0.01), math.log(0.08), generator=g))
    opacities = torch.empty(n).uniform_(0.3, 0.95, generator=g)
    colors = torch.rand(n, 3, generator=g)
    return {
        "means": means,
        "quats": quats,
        "scales": scales,
        "opacities": opacities,
        "features": colors,
    }


def look_at_camera(width: int, height: int, distance: float = 4.0, fov_deg: float = 50.0):
    """World-to-camera matrix (OpenCV axes) for a camera on -z looking at the origin, plus K."""
    viewmat = torch.eye(4)
    viewmat[2, 3] = distance  # camera at (0, 0, -distance); +z forward, y down, x right
    focal = 0.5 * width / math.tan(math.radians(fov_deg) / 2.0)
    K = torch.tensor(
        [[focal, 0.0, width / 2.0], [0.0, focal, height / 2.0], [0.0, 0.0, 1.0]],
        dtype=torch.float32,
    )
    return viewmat, K


def write_png(path: Path, rgb: np.ndarray) -> None:
    """Write an [H, W, 3] uint8 array as an 8-bit RGB PNG (no filtering, zlib level 9)."""
    if rgb.dtype != np.uint8 or rgb.ndim != 3 or rgb.shape[2] != 3:
        raise ValueError(f"expected [H, W, 3] uint8, got {rgb.dtype} {rgb.shape}")
    height, width, _ = rgb.shape
    # Each scanline is prefixed with filter type 0 (None).
    raw = np.concatenate([np.zeros((height, 1), np.uint8), rgb.reshape(height, -1)], axis=1)

    def chunk(tag: bytes, data: bytes) -> bytes:
        body = tag + data
        return struct.pack(">I", len(data)) + body + struct.pack(">I", zlib.crc32(body))

    header = struct.pack(">IIBBBBB", width, height, 8, 2, 0, 0, 0)  # 8-bit, truecolour
    png = (
        b"\x89PNG\r\n\x1a\n"
        + chunk(b"IHDR", header)
        + chunk(b"IDAT", zlib.compress(raw.tobytes(), 9))
        + chunk(b"IEND", b"")
    )
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_bytes(png)


def parse_size(text: str) -> tuple[int, int]:
    w, _, h = text.lower().partition("x")
    if not (w.isdigit() and h.isdigit()) or int(w) < 1 or int(h) < 1:
        raise argparse.ArgumentTypeError(f"expected WIDTHxHEIGHT, got {text!r}")
    return int(w), int(h)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, default=Path("runs/random_scene.png"))
    parser.add_argument("--n", type=int, default=2000, help="number of Gaussians")
    parser.add_argument("--size", type=parse_size, default=(320, 240), help="WIDTHxHEIGHT")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--threads", type=int, default=None, help="rayon threads (default all)")
    args = parser.parse_args()

    width, height = args.size
    scene = random_scene(args.n, args.seed)
    viewmat, K = look_at_camera(width, height)
    background = torch.tensor([1.0, 1.0, 1.0])  # white

    start = time.perf_counter()
    with torch.no_grad():
        out = rasterize(
            **scene,
            viewmat=viewmat,
            K=K,
            width=width,
            height=height,
            background=background,
            threads=args.threads,
        )
    elapsed = time.perf_counter() - start

    image = (out.features.clamp(0.0, 1.0) * 255.0 + 0.5).to(torch.uint8).numpy()
    write_png(args.out, np.ascontiguousarray(image))
    print(
        f"rendered {args.n} Gaussians at {width}x{height} in {elapsed * 1e3:.1f} ms "
        f"(counters: {out.counters}) -> {args.out}"
    )


if __name__ == "__main__":
    main()
