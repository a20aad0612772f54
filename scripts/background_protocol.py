"""How the background colour a Blender/D-NeRF scene is composited on changes its test PSNR: the
measurements of docs/results/hellwarrior.md.

Without a run: the ground truth's alpha (how much is background, partial alpha, colour under
alpha = 0, whether the RGB is premultiplied) and what a constant image of the background colour
scores against the ground truth composited on white and on black. With `--run RUN`: the run's
renders composited on white and on black, each scored against the ground truth composited on
the same colour (the protocol of `eval`), on the whole image, on the foreground (alpha > 0,
dilated by 2 pixels) and on the rest.

    python scripts/background_protocol.py ../shared/data/dnerf/hellwarrior [--run RUN] \\
        [--scale 0.5] [--threads 1]
"""

from __future__ import annotations

import argparse
import json

import numpy as np
from PIL import Image

WHITE = (1.0, 1.0, 1.0)
BLACK = (0.0, 0.0, 0.0)


def psnr(a: np.ndarray, b: np.ndarray, mask: np.ndarray | None = None) -> float:
    d = (np.clip(a, 0, 1) - b) ** 2
    mse = float(d[mask].mean()) if mask is not None else float(d.mean())
    return float("inf") if mse == 0 else -10.0 * np.log10(mse)


def alpha_stats(frames) -> dict:
    """Alpha and colour statistics of the frames' files at their native size."""
    zero = full = part = total = 0
    rgb_under_zero = []
    premult_violations = 0
    fg_rgb = []
    for f in frames:
        arr = np.asarray(Image.open(f.image_path).convert("RGBA")).astype(np.int32)
        a = arr[..., 3]
        total += a.size
        zero += int((a == 0).sum())
        full += int((a == 255).sum())
        part += int(((a > 0) & (a < 255)).sum())
        rgb_under_zero.append(arr[..., :3][a == 0].reshape(-1, 3))
        # premultiplied RGB never exceeds alpha
        premult_violations += int((arr[..., :3].max(-1) > a).sum())
        fg_rgb.append(arr[..., :3][a == 255].reshape(-1, 3))
    z = np.concatenate(rgb_under_zero)
    fg = np.concatenate(fg_rgb) / 255.0
    return {
        "frames": len(frames),
        "alpha_zero": zero / total,
        "alpha_full": full / total,
        "alpha_partial": part / total,
        "partial_of_foreground": part / max(1, part + full),
        "rgb_under_alpha_zero_max": int(z.max()) if len(z) else 0,
        "rgb_under_alpha_zero_mean": float(z.mean()) if len(z) else 0.0,
        "rgb_above_alpha_pixels": premult_violations / total,
        "foreground_mean_rgb": [round(float(v), 4) for v in fg.mean(0)],
        "foreground_luma_mean": float((fg @ np.array([0.299, 0.587, 0.114])).mean()),
    }


def foreground_mask(frame, dilate: int = 2) -> np.ndarray:
    """alpha > 0 at the camera's size (box-resized alpha), dilated by `dilate` pixels."""
    im = Image.open(frame.image_path).convert("RGBA")
    a = np.asarray(im)[..., 3]
    size = (frame.camera.width, frame.camera.height)
    if (a.shape[1], a.shape[0]) != size:
        a = np.asarray(Image.fromarray(a).resize(size, Image.Resampling.BOX))
    m = a > 0
    for _ in range(dilate):
        n = m.copy()
        n[1:] |= m[:-1]
        n[:-1] |= m[1:]
        n[:, 1:] |= m[:, :-1]
        n[:, :-1] |= m[:, 1:]
        m = n
    return m


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("data")
    ap.add_argument("--run", default=None, help="a run folder: score its renders both ways")
    ap.add_argument("--scale", type=float, default=0.5, help="resolution scale (dnerf: 0.5)")
    ap.add_argument("--split", default="test")
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--json", default=None, help="write the numbers to this file")
    args = ap.parse_args()

    from sync4d.data.detect import load_scene

    scene = load_scene(args.data, args.scale)
    frames = scene.test if args.split == "test" else scene.train
    out: dict = {"data": str(args.data), "split": args.split, "scale": args.scale}
    out["alpha"] = alpha_stats(frames)
    print(json.dumps(out["alpha"], indent=1))

    gts = {name: [f.load_image(bg) for f in frames] for name, bg in (("white", WHITE),
                                                                     ("black", BLACK))}
    masks = [foreground_mask(f) for f in frames]
    out["foreground_fraction"] = float(np.mean([m.mean() for m in masks]))
    const = {}
    for name, bg in (("white", WHITE), ("black", BLACK)):
        img = np.broadcast_to(np.asarray(bg, np.float32), gts[name][0].shape)
        const[name] = float(np.mean([psnr(img, g) for g in gts[name]]))
    out["constant_background_psnr"] = const
    print(f"foreground (alpha > 0, dilated 2 px): {out['foreground_fraction']:.4f} of the image")
    print(f"constant background image: on white {const['white']:.2f} dB, "
          f"on black {const['black']:.2f} dB")

    if args.run:
        import torch

        from sync4d.pipeline.evaluate import render_frame
        from sync4d.runs import load_run

        torch.set_num_threads(args.threads)
        run = load_run(args.run)
        res: dict = {"trained_on": run.background, "iteration": run.iteration,
                     "gaussians": int(run.model.num_gaussians)}
        per_frame: dict = {}
        for name, bg in (("white", WHITE), ("black", BLACK)):
            whole, fgp, bgp = [], [], []
            for f, g, m in zip(frames, gts[name], masks, strict=True):
                pred = render_frame(run.model, f, bg, args.threads).numpy()
                whole.append(psnr(pred, g))
                fgp.append(psnr(pred, g, m))
                bgp.append(psnr(pred, g, ~m))
            per_frame[name] = [round(v, 2) for v in whole]
            res[name] = {"psnr": float(np.mean(whole)), "foreground_psnr": float(np.mean(fgp)),
                         "background_psnr": float(np.mean(bgp))}
            print(f"render and ground truth on {name}: {res[name]['psnr']:.2f} dB "
                  f"(foreground {res[name]['foreground_psnr']:.2f}, "
                  f"rest {res[name]['background_psnr']:.2f} dB)")
        res["per_frame"] = per_frame
        out["run"] = res
    if args.json:
        with open(args.json, "w") as fh:
            json.dump(out, fh, indent=1)


if __name__ == "__main__":
    main()
