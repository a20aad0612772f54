"""``sync4d export RUN ...``: a run as files other tools read (docs/export.md). Each option names
the file it writes:

* ``--scene FILE.json``: the scene description (objects, tracks, motion segments, events,
  language slots; JSON Schema in the package) and its embeddings side file;
* ``--prompt FILE.txt``: a plain-text summary for an LLM, made from that JSON alone, with its
  token count;
* ``--ply FILE.ply`` / ``--spz FILE.spz``: the Gaussians at ``--time T`` (default: canonical);
* ``--sequence FILE.ply|DIR/``: the scene over time (``--frames N``, default the run's
  stored frames), as brush's delta-frame PLY or a folder of per-time PLYs named for
  SuperSplat's sequence import (times in ``DIR.json`` beside it); ``FILE.zip`` (deprecated)
  a zip of per-time PLYs;
* ``--4dgs FILE.4dgs``: the open ``.4dgs`` container (canonical Gaussians with SH, each
  Gaussian's object, M_phi's tracks refined to D_theta, the Object Table with Phase 3's
  embeddings, D_theta's residual where a track alone is not close enough: ``--4dgs-residual``,
  ``--4dgs-tolerance``) through ``fourdgs`` (optional: ``pip install
  'sync4d[4dgs]'``); ``--4dgs-snapshot FILE.glb|FILE.usd`` one instant of it (``--time T``) as
  glTF (KHR_gaussian_splatting) or USD through fourdgs' converters.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from sync4d.errors import Sync4dError
from sync4d.files import write_text_atomic
from sync4d.options import (
    add_encoder,
    add_threads,
    frame_count,
    non_negative_float,
    positive_int,
)

#: `--4dgs-tolerance`'s default and `--4dgs-residual`'s choices: `sync4d.export.fourdgs`'s
#: `TOLERANCE` and `RESIDUAL_CHOICES` (a test keeps them equal; that module imports numpy, which
#: parsing a command line does not).
TOLERANCE = 0.25
RESIDUAL_CHOICES = ("all", "background", "none")

__all__ = ["add_arguments", "main", "read_vocab"]


def add_arguments(p: argparse.ArgumentParser) -> None:
    """The description and arguments of ``sync4d export`` (`sync4d.cli`)."""
    p.description = (
        "Write the scene description of a run with a language field (objects, per-frame "
        "tracks, motion segments, contacts and other events, language slots; JSON valid "
        "against the schema shipped in sync4d/export, deterministic), a plain-text summary of "
        "it for an LLM, and the Gaussians as 3DGS PLY or SPZ at a time, or as a 4D sequence "
        "(brush's delta-frame PLY, or a folder of PLYs for SuperSplat's timeline). Each option "
        "names the file it writes."
    )
    p.add_argument("run", metavar="RUN", help="run folder written by 'fit'")
    p.add_argument("--scene", default=None, metavar="FILE.json",
                   help="the scene description (needs the language field: fit --out RUN "
                   "--phases 3); embeddings go beside it in FILE.embeddings.safetensors")
    p.add_argument("--prompt", default=None, metavar="FILE.txt",
                   help="a plain-text summary of the scene description for an LLM")
    p.add_argument("--vocab", default=None, metavar="FILE",
                   help="vocabulary (one entry per line, or a JSON list): each object's "
                   "nearest entries, and where each entry is active")
    p.add_argument("--query", nargs="+", default=None, metavar="TEXT",
                   help="queries whose active frames go into the description")
    p.add_argument("--ply", default=None, metavar="FILE.ply",
                   help="the Gaussians as a 3DGS PLY (gsplat's layout plus object_id)")
    p.add_argument("--spz", default=None, metavar="FILE.spz",
                   help="the Gaussians as SPZ (compressed, lossy; no object ids)")
    p.add_argument("--time", type=float, default=None, metavar="T",
                   help="with --ply / --spz: the scene deformed to time T in [0, 1] "
                   "(default: the canonical Gaussians)")
    p.add_argument("--sequence", default=None, metavar="FILE.ply|DIR/",
                   help="the scene over time: FILE.ply is brush's delta-frame PLY (brush 0.3 "
                   "and earlier play it); DIR/ a folder of one PLY per time, NAME_0000.ply ..., "
                   "that SuperSplat imports as a sequence, times in DIR.json beside it; "
                   "FILE.zip (deprecated) a zip of PLYs")
    p.add_argument("--frames", type=frame_count, default=None, metavar="N",
                   help="with --sequence: N evenly spaced times (default: the run's frames)")
    p.add_argument("--4dgs", dest="fourdgs", default=None, metavar="FILE.4dgs",
                   help="the scene as a .4dgs file (canonical Gaussians with SH, Phase 2's "
                   "object of each Gaussian, one track per moving object from M_phi, the "
                   "object table with Phase 3's embeddings); needs fourdgs: pip install "
                   "'sync4d[4dgs]'")
    p.add_argument("--4dgs-residual", dest="fourdgs_residual", default=None,
                   choices=RESIDUAL_CHOICES,
                   help="with --4dgs: which Gaussians may keep D_theta's residual over their "
                   "track as piecewise-linear records: all (default), background (the objects "
                   "move by their tracks alone), none (the tracks alone move the objects and "
                   "the background stands still)")
    p.add_argument("--4dgs-tolerance", dest="fourdgs_tolerance", type=non_negative_float,
                   default=None, metavar="T",
                   help="with --4dgs: how far a Gaussian may be from D_theta at a stored frame "
                   "before it gets a residual, in pixels of the training camera that sees it "
                   f"largest, times its opacity (default {TOLERANCE}; 0: every stored frame "
                   "exact; larger: a smaller file)")
    p.add_argument("--4dgs-snapshot", dest="fourdgs_snapshot", default=None,
                   metavar="FILE.glb|FILE.usd",
                   help="with --4dgs: the file's state at --time T (default 0) as glTF "
                   "(KHR_gaussian_splatting; .glb or .gltf) or USD (.usd/.usda/.usdc, needs "
                   "usd-core), tracks composed; static, no object ids")
    p.add_argument("--decimals", type=positive_int, default=6, metavar="D",
                   help="decimal places of the scene description's numbers (default 6)")
    add_encoder(p)
    add_threads(p, "torch")


class _Usage(Sync4dError, ValueError):
    """A command line that asks for nothing, or for something that does not fit."""


def read_vocab(path: str | Path) -> list[str]:
    """The entries of a vocabulary file: a JSON list of strings, or a text file with one entry
    per line (blank lines and lines starting with # skipped). ValueError naming the file."""
    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as e:
        raise _Usage(f"{path}: cannot read the vocabulary file ({e})") from None
    if text.lstrip().startswith("["):
        try:
            items = json.loads(text)
        except ValueError as e:
            raise _Usage(f"{path}: not valid JSON ({e}); give a JSON list of strings or one "
                         "entry per line") from None  # fmt: skip
        if not all(isinstance(x, str) for x in items):
            raise _Usage(f"{path}: a JSON vocabulary must be a list of strings")
    else:
        items = [ln for ln in text.splitlines() if not ln.lstrip().startswith("#")]
    entries = [" ".join(x.split()) for x in items if x.strip()]
    if not entries:
        raise _Usage(f"{path}: the vocabulary file has no entries (one per line)")
    return list(dict.fromkeys(entries))


def _scene(args: argparse.Namespace, run, out: list[str]) -> None:
    """Write the scene description (and the prompt) that `args` ask for."""
    from sync4d.export.describe import SceneSettings, describe
    from sync4d.export.prompt import count_tokens, prompt_text
    from sync4d.export.scene import embeddings_path, write_scene
    from sync4d.phase3.query import TextCache
    from sync4d.phase3.store import load_field

    field = load_field(run.path)
    vocab = read_vocab(args.vocab) if args.vocab else []
    queries = list(dict.fromkeys(" ".join(q.split()) for q in args.query or []))
    cache = TextCache(run.path, field, args.encoder) if vocab or queries else None
    scene, emb = describe(run, field, cache=cache, vocab=vocab, queries=queries,
                          settings=SceneSettings(decimals=args.decimals))  # fmt: skip
    if cache is not None:
        cache.save()
    if args.scene:
        path = write_scene(args.scene, scene, emb)
        out.append(f"scene: {path} ({len(scene.objects)} objects, "
                   f"{len(scene.metadata.frames.times)} frames, {len(scene.events)} events; "
                   f"embeddings in {embeddings_path(path)})")
    if args.prompt:  # from the description's data alone, as the file holds it
        text = prompt_text(scene.model_dump())
        write_text_atomic(Path(args.prompt), text)
        n, tokenizer = count_tokens(text)
        out.append(f"prompt: {args.prompt} ({n:,} tokens by {tokenizer})")


def _splats(args: argparse.Namespace, run, out: list[str]) -> None:
    """Write the splat files that `args` ask for."""
    from sync4d.export import splats as sp

    when = "canonical" if args.time is None else f"t = {args.time:g}"
    if args.ply or args.spz:
        g = sp.splats_at(run, args.time)
        if args.ply:
            sp.write_ply(args.ply, g)
            out.append(f"ply: {args.ply} ({len(g.means):,} Gaussians, {when})")
        if args.spz:
            sp.write_spz(args.spz, g)
            out.append(f"spz: {args.spz} ({len(g.means):,} Gaussians, {when})")
    if args.fourdgs:
        _fourdgs(args, run, out)
    if args.sequence:
        times = sp.default_times(run, args.frames)
        if sp.is_sequence_folder(args.sequence):
            folder = sp.write_sequence_folder(args.sequence, run, times)
            out.append(f"sequence: {folder}/ ({len(times)} frames, "
                       f"{sp.sequence_frame_name(folder, 0)} ...; times in "
                       f"{sp.sequence_sidecar(folder)})")  # fmt: skip
        else:
            sp.write_sequence(args.sequence, run, times)
            out.append(f"sequence: {args.sequence} ({len(times)} frames)")
            if Path(args.sequence).suffix.lower() == ".zip":
                print("export: --sequence FILE.zip is deprecated (no viewer imports it); "
                      "--sequence DIR/ writes the frames as a folder SuperSplat plays",
                      file=sys.stderr)  # fmt: skip


def _fourdgs(args: argparse.Namespace, run, out: list[str]) -> None:
    """Write the .4dgs file (and its snapshot) that `args` ask for."""
    from sync4d.export import fourdgs as fd

    kw = {"residual": args.fourdgs_residual, "tolerance": args.fourdgs_tolerance}
    rep = fd.write_4dgs(args.fourdgs, run, **{k: v for k, v in kw.items() if v is not None})
    what = (f"{rep.tracks} tracks" if rep.tracks else "no tracks (no Phase 2)")
    residual = (f"D_theta's residual on {rep.residual_gaussians:,} Gaussians "
                f"({rep.records:,} records)" if rep.residual_gaussians
                else "no residual: the tracks alone move the objects")
    emb = f"embeddings: {rep.embeddings}" if rep.embeddings else (rep.note or "no embeddings")
    out.append(f"4dgs: {rep.path} ({rep.bytes:,} bytes, {rep.gaussians:,} Gaussians, "
               f"{len(rep.objects)} objects, {what}; {residual}; {emb})")
    if args.fourdgs_snapshot:
        t = 0.0 if args.time is None else args.time
        n = fd.snapshot(args.fourdgs_snapshot, fd.read_4dgs(rep.path), t)
        usd = Path(args.fourdgs_snapshot).suffix.lower() in (".usd", ".usda", ".usdc")
        checked = ("OpenUSD's runtime opens it" if usd else "fourdgs' glTF importer reads it")
        out.append(f"4dgs snapshot: {args.fourdgs_snapshot} ({n:,} bytes, t = {t:g}; {checked} "
                   "in sync4d's tests; no graphical viewer was checked)")


def main(args: argparse.Namespace) -> int:
    """Run `export` with parsed `args`; the exit status."""
    from sync4d.runs import load_run

    out: list[str] = []
    try:
        if not (args.scene or args.prompt or args.ply or args.spz or args.sequence
                or args.fourdgs):
            raise _Usage("nothing to export: give --scene FILE.json, --prompt FILE.txt, "
                         "--ply FILE.ply, --spz FILE.spz, --sequence FILE.ply|DIR/ or "
                         "--4dgs FILE.4dgs")
        if (args.fourdgs_residual or args.fourdgs_tolerance is not None
                or args.fourdgs_snapshot) and not args.fourdgs:
            raise _Usage("--4dgs-residual, --4dgs-tolerance and --4dgs-snapshot go with --4dgs "
                         "FILE.4dgs")
        if (args.vocab or args.query) and not (args.scene or args.prompt):
            raise _Usage("--vocab and --query fill the scene description: add --scene "
                         "FILE.json or --prompt FILE.txt")  # fmt: skip
        for flag, ext in (("scene", "json"), ("prompt", "txt"), ("ply", "ply"), ("spz", "spz"),
                          ("fourdgs", "4dgs")):  # fmt: skip
            given = getattr(args, flag)  # each names a file to write, not a folder
            if given is not None and (Path(given).name in ("", "..") or Path(given).is_dir()):
                name = "4dgs" if flag == "fourdgs" else flag
                raise _Usage(f"--{name} {given[:80]!r} is a folder; give the file to write, "
                             f"e.g. --{name} {given.rstrip('/') or '.'}/scene.{ext}")
        if args.time is not None and not 0.0 <= args.time <= 1.0:
            raise _Usage(f"--time {args.time}: times are normalised, give one in [0, 1]")
        if args.threads:
            import torch

            torch.set_num_threads(args.threads)
        run = load_run(args.run)
        if args.scene or args.prompt:
            _scene(args, run, out)
        _splats(args, run, out)
    except (Sync4dError, OSError) as e:  # OSError: a file the system refuses
        print(f"export: {e}", file=sys.stderr)
        return 2
    print("\n".join(out))
    return 0
