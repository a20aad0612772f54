"""Command-line interface: ``sync4d <command> ...`` (the console script) or, the same,
``python -m sync4d <command> ...``.

Every command is one row of `COMMANDS`: its name, its forms (the grammar, `GRAMMAR`), its help,
the module whose ``main(args)`` runs it, the function that adds its arguments, and the earlier
spellings it still answers to. `build_parser`, ``--help``, the shell completion and docs/cli.md
(`scripts/gen_docs.py`) all come from that table, and so does the command list at the end of
this docstring. Adding a command is a row and an argument function here, and its module.

The modules are imported lazily, so ``--help`` stays fast and a missing optional module only
affects the command that needs it. The names the options offer (scorers, activation rules,
encoders) come from their registries in `sync4d.phase3` (numpy only), read when a command's
arguments are added: `main` adds only those of the command it runs.

Old spellings keep working for one release, hidden from ``--help``, the completion and the docs:
a command's earlier names (`Command.aliases`, with a note on stderr) and hidden options
(``options.renamed``, with a note; ``render --times``).
"""

from __future__ import annotations

import argparse
import importlib
import sys
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path

from sync4d import __version__
from sync4d.data import loaders
from sync4d.options import (
    add_bench_fit_options,
    add_bench_raster_options,
    add_threads,
    add_training_options,
    background_colour,
    frame_count,
    port_number,
    positive_float,
    positive_int,
    thread_count,
)

__all__ = ["COMMANDS", "GRAMMAR", "GROUPS", "Command", "build_parser", "command_parsers", "main"]

#: The one rule every command's arguments follow (--help's epilog, docs/cli.md).
GRAMMAR = """\
The grammar, the same for every command:
  * Positional arguments name what a command works on; --out names the folder or file it
    writes. Folders are DATA (a dataset), RUN (a run folder) or DIR (any other).
  * A run is made and extended by fit alone, and fit always names it --out RUN: a new run
    (fit DATA --out RUN), or one continued (--resume), refit from Phase 2 (--phases 2) or
    given its language field (--phases 3), where DATA is optional: the run records it.
  * Every other command that reads a run takes it first, as RUN (eval, render, query, export,
    bench raster, bench phase3, view, serve); --data DATA names the run's dataset if it has
    moved.
  * export writes several files at once, so each of its options names one (--scene FILE)."""


@dataclass(frozen=True)
class Command:
    """One command of the command line (a row of `COMMANDS`)."""

    #: Its words: "fit", "bench raster".
    name: str
    #: Its forms, by `GRAMMAR`: "fit [DATA] --out RUN" (--help's epilog, docs/cli.md).
    forms: tuple[str, ...]
    #: One line for --help's command list.
    help: str
    #: The paragraph of ``sync4d NAME --help``.
    description: str
    #: The module whose ``main(args)`` runs it (imported on use); None: `main` itself.
    module: str | None
    #: Adds its arguments to its parser.
    arguments: Callable[[argparse.ArgumentParser], None]
    #: Earlier names it still answers to, hidden ("encoder export").
    aliases: tuple[str, ...] = ()


@dataclass(frozen=True)
class Group:
    """A word that gathers commands ("bench raster", "bench fit"): its help, and the argument
    name (`dest`) and placeholder of its second word."""

    help: str
    dest: str
    metavar: str


# --------------------------------------------------------------------------------------------
# The arguments of each command
# --------------------------------------------------------------------------------------------

def _encoder_help(prefix: str = "", default: bool = False) -> str:
    """--encoder's help: the encoder kinds of `sync4d.phase3.encoders.encoder.ENCODERS`;
    `default`: with the default when it is not given."""
    from sync4d.phase3.encoders.encoder import DEFAULT_ENCODER, ENCODER_ENV, describe_specs

    last = f"; ${ENCODER_ENV}, else {DEFAULT_ENCODER}, when not given" if default else ""
    return f"{prefix}{describe_specs(summaries=True)}{last}"


def _add_field_encoder(p: argparse.ArgumentParser) -> None:
    """--encoder of a command that reads a built field: the encoder, if it moved."""
    p.add_argument("--encoder", default=None, metavar="DIR",
                   help=_encoder_help("the encoder the field was built with, if it moved: "))


def _add_cpu_threads(p: argparse.ArgumentParser, what: str) -> None:
    """--threads alone (no --backend: a command that composites nothing on a GPU)."""
    p.add_argument("--threads", type=thread_count, default=None, metavar="T",
                   help=f"CPU threads for {what} (default: all cores)")


def _add_rule(p: argparse.ArgumentParser, prefix: str) -> None:
    """--rule: the activation rules of `sync4d.phase3.activation.RULES`."""
    from sync4d.phase3.activation import RULES

    rules = "; ".join(f"{name}: {rule.summary}" for name, rule in RULES.items())
    p.add_argument("--rule", choices=tuple(RULES), default=None,
                   help=f"{prefix}temporal activation, {rules} (default: the field's "
                   "phase3.activation)")  # fmt: skip


def _fit_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("data", nargs="?", default=None, metavar="DATA",
                   help="dataset folder (optional when RUN exists: the run records it)")
    p.add_argument("--out", metavar="RUN", default=None,
                   help="the run folder to write, new or existing (default runs/NAME)")
    add_training_options(
        p, "hyperparameters: a TOML file or a shipped config's name (dnerf, panoptic, "
        "synthetic; default: the paper's values, synthetic for the embedded scene)",
    )  # fmt: skip
    p.add_argument("--iters", type=positive_int, default=None, metavar="N",
                   help="bound each phase to N iterations: Phase 1 trains N, with the config's "
                   "densification, opacity-reset and SH schedules scaled to the new length; "
                   "Phase 2 trains at most N, its start and warm-up iterations and the "
                   "photometric refinement's steps per frame scaled alike. With --resume: "
                   "continue the checkpoint's phase to N iterations")  # fmt: skip
    p.add_argument("--resolution-scale", type=positive_float, default=None, metavar="S",
                   help="downsample images by S, e.g. 0.5")  # fmt: skip
    p.add_argument("--phases", default=None, metavar="P",
                   help="1, 2, 3 or a contiguous list such as 1,2 or 1,2,3 (default from the "
                   "config: 1,2): Phase 1 reconstruction, Phase 2 motion decomposition, Phase "
                   "3 language field; 2 alone restarts Phase 2 from RUN's Phase 1 checkpoint, "
                   "3 alone builds the field of RUN's Phase 2 checkpoint "
                   "(fit --out RUN --phases 3)")  # fmt: skip
    p.add_argument("--encoder", default=None, metavar="DIR",
                   help=_encoder_help("Phase 3's image-text encoder: ", default=True))
    p.add_argument("--resume", action="store_true",
                   help="continue RUN's checkpoint with the data and settings RUN recorded "
                   "(DATA and settings that contradict them are refused)")
    p.add_argument("--force", action="store_true",
                   help="start over in an existing RUN (deletes its results)")


def _process_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("input", metavar="VIDEO|IMAGE_DIR",
                   help="a video file (mp4, mov, mkv, ...) or a folder of photos")
    p.add_argument("--out", required=True, metavar="DATA",
                   help="dataset folder to write (new or empty)")
    p.add_argument("--fps", type=positive_float, default=None, metavar="F",
                   help="video frames to keep per second of video time (default: every "
                   "frame, then --max-frames)")  # fmt: skip
    p.add_argument("--max-frames", type=positive_int, default=150, metavar="N",
                   help="keep at most N frames, evenly spaced (default 150)")
    p.add_argument("--max-size", type=positive_int, default=960, metavar="PX",
                   help="downscale frames whose longest side exceeds PX pixels (default 960)")
    p.add_argument("--camera-model", choices=("SIMPLE_RADIAL", "OPENCV", "PINHOLE"),
                   default="SIMPLE_RADIAL",
                   help="COLMAP model of the one camera all frames share: SIMPLE_RADIAL "
                   "(default: focal + one radial term), OPENCV (two focals, k1, k2, p1, p2: "
                   "wide-angle lenses, needs large frames) or PINHOLE")  # fmt: skip
    p.add_argument("--matcher", choices=("sequential", "exhaustive"), default="sequential",
                   help="sequential (default: each frame with its neighbours in time; "
                   "videos) or exhaustive (every pair; unordered photos, slower)")
    p.add_argument("--threads", type=thread_count, default=None, metavar="T",
                   help="CPU threads for COLMAP (default: all cores)")
    p.add_argument("--force", action="store_true",
                   help="replace what an earlier 'process' wrote in DATA")
    p.add_argument("--verbose", action="store_true", help="show COLMAP's own log")


def _eval_arguments(p: argparse.ArgumentParser) -> None:
    from sync4d.phase3.query import SCORERS

    p.add_argument("run", metavar="RUN", help="run folder written by 'fit'")
    p.add_argument("--data", default=None, metavar="DATA",
                   help="dataset folder, if it moved since training")
    p.add_argument("--split", choices=("test", "train"), default="test")
    p.add_argument("--background", type=background_colour, default=None, metavar="COLOUR",
                   help="composite render and ground truth on this colour instead of the "
                   "run's own: white, black or R,G,B in [0, 1] (Deformable-3DGS and SC-GS "
                   "score D-NeRF on black); writes RUN/eval-<colour>.json")
    p.add_argument("--queries", default=None, metavar="ANNOTATIONS",
                   help="evaluate Phase 3's temporal queries instead (Acc, vIoU, tIoU, "
                   "Appendix F): our query JSON or 4D LangSplat's annotations folder; a relational "
                   "question file (\"kind\": \"relational\") reports Acc, tIoU and counts per "
                   "question form")
    p.add_argument("--scorer", nargs="+", default=None, metavar="S", choices=SCORERS,
                   help=f"with --queries: the scorers to report, of {', '.join(SCORERS)} "
                   "(default: all, in that order)")
    _add_rule(p, "with --queries: ")
    p.add_argument("--encoder", default=None, metavar="DIR",
                   help="with --queries: the encoder the field was built with, if it moved")
    add_threads(p)


def _render_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("run", metavar="RUN", help="run folder (or a checkpoint file)")
    p.add_argument("--time", nargs="+", type=float, default=None, metavar="T", dest="times",
                   help="times in [0, 1], one PNG each (default: a --sweep)")
    p.add_argument("--sweep", type=frame_count, default=48, metavar="N", dest="frames",
                   help="frames of the default time sweep, evenly spaced over [0, 1] "
                   "(default 48)")
    # The spellings before sync4d-render's words: --times, --frames.
    p.add_argument("--times", nargs="+", type=float, dest="times", help=argparse.SUPPRESS)
    p.add_argument("--frames", type=frame_count, dest="frames", help=argparse.SUPPRESS)
    p.add_argument("--camera", default=None, metavar="CAM",
                   help="test:K / train:K (K-th frame of that split), K (a test frame) or a "
                   "frame name such as cam10_000000.jpg; default test:0")
    p.add_argument("--out", default=None, metavar="DIR",
                   help="output folder (default RUN/renders)")
    p.add_argument("--fps", type=positive_float, default=15.0, help="GIF frame rate")
    p.add_argument("--no-gif", action="store_true", help="write PNGs only")
    add_threads(p)


def _query_arguments(p: argparse.ArgumentParser) -> None:
    from sync4d.phase3.query import DEFAULT_SCORER, SCORER_TABLE, SCORERS

    p.add_argument("run", metavar="RUN",
                   help="run folder with a Phase 3 field (fit --out RUN --phases 3)")
    p.add_argument("texts", nargs="+", metavar="TEXT",
                   help="one or more queries; relational ones (first, how many times, while, "
                   "before, highest, never ...) print the plan they were read as "
                   "(docs/phase3-queries.md)")
    scorers = "; ".join(f"{name}: {s.summary}" for name, s in SCORER_TABLE.items())
    p.add_argument("--scorer", choices=SCORERS, default=DEFAULT_SCORER,
                   help=f"{scorers} (default {DEFAULT_SCORER})")
    _add_rule(p, "")
    _add_field_encoder(p)
    p.add_argument("--json", action="store_true", help="print the answers as JSON")
    p.add_argument("--plot", default=None, metavar="DIR",
                   help="folder for the timeline PNGs (default RUN/phase3)")
    p.add_argument("--no-plot", action="store_true", help="write no timeline PNG")


def _export_arguments(p: argparse.ArgumentParser) -> None:
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
    p.add_argument("--decimals", type=positive_int, default=6, metavar="D",
                   help="decimal places of the scene description's numbers (default 6)")
    _add_field_encoder(p)
    _add_cpu_threads(p, "torch")


def _view_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("run", metavar="RUN", help="run folder (one still training is reloaded as "
                   "it saves)")
    p.add_argument("--port", type=port_number, default=8080, metavar="P",
                   help="the port to serve on (default 8080)")
    p.add_argument("--host", default="127.0.0.1", metavar="ADDR",
                   help="the address to listen on (default 127.0.0.1: this machine only; "
                   "0.0.0.0 shares it on the network)")
    p.add_argument("--keep-open", action="store_true",
                   help="keep serving after the last browser tab closes (default: stop)")
    _add_field_encoder(p)
    _add_cpu_threads(p, "torch and the rasterizer")


def _serve_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("run", metavar="RUN", help="run folder written by 'fit' (the language field "
                   "of --phases 3 answers query, describe, track and events)")
    p.add_argument("--http", default=None, metavar="[HOST:]PORT",
                   help="serve over HTTP (streamable HTTP at http://HOST:PORT/mcp) instead of "
                   "stdio; HOST defaults to 127.0.0.1 (this machine only)")
    p.add_argument("--sse", action="store_true",
                   help="with --http: the older SSE transport (at /sse) for clients without "
                   "streamable HTTP")
    _add_field_encoder(p)
    _add_cpu_threads(p, "torch and the rasterizer")


def _bench_phase3_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("runs", nargs="+", metavar="RUN", help="Phase 2 run folders")
    p.add_argument("--encoder", default=None, metavar="DIR",
                   help=_encoder_help(default=True))
    p.add_argument("--queries", nargs="+", default=None, metavar="TEXT",
                   help="the queries to time (default: five identity, state and motion "
                   "queries)")  # fmt: skip
    p.add_argument("--repeat", type=positive_int, default=3, metavar="N",
                   help="timings per query (the median is reported; default 3)")
    p.add_argument("--out", default=None, metavar="FILE.json",
                   help="results JSON (default bench-phase3.json)")
    add_threads(p)


def _sweep_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("manifest", metavar="MANIFEST.toml",
                   help="the jobs: [[job]] entries and/or a [grid] (docs/sweep.md)")
    p.add_argument("--out", required=True, metavar="SWEEP",
                   help="folder of the sweep: runs/, logs/, results.csv/json, psnr-time.png")
    p.add_argument("--address", default=None, metavar="auto|HOST:PORT",
                   help="join a running Ray cluster (default: a local Ray in this process)")
    p.add_argument("--cpus", type=positive_int, default=None, metavar="N",
                   help="CPUs the local Ray may use (default: all)")


def _bench_view_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("run", metavar="RUN", help="run folder")
    p.add_argument("--moves", type=positive_int, default=30, metavar="N",
                   help="slider moves to time (default 30)")
    p.add_argument("--query", default="the red ball", metavar="TEXT",
                   help="a query to time too, when the run has a field (default: the red ball)")
    p.add_argument("--out", default="bench-view.json", metavar="FILE.json",
                   help="results JSON (default bench-view.json)")
    _add_cpu_threads(p, "torch")


def _bench_step_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("run", metavar="RUN", help="run folder (its Gaussians are stepped)")
    p.add_argument("--variant", action="append", default=None, metavar="NAME[:KEY=VALUE,...]",
                   help="a motion variant: overrides of the run's config (repeatable; default: "
                   "gaussians:phase1.motion=gaussians and nodes:phase1.motion=nodes)")  # fmt: skip
    p.add_argument("--steps", type=positive_int, default=10, metavar="N",
                   help="steps timed per round and variant (default 10)")
    p.add_argument("--rounds", type=positive_int, default=3, metavar="R",
                   help="rounds, each variant in turn (default 3)")
    p.add_argument("--data", default=None, metavar="DATA",
                   help="the run's dataset, if it has moved")
    p.add_argument("--out", default="bench-step.json", metavar="FILE.json",
                   help="results JSON (default bench-step.json)")
    _add_cpu_threads(p, "torch and the rasterizer")


def _encoder_convert_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--model", default="google/siglip-base-patch16-224", metavar="NAME",
                   help="Hugging Face model id or a local save_pretrained folder "
                   "(default google/siglip-base-patch16-224)")  # fmt: skip
    p.add_argument("--out", required=True, metavar="DIR", help="encoder directory to write")
    p.add_argument("--force", action="store_true", help="replace the encoder already in DIR")


def _encoder_info_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("dir", metavar="DIR", help="encoder directory written by 'encoder convert'")


def _completion_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("shell", choices=("bash", "zsh"), help="the shell to complete for")


# --------------------------------------------------------------------------------------------
# The commands
# --------------------------------------------------------------------------------------------

#: The words that gather commands.
GROUPS: dict[str, Group] = {
    "bench": Group("run a benchmark", "target", "TARGET"),
    "encoder": Group("convert or inspect a SigLIP-ONNX encoder (Phase 3)", "action", "ACTION"),
}

#: Every command, in --help's order.
COMMANDS: tuple[Command, ...] = (
    Command(
        "fit", ("fit [DATA] --out RUN", "fit --out RUN --resume | --phases 2 | --phases 3"),
        "train a deformable 4D Gaussian scene (Phase 1) and decompose its motion (Phase 2)",
        f"Train Phase 1, then Phase 2, on a dataset folder ({loaders.titles()}) or, without "
        "DATA, on the embedded synthetic scene, into the run folder RUN; --phases 3 adds the "
        "language field. Ctrl-C saves a checkpoint; fit --out RUN --resume continues it.",
        "sync4d.commands.fit", _fit_arguments,
    ),
    Command(
        "process", ("process VIDEO|IMAGE_DIR --out DATA",),
        "turn your own video or photos into a dataset (camera poses from COLMAP)",
        "Extract frames from a video (PyAV) or read a folder of photos (sorted by name), "
        "recover one shared camera and every frame's pose with COLMAP (pycolmap: SIFT, "
        "matching, incremental mapping), undistort the frames to a pinhole camera and write a "
        "nerfstudio dataset (transforms.json with per-frame time, images/, sparse_pc.ply) that "
        "'fit DATA' reads. Frames COLMAP cannot register are left out and named.",
        "sync4d.commands.process", _process_arguments,
    ),
    Command(
        "eval", ("eval RUN", "eval RUN --queries ANNOTATIONS"),
        "PSNR / SSIM / LPIPS of a run, or its temporal queries (--queries)",
        "Evaluate a run's checkpoint on its dataset's test split (writes RUN/eval.json), or "
        "with --queries its Phase 3 field on annotated temporal queries (writes "
        "RUN/phase3/eval-NAME*.csv/json).",
        "sync4d.commands.eval", _eval_arguments,
    ),
    Command(
        "render", ("render RUN [--time T... | --sweep N] [--out DIR]",),
        "render a run at chosen times",
        "Render a run's checkpoint from one of its stored cameras at chosen times (default: a "
        "sweep over [0, 1]) to PNGs and a GIF.",
        "sync4d.commands.render", _render_arguments,
    ),
    Command(
        "query", ("query RUN TEXT...",),
        "ask a run's language field which object matches a text, and when",
        "Rank a run's objects for each text query and give the frames where each is active, "
        "from the Phase 3 field (fit --out RUN --phases 3). Writes a timeline PNG per query.",
        "sync4d.commands.query", _query_arguments,
    ),
    Command(
        "export", ("export RUN --scene FILE.json [--prompt FILE.txt] [--vocab FILE]",
                   "export RUN --ply FILE.ply | --spz FILE.spz [--time T]",
                   "export RUN --sequence FILE.ply|DIR/ [--frames N]"),
        "write a run as files other tools read: scene description, LLM prompt, PLY, SPZ",
        "Write the scene description of a run with a language field (objects, per-frame "
        "tracks, motion segments, contacts and other events, language slots; JSON valid "
        "against the schema shipped in sync4d/export, deterministic), a plain-text summary of "
        "it for an LLM, and the Gaussians as 3DGS PLY or SPZ at a time, or as a 4D sequence "
        "(brush's delta-frame PLY, or a folder of PLYs for SuperSplat's timeline). Each option "
        "names the file it writes.",
        "sync4d.commands.export", _export_arguments,
    ),
    Command(
        "view", ("view RUN [--port P] [--host ADDR]",),
        "open a run in the browser: scrub time, see each object move, ask a question",
        "Serve a run's Gaussians on a local web page (viser): a time slider with play and "
        "speed, the dataset's cameras, the objects (show, isolate, highlight) and their "
        "tracks, a query box that ranks the objects and lights up the answer while it is "
        "active, and a button that renders the current view through sync4d's rasterizer "
        "into RUN/renders. Ctrl-C, or closing the last tab, stops it.",
        "sync4d.commands.view", _view_arguments,
    ),
    Command(
        "serve", ("serve RUN [--http [HOST:]PORT]",),
        "serve a run to AI agents over the Model Context Protocol (MCP)",
        "Serve a run to an MCP client (an LLM desktop app, an agent): tools describe (the "
        "scene description), query (which object matches a text, and when), track (an "
        "object's pose, velocity and box over an interval), events (contacts, approaches, "
        "motion segments) and render (a PNG at a time and camera), and the scene JSON and "
        "LLM prompt as resources. Over stdio (the client starts it), or --http. docs/mcp.md "
        "has a client's configuration.",
        "sync4d.commands.serve", _serve_arguments,
    ),
    Command(
        "sweep", ("sweep MANIFEST.toml --out SWEEP [--address auto|HOST:PORT]",),
        "fit many scenes, configs and seeds on Ray, locally or on a cluster",
        "Run every job of a manifest (dataset, config, overrides, seeds, phases; or a grid of "
        "them) as a Ray task with its CPU count declared and torch, rayon and OpenMP threads "
        "pinned to it, each into a normal run folder under SWEEP/runs; finished runs are not "
        "run again, interrupted ones resume, failed ones are reported with their log's tail. "
        "Writes a table (CSV, JSON, printed) and a plot of test PSNR against training time. "
        "Needs Ray: pip install 'sync4d[sweep]'.",
        "sync4d.sweep", _sweep_arguments,
    ),
    Command(
        "bench raster", ("bench raster [RUN]",),
        "rasterizer forward/backward timings",
        "Time sync4d.raster (forward and backward) on seeded random scenes or, given RUN, on "
        "the run's own Gaussians at its test cameras.",
        "sync4d.bench.raster", add_bench_raster_options,
    ),
    Command(
        "bench fit", ("bench fit [DATA]", "bench fit --runs RUN..."),
        "Phase 1 test PSNR against training time (Pareto curve)",
        "Train one scene at several budgets (iterations x resolution scale x Gaussian cap) and "
        "write a JSON and a PNG plot of test PSNR against training time; --runs tabulates "
        "finished runs instead.",
        "sync4d.bench.fit", add_bench_fit_options,
    ),
    Command(
        "bench phase3", ("bench phase3 RUN...",),
        "Phase 3 build time and query latency on Phase 2 runs",
        "Build each run's language field in a temporary folder (the run is not touched) and "
        "time its steps and text queries, cold and cached; writes a JSON.",
        "sync4d.bench.phase3", _bench_phase3_arguments,
    ),
    Command(
        "bench step", ("bench step RUN",),
        "where a Phase 1 step's time goes, per motion model (D_theta per Gaussian or nodes)",
        "Step a run's Gaussians with each variant of its config in turn and time the whole "
        "step, the motion (D_theta, the node blend) and the rasterizer, forward and backward; "
        "prints a table and writes a JSON.",
        "sync4d.bench.step", _bench_step_arguments,
    ),
    Command(
        "bench view", ("bench view RUN",),
        "the viewer's time-slider latency on a run",
        "Serve a run in the viewer and time slider moves to new and to cached times (from "
        "the change to the splats sent) and a query; prints a table and writes a JSON.",
        "sync4d.bench.view", _bench_view_arguments,
    ),
    Command(
        "encoder convert", ("encoder convert --out DIR [--model NAME]",),
        "convert a Hugging Face SigLIP model into a SigLIP-ONNX encoder directory",
        "Download a SigLIP model (needs internet once and the export extra: pip install "
        "'sync4d[export]'), convert it to ONNX and write DIR: vision.onnx, text.onnx, "
        "tokenizer.json and the manifest encoder.json. Phase 3 then runs it with onnxruntime, "
        "offline (--encoder DIR or $SYNC4D_ENCODER).",
        "sync4d.commands.encoder", _encoder_convert_arguments, aliases=("encoder export",),
    ),
    Command(
        "encoder info", ("encoder info DIR",),
        "describe an encoder directory and check its files",
        "Print an encoder directory's kind, embedding size, preprocessing and files, after "
        "checking every file's sha256 and loading both graphs.",
        "sync4d.commands.encoder", _encoder_info_arguments,
    ),
    Command(
        "completion", ("completion bash|zsh",),
        "print a shell completion script (bash or zsh)",
        "Print a completion script for the sync4d command. bash: sync4d completion bash > "
        "~/.local/share/bash-completion/completions/sync4d; zsh: sync4d completion zsh > "
        "~/.zfunc/_sync4d (with ~/.zfunc on $fpath).",
        None, _completion_arguments,
    ),
)


def command_list(helps: bool = True) -> str:
    """Every command's forms, one line each, and its help below them (`helps`)."""
    lines = []
    for c in COMMANDS:
        lines += [f"  {form}" for form in c.forms] + ([f"      {c.help}"] if helps else [])
    return "\n".join(lines)


def _defaults(name: str) -> dict[str, str]:
    """The words of command `name` as parsed arguments: command="bench", target="raster"."""
    first, *rest = name.split()
    out = {"command": first}
    if rest:
        out[GROUPS[first].dest] = rest[0]
    return out


def _wanted(argv: Sequence[str]) -> str:
    """The command words `argv` starts with ("query", "bench raster"; "" for none)."""
    words = [a for a in argv if not a.startswith("-")]
    if words and words[0] in GROUPS:
        return " ".join(words[:2])
    return words[0] if words else ""


def build_parser(prog: str = "sync4d", argv: Sequence[str] | None = None
                 ) -> argparse.ArgumentParser:  # fmt: skip
    """The parser of every command in `COMMANDS`, old spellings included (hidden). Given the
    command line `argv`, only the command it runs gets its arguments (`main`: ``--help`` imports
    no registry); every command is listed either way."""
    wanted = None if argv is None else _wanted(argv)
    parser = argparse.ArgumentParser(
        prog=prog,
        description="sync4d: 4D Synchronized Fields (CPU Gaussian splatting in Rust + PyTorch).",
        epilog=f"forms (sync4d COMMAND --help: its options):\n{command_list(helps=False)}\n\n"
        f"{GRAMMAR}",
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument("--version", action="version", version=f"sync4d {__version__}")
    levels = {"": parser.add_subparsers(dest="command", metavar="COMMAND", required=True)}
    for cmd in COMMANDS:
        for name in (cmd.name, *cmd.aliases):
            *group, leaf = name.split()
            key = " ".join(group)
            if key not in levels:  # the group's own parser, on its first command
                g = GROUPS[key]
                words = levels[""].add_parser(key, help=g.help)
                levels[key] = words.add_subparsers(dest=g.dest, metavar=g.metavar, required=True)
            hidden = name != cmd.name  # no help: argparse and shtab list it nowhere
            sub = levels[key].add_parser(leaf, description=cmd.description,
                                         **({} if hidden else {"help": cmd.help}))
            if wanted is None or wanted == name:
                cmd.arguments(sub)
            sub.set_defaults(handler=cmd.module, renamed=(name, cmd.name) if hidden else None,
                             **_defaults(cmd.name))  # fmt: skip
    _complete_paths(parser)
    return parser


def command_parsers(parser: argparse.ArgumentParser) -> dict[str, argparse.ArgumentParser]:
    """The parser of every visible command of `parser` by its words ("bench raster"), in
    `COMMANDS`' order; hidden old spellings left out."""
    out: dict[str, argparse.ArgumentParser] = {}

    def walk(p: argparse.ArgumentParser, prefix: str) -> None:
        for action in p._actions:
            if isinstance(action, argparse._SubParsersAction):
                for shown in action._choices_actions:  # the names given a help
                    sub = action.choices[shown.dest]
                    full = f"{prefix} {shown.dest}".strip()
                    if any(isinstance(a, argparse._SubParsersAction) for a in sub._actions):
                        walk(sub, full)
                    else:
                        out[full] = sub

    walk(parser, "")
    return out


def _complete_paths(parser: argparse.ArgumentParser) -> None:
    """Mark path arguments (metavars DATA, RUN, DIR, FILE...) for shtab's completion: folders
    complete as folders, files as files. Without shtab the parser is unchanged."""
    try:
        import shtab
    except ImportError:
        return
    folders = {"DATA", "RUN", "DIR", "RUNS"}
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            for sub in action.choices.values():
                _complete_paths(sub)
        elif action.metavar in folders:
            action.complete = shtab.DIRECTORY  # type: ignore[attr-defined]
        elif isinstance(action.metavar, str) and (
            action.metavar.startswith("FILE")
            or action.metavar in ("ANNOTATIONS", "CONFIG", "VIDEO|IMAGE_DIR")
        ):
            action.complete = shtab.FILE  # type: ignore[attr-defined]


def _print_completion(parser: argparse.ArgumentParser, shell: str) -> int:
    try:
        import shtab
    except ImportError:
        print("sync4d completion: needs the shtab package: python -m pip install shtab",
              file=sys.stderr)  # fmt: skip
        return 2
    print(shtab.complete(parser, shell=shell, root_prefix="sync4d"))
    return 0


def main(argv: Sequence[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else list(argv)
    _tolerate_undecodable_output()
    args = build_parser(_prog(), argv).parse_args(argv)
    if args.renamed is not None:
        old, new = args.renamed
        print(f"sync4d: `{old}` is now `{new}` (the old spelling goes after this release)",
              file=sys.stderr)  # fmt: skip
    if args.command == "completion":  # completes every command: all their arguments
        return _print_completion(build_parser("sync4d"), args.shell)
    module_name: str = args.handler
    try:
        module = importlib.import_module(module_name)
    except ModuleNotFoundError as exc:
        if exc.name is not None and module_name.startswith(exc.name):
            print(
                f"python -m sync4d: '{args.command}' is not available: "
                f"module {module_name} is missing from this install",
                file=sys.stderr,
            )
            return 2
        raise
    _bound_torch_threads(args)
    if not hasattr(args, "backend"):  # e.g. query: no rendering, no torch import
        return _call(module, args)
    from sync4d import raster

    backend = getattr(args, "backend", None)
    previous = raster.resolve_backend()
    if backend not in (None, "cpu"):
        try:
            args.backend = raster.set_default_backend(backend)
        except RuntimeError as e:
            print(f"python -m sync4d {args.command}: {e}", file=sys.stderr)
            return 2
        if backend == "wgpu":
            print(f"sync4d: backend wgpu on {_core_adapter()}", file=sys.stderr)
    try:
        return _call(module, args)
    finally:
        raster.set_default_backend(previous)  # main() may be called again in-process


def _call(module, args: argparse.Namespace) -> int:  # noqa: ANN001
    """`module.main(args)`'s exit status. The watchdog's stop (a NaN or a diverged value in
    what a command renders or solves) becomes its one message and exit 3; an OSError that
    reaches here (a path of the command line the system refuses: too long, a folder where a
    file goes, no permission) becomes one line naming the path, and exit 2."""
    try:
        return int(module.main(args) or 0)
    except FloatingPointError as e:  # the watchdog's NonFinite (no torch import here)
        if type(e).__name__ != "NonFinite":
            raise
        print(f"{_prog()} {args.command}: {e}", file=sys.stderr)
        return 3
    except OSError as e:
        group = GROUPS.get(args.command)
        words = " ".join([args.command] + ([getattr(args, group.dest)] if group else []))
        name = str(e.filename) if e.filename is not None else ""
        shown = f"{name[:80]}... ({len(name)} characters)" if len(name) > 100 else name
        if not name:  # not a path: a connection, a device
            print(f"{_prog()} {words}: {e}", file=sys.stderr)
            return 2
        print(f"{_prog()} {words}: {e.strerror or e}: {shown!r}; check the paths on the command "
              "line (a folder that exists and is writable, names of a sane length)",
              file=sys.stderr)  # fmt: skip
        return 2


def _tolerate_undecodable_output() -> None:
    """Let stdout and stderr print the paths of any command line: argv's bytes that are not
    UTF-8 arrive as surrogate escapes, which a strict stream refuses (UnicodeEncodeError);
    stdout writes them back as the same bytes, stderr as backslash escapes (its default)."""
    for stream, errors in ((sys.stdout, "surrogateescape"), (sys.stderr, "backslashreplace")):
        if getattr(stream, "errors", None) == "strict" and hasattr(stream, "reconfigure"):
            stream.reconfigure(errors=errors)


def _bound_torch_threads(args: argparse.Namespace) -> None:
    """`--threads T`: torch's intra-op threads before the command runs anything (the command
    modules import torch but run no op on import; query, which does not import it, stays
    light). Measured (issue 51): `eval RUN --threads 1` and `render RUN --threads 1` set them
    after `load_run`, whose ops had started a second OpenMP thread already (0.4 s of the 3.8 s
    of CPU time of an eval of the embedded scene)."""
    threads = getattr(args, "threads", None)
    if type(threads) is int and "torch" in sys.modules:  # not bench raster's list
        import torch

        torch.set_num_threads(threads)


def _prog() -> str:
    """The name the user typed: ``sync4d`` (console script) or ``python -m sync4d``."""
    return "python -m sync4d" if Path(sys.argv[0]).name == "__main__.py" else "sync4d"


def _core_adapter() -> str:
    from sync4d import _core

    return _core.wgpu_adapter()


__doc__ = f"{__doc__}\nCommands (from `COMMANDS`; every option: docs/cli.md):\n{command_list()}\n"

if __name__ == "__main__":
    sys.exit(main())
