"""``python -m sync4d bench fit [DATA]``: run time against error for Phase 1.

Trains the same scene at several budgets (iterations x resolution scale x Gaussian cap), each a
full `fit` run with its schedule scaled to the budget, and records training seconds against
test PSNR / SSIM / LPIPS and the worst test view (SSIM: the standard 11x11 Gaussian SSIM; the
training loss's 3x3 box SSIM is kept as ``ssim_box3``, docs/metrics.md). Writes a JSON, a PNG
plot of test PSNR against wall time with the Pareto front (no other budget is both faster and
better) marked, so a user can pick the budget that fits their time, and the largest budget's
worst test view rendered beside its ground truth (``<out>-worst.png``).

``bench fit --runs RUN [RUN ...]`` trains nothing: it tabulates finished `fit` runs (one per
scene, say) in the same JSON and table, a row per run, and copies each run's worst test view
beside the JSON (``<out>-<scene>-worst.png``), so a table over several scenes comes from the
runs that produced their numbers. Each row's ``metrics`` says what its metrics are (eval.json's
record, docs/metrics.md); a run evaluated before the standard SSIM has ``"ssim": null``,
``"metrics": null`` and its old value under ``ssim_box3``; the table marks it "box".
"""

from __future__ import annotations

import argparse
import dataclasses
import datetime as _dt
import json
import platform
import shutil
import sys
import tempfile
from itertools import product
from pathlib import Path
from typing import TYPE_CHECKING, Any

from sync4d.errors import Sync4dError
from sync4d.options import add_training_options, positive_float, positive_int
from sync4d.report import align_table
from sync4d.runs.names import EVAL_FILE, RENDERS_DIR
from sync4d.settings import ConfigError
from sync4d.terminal import TerminalRenderer

if TYPE_CHECKING:
    from sync4d.config import RunConfig

__all__ = ["add_arguments", "main", "pareto_front", "plot_pareto", "rows_from_runs", "run_grid"]


def add_arguments(p: argparse.ArgumentParser) -> None:
    """The description and arguments of ``sync4d bench fit`` (`sync4d.cli`)."""
    p.description = (
        "Train one scene at several budgets (iterations x resolution scale x Gaussian cap) "
        "and write a JSON and a PNG plot of test PSNR against training time; --runs tabulates "
        "finished runs instead."
    )
    p.add_argument("data", nargs="*", default=[], metavar="DATA",
                   help="dataset folders, each trained with every budget and variant in "
                   "one invocation (default: the embedded synthetic scene)")
    add_training_options(p, "hyperparameters of every budget (default as for 'fit')")
    p.add_argument("--iters", nargs="+", type=positive_int, metavar="N", default=None,
                   help="iteration budgets (default: 1/8, 1/4, 1/2 and all of the config's)")
    p.add_argument("--scales", nargs="+", type=positive_float, metavar="S", default=None,
                   help="resolution scales (default: the config's)")
    p.add_argument("--caps", nargs="+", type=positive_int, metavar="N", default=None,
                   help="Gaussian caps (default: the config's max_gaussians)")
    p.add_argument("--variant", action="append", default=None, metavar="NAME[:KEY=VALUE,...]",
                   help="a config variant to compare (repeatable): NAME, then the --set "
                   "overrides it adds, e.g. --variant off --variant "
                   "skip:phase1.static.enabled=true; every budget trains each variant in "
                   "turn, so both see the same machine load. budget=F among them trains that "
                   "variant F times the iterations (schedules scaled alike): equal-time "
                   "comparisons")  # fmt: skip
    p.add_argument("--out", metavar="FILE.json", default=None,
                   help="results JSON (default bench-fit-NAME.json, bench-fit-scenes.json "
                   "for several; the plots go beside it)")
    p.add_argument("--keep-runs", metavar="DIR", default=None,
                   help="keep each budget's run folder under DIR")
    p.add_argument("--runs", nargs="+", metavar="RUN", default=None,
                   help="train nothing: tabulate these finished fit runs (one per scene, "
                   "say) and copy each one's worst test view beside --out")


def pareto_front(points: list[tuple[float, float]]) -> list[bool]:
    """For (seconds, psnr) points, whether each is on the front: no other point is at least as
    fast and strictly better, or strictly faster and at least as good."""
    out = []
    for i, (ti, pi) in enumerate(points):
        dominated = any(
            (tj <= ti and pj > pi) or (tj < ti and pj >= pi)
            for j, (tj, pj) in enumerate(points)
            if j != i
        )
        out.append(not dominated)
    return out


def parse_variant(text: str) -> tuple[str, list[str]]:
    """``NAME[:KEY=VALUE,KEY=VALUE...]`` -> (NAME, the overrides); ConfigError when malformed.
    The pseudo-key ``budget=F`` (see `split_budget`) stays among the overrides."""
    name, _, rest = text.partition(":")
    overrides = [o.strip() for o in rest.split(",") if o.strip()]
    if not name or any("=" not in o for o in overrides):
        raise ConfigError(f"--variant {text!r}: expected NAME or NAME:KEY=VALUE[,KEY=VALUE...]")
    return name, overrides


def split_budget(name: str, overrides: list[str]) -> tuple[float, list[str]]:
    """A variant's ``budget=F`` pseudo-key and the config overrides without it: F multiplies
    every iteration budget of that variant (1.0 when absent), so a variant whose steps are
    cheaper can be given the iterations that fill the same time."""
    factor, rest = 1.0, []
    for o in overrides:
        key, _, value = o.partition("=")
        if key.strip() != "budget":
            rest.append(o)
            continue
        try:
            factor = float(value)
        except ValueError:
            factor = -1.0
        if not (factor > 0 and factor < 1e3):
            raise ConfigError(f"--variant {name}: budget={value!r} must be a positive factor")
    return factor, rest


def run_grid(
    data: Path,
    base: RunConfig | dict[str, RunConfig],
    iterations: list[int],
    scales: list[float],
    caps: list[int],
    threads: int | None,
    work_dir: Path,
    budget_factors: dict[str, float] | None = None,
) -> list[dict[str, Any]]:
    """Train every budget in the grid; one result record per budget. `base` may map variant
    names to configs: each budget then trains every variant in turn (interleaved, so a
    change of machine load hits both alike). `budget_factors` multiplies a variant's
    iterations (its schedules scaled alike), to compare variants at equal time."""
    from sync4d import raster
    from sync4d.config import with_budget
    from sync4d.pipeline import FitData, run_fit

    variants = base if isinstance(base, dict) else {"": base}
    factors = budget_factors or {}
    rows: list[dict[str, Any]] = []
    grid = list(product(scales, caps, iterations, variants))
    for k, (scale, cap, budget, variant) in enumerate(grid):
        iters = max(1, round(budget * factors.get(variant, 1.0)))
        cfg = with_budget(dataclasses.replace(variants[variant], resolution_scale=scale), iters)
        densify = dataclasses.replace(cfg.phase1.densify, max_gaussians=cap)
        cfg = dataclasses.replace(
            cfg, phase1=dataclasses.replace(cfg.phase1, densify=densify), eval_every=0,
            checkpoint_every=0, phases="1",
        )  # fmt: skip
        label = f", variant {variant}" if variant else ""
        print(
            f"bench fit: [{k + 1}/{len(grid)}] {iters} iterations, scale {scale}, cap {cap}"
            f"{label}",
            file=sys.stderr,
        )
        fit_data = FitData.load(data, cfg)  # at cfg.resolution_scale = scale
        scene = fit_data.scene
        run_dir = work_dir / f"s{scale}_c{cap}_i{iters}{'_' + variant if variant else ''}"
        summary = run_fit(fit_data, cfg, run_dir, threads=threads,
                          log_every=max(50, iters // 10))  # fmt: skip
        worst = worst_view(run_dir)
        rows.append(
            {
                "iterations": iters,
                **({"budget": budget} if iters != budget else {}),
                "resolution_scale": scale,
                "max_gaussians": cap,
                "backend": raster.resolve_backend(),
                "width": scene.train[0].camera.width,
                "height": scene.train[0].camera.height,
                "train_seconds": summary["train_seconds"],
                "wall_seconds": summary["wall_seconds"],
                "gaussians": summary["gaussians"],
                "peak_rss_mib": summary.get("peak_rss_mib"),
                "psnr": summary["psnr"],
                "ssim": summary["ssim"],
                "ssim_box3": summary["ssim_box3"],
                "lpips": summary["lpips"],
                "metrics": summary["metrics"],
                "worst_view": worst,
                "backgrounds": background_scores(run_dir, dataclasses.asdict(cfg.phase1)),
                **({"variant": variant} if variant else {}),
                "skipped": summary.get("skipped"),
            }
        )
    front = pareto_front([(r["train_seconds"], r["psnr"]) for r in rows])
    for r, f in zip(rows, front, strict=True):
        r["pareto"] = f
    return rows


def background_scores(run_dir: Path, phase1: dict[str, Any]) -> dict[str, Any]:
    """A row's background fields from `run_dir`'s evaluations: ``train_background`` (what
    training composited behind the Gaussians: "white", "black", "random", ...) and
    ``on``: background name -> PSNR, SSIM, LPIPS and worst view (name, PSNR) of
    ``eval.json`` (the run's own background, `phase1`'s) and of ``eval-white.json`` /
    ``eval-black.json`` where they exist."""
    from sync4d.runs.names import BACKGROUNDS, background_tag, eval_file

    own = background_tag(phase1.get("background", (1.0, 1.0, 1.0)))
    mode = phase1.get("train_background", "fixed")
    on: dict[str, Any] = {}
    for name in dict.fromkeys([own, *BACKGROUNDS]):
        try:
            rec = json.loads((run_dir / eval_file(None if name == own else name)).read_text())
            mean, frames = rec["mean"], rec["frames"]
        except (OSError, ValueError, KeyError, TypeError):
            continue
        worst = min(frames, key=lambda f: f["psnr"]) if frames else None
        on[name] = {k: mean.get(k) for k in ("psnr", "ssim", "lpips")} | {
            "worst": None if worst is None else {"name": worst["name"], "time": worst["time"],
                                                 "psnr": worst["psnr"]}}  # fmt: skip
    return {"train_background": own if mode == "fixed" else mode, "on": on}


def worst_view(run_dir: Path) -> dict[str, Any] | None:
    """The test frame with the lowest PSNR in `run_dir/eval.json` (name, time, PSNR, and the
    path of its render beside the ground truth), or None when the run has no evaluation."""
    try:
        frames = json.loads((run_dir / EVAL_FILE).read_text())["frames"]
    except (OSError, ValueError, KeyError):
        return None
    if not frames:
        return None
    f = min(frames, key=lambda f: f["psnr"])
    render = run_dir / RENDERS_DIR / "test" / f["name"]
    return {
        "name": f["name"], "time": f["time"], "psnr": f["psnr"],
        "render": str(render) if render.is_file() else None,
    }  # fmt: skip


def copy_worst_view(rows: list[dict[str, Any]], path: Path) -> Path | None:
    """Copy the worst test view of the largest budget (most iterations, then resolution) to
    `path`; None when that run wrote no render."""
    if not rows:
        return None
    largest = max(rows, key=lambda r: (r["iterations"], r["resolution_scale"]))
    render = _render_path(largest["worst_view"])
    if render is None:
        return None
    shutil.copyfile(render, path)
    return path


def _render_path(worst: dict[str, Any] | None) -> Path | None:
    """The side-by-side render of a `worst_view` record, None when it has none on disk."""
    if not worst or not worst["render"] or not Path(worst["render"]).is_file():
        return None
    return Path(worst["render"])


def _final_summary(run_dir: Path) -> dict[str, Any]:
    """The last final-evaluation record of `run_dir`'s metrics log."""
    from sync4d.runs import METRICS_FILE, RunError

    path = run_dir / METRICS_FILE
    try:
        lines = path.read_text(encoding="utf-8").splitlines()
    except FileNotFoundError:
        raise RunError(f"{run_dir}: not a fit run ({METRICS_FILE} is missing)") from None
    for line in reversed(lines):
        try:
            rec = json.loads(line)
        except ValueError:
            continue  # a line cut short by a kill; earlier lines still count
        if isinstance(rec, dict) and isinstance(rec.get("final"), dict):
            return rec["final"]
    raise RunError(
        f"{path}: the run has no final evaluation; finish it with "
        f"`python -m sync4d fit --resume --out {run_dir}`"
    )


def rows_from_runs(run_dirs: list[Path]) -> list[dict[str, Any]]:
    """One result record per finished `fit` run (scene, budget, time, metrics, worst view),
    read from its record, metrics log and evaluation; `pareto` is within each scene."""
    from sync4d.pipeline.record import read_record
    from sync4d.runs import RunError

    rows: list[dict[str, Any]] = []
    for run_dir in run_dirs:
        run_dir = Path(run_dir)
        if not run_dir.is_dir():
            raise RunError(f"{run_dir}: no such run folder")
        record = read_record(run_dir)
        final = _final_summary(run_dir)
        cfg = record["config"]
        worst = worst_view(run_dir)
        size = _render_size(worst)
        # A final record without "ssim_box3" predates the standard SSIM: its "ssim" is the box.
        standard = "ssim_box3" in final
        rows.append(
            {
                "scene": record.get("scene", run_dir.name),
                "run": str(run_dir),
                "split": record.get("test_split", "test"),
                "iterations": final.get("iterations", cfg["phase1"]["iterations"]),
                "resolution_scale": record.get("resolution_scale", cfg["resolution_scale"]),
                "max_gaussians": cfg["phase1"]["densify"]["max_gaussians"],
                "threads": record.get("threads"),
                "settings": _settings(record),
                "width": size[0],
                "height": size[1],
                "train_seconds": final["train_seconds"],
                "wall_seconds": final.get("wall_seconds"),
                "gaussians": final["gaussians"],
                "peak_rss_mib": final.get("peak_rss_mib"),
                "psnr": final["psnr"],
                "ssim": final["ssim"] if standard else None,
                "ssim_box3": final["ssim_box3"] if standard else final["ssim"],
                "lpips": final.get("lpips"),
                "metrics": final.get("metrics"),
                "worst_view": worst,
                "backgrounds": background_scores(run_dir, cfg["phase1"]),
            }
        )
    for scene in {r["scene"] for r in rows}:
        same = [r for r in rows if r["scene"] == scene]
        for r, f in zip(same, pareto_front([(r["train_seconds"], r["psnr"]) for r in same]),
                        strict=True):  # fmt: skip
            r["pareto"] = f
    return rows


def _settings(record: dict[str, Any]) -> list[str]:
    """The config name and `--set` overrides the run was started with."""
    calls = record.get("command", {}).get("invocations") or [{}]
    first = calls[0] if isinstance(calls[0], dict) else {}
    named = [f"config={first['config']}"] if first.get("config") else []
    return named + [str(s) for s in first.get("set") or []]


def _render_size(worst: dict[str, Any] | None) -> tuple[int | None, int | None]:
    """(width, height) of one view from a side-by-side render (render | ground truth)."""
    render = _render_path(worst)
    if render is None:
        return None, None
    from PIL import Image

    with Image.open(render) as im:
        return im.size[0] // 2, im.size[1]


def copy_worst_views(rows: list[dict[str, Any]], out: Path) -> list[Path]:
    """Copy each row's worst test view to ``<out stem>-<scene>-worst.png`` (a row index is
    added when a scene has several rows); the paths written."""
    written = []
    for i, r in enumerate(rows):
        render = _render_path(r["worst_view"])
        if render is None:
            continue
        several = sum(q["scene"] == r["scene"] for q in rows) > 1
        tag = f"{r['scene']}-{i}" if several else r["scene"]
        path = out.with_name(f"{out.stem}-{tag}-worst.png")
        shutil.copyfile(render, path)
        r["worst_view_png"] = str(path)
        written.append(path)
    return written


def plot_pareto(rows: list[dict[str, Any]], path: Path, title: str) -> Path:
    """Scatter of test PSNR against training time, the Pareto front as a line."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(7, 4.5), dpi=120)
    groups: dict[tuple[float, int], list[dict[str, Any]]] = {}
    for r in rows:
        groups.setdefault((r["resolution_scale"], r["max_gaussians"]), []).append(r)
    for (scale, cap), rs in sorted(groups.items()):
        rs = sorted(rs, key=lambda r: r["train_seconds"])
        ax.plot(
            [r["train_seconds"] / 60 for r in rs], [r["psnr"] for r in rs], "o-", alpha=0.6,
            label=f"{rs[0]['width']}x{rs[0]['height']} (scale {scale}), cap {cap:,}",
        )  # fmt: skip
        for r in rs:
            ax.annotate(
                f"{r['iterations']}", (r["train_seconds"] / 60, r["psnr"]), fontsize=7,
                xytext=(3, -9), textcoords="offset points",
            )  # fmt: skip
    front = sorted((r for r in rows if r["pareto"]), key=lambda r: r["train_seconds"])
    ax.plot(
        [r["train_seconds"] / 60 for r in front], [r["psnr"] for r in front], "k--", lw=1.2,
        label="Pareto front",
    )  # fmt: skip
    ax.set_xlabel("training time on this machine (minutes)")
    ax.set_ylabel("test PSNR (dB)")
    ax.set_title(title)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)
    return path


def _worst_text(worst: dict[str, Any] | None) -> str:
    return "-" if not worst else f"{worst['name']} {worst['psnr']:.2f}"


def _ssim_text(row: dict[str, Any]) -> str:
    """The standard SSIM of a row, else its 3x3 box SSIM marked "box", else "-"."""
    if row["ssim"] is not None:
        return f"{row['ssim']:.4f}"
    box = row.get("ssim_box3")
    return "-" if box is None else f"{box:.4f} box"


def _background_cells(row: dict[str, Any]) -> list[str]:
    """The training background, and PSNR and worst view on white and on black ("-" where
    the run has no such evaluation)."""
    bg = row.get("backgrounds") or {}
    on = bg.get("on") or {}

    def psnr(name: str) -> str:
        return f"{on[name]['psnr']:.2f}" if name in on and on[name]["psnr"] is not None else "-"

    black = on.get("black", {}).get("worst")
    return [bg.get("train_background", "-"), psnr("white"), psnr("black"), _worst_text(black)]


#: The columns `_background_cells` fills.
BACKGROUND_HEADER = ["train bg", "PSNR white", "PSNR black", "worst black"]


def _ssim_note(rows: list[dict[str, Any]]) -> str:
    """A line under a table that shows a box SSIM, saying what it is; "" when none does."""
    if all(r["ssim"] is not None or r.get("ssim_box3") is None for r in rows):
        return ""
    return ("\nSSIM 'box': the training loss's 3x3 box SSIM of a run evaluated before the "
            "standard SSIM (or with images under 11 pixels); not comparable with the others; "
            "see docs/metrics.md")  # fmt: skip


def format_rows(rows: list[dict[str, Any]]) -> str:
    """The results as an aligned table (a scene column when there are several, each scene's
    rows together, fastest first)."""
    scenes = list(dict.fromkeys(r.get("scene", "") for r in rows))
    order = sorted(rows, key=lambda r: (scenes.index(r.get("scene", "")), r["train_seconds"]))
    body = [
        [
            str(r["iterations"]), f"{r['width']}x{r['height']}", f"{r['max_gaussians']:,}",
            f"{r['train_seconds']:.0f}", f"{r['psnr']:.2f}", _ssim_text(r),
            "-" if r["lpips"] is None else f"{r['lpips']:.4f}", f"{r['gaussians']:,}",
            "*" if r["pareto"] else "",
            _worst_text(r["worst_view"]),
        ]
        for r in order
    ]  # fmt: skip
    header = ["iters", "res", "cap", "train s", "PSNR", "SSIM", "LPIPS", "#G", "front", "worst"]
    left = [1]
    if any(r.get("backgrounds") for r in rows):
        for line, r in zip(body, order, strict=True):
            line.extend(_background_cells(r))
        header += BACKGROUND_HEADER
    if any("variant" in r for r in rows):
        header.insert(0, "variant")
        for line, r in zip(body, order, strict=True):
            line.insert(0, r.get("variant", ""))
            sk = r.get("skipped") or {}
            line.append(f"{sk['share']:.0%}" if sk.get("share") is not None else "-")
        header.append("D_theta skipped")
        left = [0, 2]
    if len(scenes) > 1:
        header.insert(0, "scene")
        for line, r in zip(body, order, strict=True):
            line.insert(0, r["scene"])
        left = [0] + [i + 1 for i in left]
    return align_table(header, body, left=tuple(left)) + _ssim_note(rows)


def format_run_rows(rows: list[dict[str, Any]]) -> str:
    """`--runs` results as an aligned table, a row per run in the order given."""
    body = [
        [
            r["scene"], r["split"], str(r["iterations"]),
            "-" if r["width"] is None else f"{r['width']}x{r['height']}",
            "-" if r["threads"] is None else str(r["threads"]),
            f"{r['train_seconds'] / 60:.1f}", f"{r['psnr']:.2f}", _ssim_text(r),
            "-" if r["lpips"] is None else f"{r['lpips']:.4f}", f"{r['gaussians']:,}",
            "-" if r.get("peak_rss_mib") is None else f"{r['peak_rss_mib']:,.0f}",
            _worst_text(r["worst_view"]), *_background_cells(r), " ".join(r["settings"]) or "-",
        ]
        for r in rows
    ]  # fmt: skip
    header = ["scene", "split", "iters", "res", "threads", "train min", "PSNR", "SSIM", "LPIPS",
              "#G", "peak MiB", "worst", *BACKGROUND_HEADER, "settings"]  # fmt: skip
    return align_table(header, body, left=(0, 1, 11, 12, 16, 17)) + _ssim_note(rows)


def _tabulate_runs(args: argparse.Namespace) -> int:
    """`bench fit --runs`: the table, JSON and worst views of finished runs; trains nothing."""
    from sync4d.files import check_writable, write_text_atomic

    keys = ("iters", "scales", "caps", "keep_runs", "set", "config")
    given = [f"--{k.replace('_', '-')}" for k in keys if getattr(args, k, None)]
    if args.data or given:
        what = ", ".join(list(args.data) + given)
        msg = (f"bench fit: --runs tabulates finished runs and trains nothing; {what} would not "
               "be used: drop it, or train with `bench fit DATA` instead")  # fmt: skip
        print(msg, file=sys.stderr)
        return 2
    out = Path(args.out or "bench-fit-runs.json")
    try:
        check_writable(out.parent)
        rows = rows_from_runs([Path(r) for r in args.runs])
        written = copy_worst_views(rows, out)
    except (Sync4dError, OSError) as e:
        print(f"bench fit: {e}", file=sys.stderr)
        return 2
    record = {
        "benchmark": "fit",
        "runs": [r["run"] for r in rows],
        "date": _dt.datetime.now(_dt.UTC).isoformat(timespec="seconds"),
        "command": [sys.executable, *sys.argv],
        "machine": {"platform": platform.platform(), "processor": platform.processor()},
        "results": rows,
    }
    write_text_atomic(out, json.dumps(record, indent=2) + "\n")
    print(format_run_rows(rows))
    print(f"bench fit: wrote {', '.join(str(w) for w in [out, *written])}")
    return 0


def _variant_configs(args: argparse.Namespace, default_cfg: str | None
                     ) -> tuple[RunConfig, RunConfig | dict[str, RunConfig], dict[str, float]]:
    """The base config of a dataset (its default config unless --config), the configs of the
    variants (or the base alone) and their budget factors."""
    from sync4d.config import load_config

    base = load_config(args.config or default_cfg, list(args.set or []))
    if not args.variant:
        return base, base, {}
    configs: dict[str, RunConfig] = {}
    factors: dict[str, float] = {}
    for text in args.variant:
        name, extra = parse_variant(text)
        if name in configs:
            raise ConfigError(f"--variant {name} is given twice")
        factors[name], extra = split_budget(name, extra)
        configs[name] = load_config(args.config or default_cfg,
                                    list(args.set or []) + extra)  # fmt: skip
    return base, configs, factors


def main(args: argparse.Namespace) -> int:
    from sync4d.files import RunBusy, check_writable, write_text_atomic
    from sync4d.pipeline import FitInterrupted, resolve_data

    if args.runs:
        return _tabulate_runs(args)
    datas = list(args.data) or [None]
    try:
        # the pipeline's notes and progress bars; its tables are bench fit's rows instead
        with TerminalRenderer(details=False).installed():
            resolved = [resolve_data(d) for d in datas]  # every dataset found before training
            base = None
            names = [d.name for d, _ in resolved]
            if len(set(names)) != len(names):
                raise ConfigError(f"two datasets share a name ({', '.join(names)}): give each "
                                  "scene once")  # fmt: skip
            several = len(resolved) > 1
            out = Path(args.out or ("bench-fit-scenes.json" if several
                                    else f"bench-fit-{names[0]}.json"))  # fmt: skip
            check_writable(out.parent)  # before any budget trains, not after all of them
            if args.keep_runs:
                check_writable(args.keep_runs)
            rows: list[dict[str, Any]] = []
            worst: dict[str, Path | None] = {}
            for data, default_cfg in resolved:
                cfg, configs, factors = _variant_configs(args, default_cfg)
                base = base or cfg
                scales = args.scales or [cfg.resolution_scale]
                caps = args.caps or [cfg.phase1.densify.max_gaussians]
                n = cfg.phase1.iterations
                iterations = args.iters or [max(100, n // 8), n // 4, n // 2, n]
                with tempfile.TemporaryDirectory(prefix="sync4d-bench-fit-") as tmp:
                    work = Path(args.keep_runs) if args.keep_runs else Path(tmp)
                    if several:
                        work = work / data.name
                    scene_rows = run_grid(data, configs, iterations, scales, caps, args.threads,
                                          work, factors)  # fmt: skip
                    for r in scene_rows:
                        r["scene"] = data.name
                    tag = f"-{data.name}" if several else ""
                    worst[data.name] = copy_worst_view(
                        scene_rows, out.with_name(f"{out.stem}{tag}-worst.png"))
                rows += scene_rows
    except RunBusy as e:  # another bench's --keep-runs folder
        print(f"bench fit: {e}; or give each bench its own --keep-runs", file=sys.stderr)
        return 2
    except Sync4dError as e:  # exit 2; 3: the watchdog's stop
        print(f"bench fit: {e}", file=sys.stderr)
        return e.exit_code
    except FitInterrupted:
        print("bench fit: interrupted; no results written", file=sys.stderr)
        return 130
    assert base is not None
    record = {
        "benchmark": "fit",
        "data": str(resolved[0][0]) if not several else [str(d) for d, _ in resolved],
        "date": _dt.datetime.now(_dt.UTC).isoformat(timespec="seconds"),
        "command": [sys.executable, *sys.argv],
        "machine": {"platform": platform.platform(), "processor": platform.processor()},
        "threads": args.threads,
        "config": dataclasses.asdict(base),
        "variants": dict(parse_variant(v) for v in args.variant or []),
        "results": rows,
    }
    written: list[Path] = []
    for name in names:
        scene_rows = [r for r in rows if r["scene"] == name]
        tag = f"-{name}" if several else ""
        written.append(plot_pareto(scene_rows, out.with_name(f"{out.stem}{tag}.png"),
                                   f"sync4d fit: {name}"))  # fmt: skip
        if worst[name] is not None:
            record.setdefault("worst_view_pngs", {})[name] = str(worst[name])
            written.append(worst[name])
    if not several and worst[names[0]] is not None:
        record["worst_view_png"] = str(worst[names[0]])
    for r in rows:  # the runs' folders are gone unless --keep-runs
        if not args.keep_runs and r["worst_view"]:
            r["worst_view"]["render"] = None
    written.insert(0, out)
    write_text_atomic(out, json.dumps(record, indent=2) + "\n")
    print(format_rows(rows))
    print(f"bench fit: wrote {', '.join(str(w) for w in written)}")
    return 0
