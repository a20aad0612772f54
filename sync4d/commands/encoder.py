"""``python -m sync4d encoder convert|info``: convert a Hugging Face SigLIP model into a
SigLIP-ONNX encoder directory (once, with internet and the ``export`` extra), and describe and
check one.

The directory is what ``--encoder DIR`` (or ``$SYNC4D_ENCODER``) names in Phase 3; its layout is
documented in `sync4d.phase3.encoders.siglip`."""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

from sync4d.errors import Sync4dError

__all__ = ["add_convert_arguments", "add_info_arguments", "main"]


def add_convert_arguments(p: argparse.ArgumentParser) -> None:
    """The description and arguments of ``sync4d encoder convert`` (`sync4d.cli`)."""
    p.description = (
        "Download a SigLIP model (needs internet once and the export extra: pip install "
        "'sync4d[export]'), convert it to ONNX and write DIR: vision.onnx, text.onnx, "
        "tokenizer.json and the manifest encoder.json. Phase 3 then runs it with onnxruntime, "
        "offline (--encoder DIR or $SYNC4D_ENCODER)."
    )
    p.add_argument("--model", default="google/siglip-base-patch16-224", metavar="NAME",
                   help="Hugging Face model id or a local save_pretrained folder "
                   "(default google/siglip-base-patch16-224)")  # fmt: skip
    p.add_argument("--out", required=True, metavar="DIR", help="encoder directory to write")
    p.add_argument("--force", action="store_true", help="replace the encoder already in DIR")


def add_info_arguments(p: argparse.ArgumentParser) -> None:
    """The description and arguments of ``sync4d encoder info`` (`sync4d.cli`)."""
    p.description = (
        "Print an encoder directory's kind, embedding size, preprocessing and files, after "
        "checking every file's sha256 and loading both graphs."
    )
    p.add_argument("dir", metavar="DIR", help="encoder directory written by 'encoder convert'")


def _size(path: Path) -> str:
    n = path.stat().st_size
    return f"{n / 2**20:.1f} MiB" if n >= 2**20 else f"{n / 2**10:.1f} KiB"


def _convert(args: argparse.Namespace) -> int:
    from sync4d.phase3.encoders.siglip import FILES, MANIFEST, export_pretrained

    out = Path(args.out)
    if (out / MANIFEST).exists() and not args.force:
        print(f"encoder convert: {out} already holds an encoder ({MANIFEST}); --force replaces "
              "it", file=sys.stderr)  # fmt: skip
        return 2
    t0 = time.perf_counter()
    manifest = export_pretrained(args.model, out)
    print(f"encoder convert: {args.model} -> {out} in {time.perf_counter() - t0:.0f} s "
          f"(dim {manifest['dim']}, image {manifest['image_size']} px, "
          f"text {manifest['max_length']} tokens)")  # fmt: skip
    for f in (*FILES, MANIFEST):
        print(f"  {f:<15} {_size(out / f)}")
    return 0


def _info(args: argparse.Namespace) -> int:
    from sync4d.phase3.encoders.siglip import FILES, MANIFEST, SiglipOnnxEncoder

    enc = SiglipOnnxEncoder(args.dir, threads=1)  # checks every digest and both graphs
    m = enc.manifest
    folder = Path(args.dir)
    rows = [
        ("kind", enc.kind),
        ("model", m.get("model") or "?"),
        ("dim", str(enc.dim)),
        ("image", f"{enc.image_size} x {enc.image_size} px, {m['resize']['resample']}, "
                  f"mean {m['mean']}, std {m['std']}"),
        ("text", f"{enc.max_length} tokens, pad id {enc.pad_id}"),
        ("fingerprint", enc.fingerprint),
    ]  # fmt: skip
    for k, v in rows:
        print(f"{k:<12} {v}")
    print("files        (sha256 checked)")
    for f in (*FILES, MANIFEST):
        digest = m["files"].get(f, "")[:16]
        print(f"  {f:<15} {_size(folder / f):>10}  {digest}")
    return 0


def main(args: argparse.Namespace) -> int:
    """Run `encoder convert` or `encoder info` with parsed `args`; the exit status."""
    name = f"encoder {args.action}"
    try:
        return _convert(args) if args.action == "convert" else _info(args)
    except Sync4dError as e:
        print(f"{name}: {e}", file=sys.stderr)
        return e.exit_code
    except KeyboardInterrupt:
        done = "; the folder has no encoder.json, so it is not used" * (args.action == "convert")
        print(f"{name}: interrupted{done}", file=sys.stderr)
        return 130
