"""``sync4d sweep MANIFEST.toml --out SWEEP``: many fits on Ray (docs/sweep.md).

The manifest lists jobs (``[[job]]``: dataset, config, overrides, seeds, phases, iterations,
threads, whether to evaluate queries) and optionally a ``[grid]`` whose lists multiply into
jobs; ``[defaults]`` fills what a job leaves out. Each (job, seed) is one Ray task declaring its
CPU count; it runs ``python -m sync4d fit`` (and ``eval --queries`` when asked) in a process of
its own with torch, rayon and OpenMP pinned to that count, writing a normal run folder
``SWEEP/runs/NAME`` and its log ``SWEEP/logs/NAME.log``. Ray sets only OpenMP's thread count for
its workers; the task sets the others.

Local by default (Ray starts in this process and stops with it); ``--address auto`` or
``HOST:PORT`` joins a running cluster, whose workers must see the datasets and SWEEP at the same
paths (a shared file system; docs/sweep.md). Resumable: a run whose folder holds its final
evaluation is not run again, an interrupted one continues (``fit --resume``). A failed job is
reported with its error and the tail of its log while the others go on. Results: one table
(CSV, JSON, printed) and a plot of test PSNR against training time per scene.
"""

from __future__ import annotations

import argparse
import csv
import itertools
import json
import os
import platform
import signal
import subprocess
import sys
import time
import tomllib
from dataclasses import asdict, dataclass
from pathlib import Path

from sync4d.errors import Sync4dError
from sync4d.events import read_events
from sync4d.files import write_text_atomic
from sync4d.options import positive_int
from sync4d.report import align_table
from sync4d.runs.names import CHECKPOINT_NAME, EVAL_FILE, EVENTS_FILE, RUN_FILE

__all__ = ["add_arguments", "expand", "Job", "main", "ManifestError", "read_manifest", "run_sweep"]


def add_arguments(p: argparse.ArgumentParser) -> None:
    """The description and arguments of ``sync4d sweep`` (`sync4d.cli`)."""
    p.description = (
        "Run every job of a manifest (dataset, config, overrides, seeds, phases; or a grid of "
        "them) as a Ray task with its CPU count declared and torch, rayon and OpenMP threads "
        "pinned to it, each into a normal run folder under SWEEP/runs; finished runs are not "
        "run again, interrupted ones resume, failed ones are reported with their log's tail. "
        "Writes a table (CSV, JSON, printed) and a plot of test PSNR against training time. "
        "Needs Ray: pip install 'sync4d[sweep]'."
    )
    p.add_argument("manifest", metavar="MANIFEST.toml",
                   help="the jobs: [[job]] entries and/or a [grid] (docs/sweep.md)")
    p.add_argument("--out", required=True, metavar="SWEEP",
                   help="folder of the sweep: runs/, logs/, results.csv/json, psnr-time.png")
    p.add_argument("--address", default=None, metavar="auto|HOST:PORT",
                   help="join a running Ray cluster (default: a local Ray in this process)")
    p.add_argument("--cpus", type=positive_int, default=None, metavar="N",
                   help="CPUs the local Ray may use (default: all)")

#: Keys a job (or [defaults], or [grid]) may set.
JOB_KEYS = ("name", "data", "config", "set", "seeds", "phases", "iters", "threads",
            "queries", "resolution_scale")  # fmt: skip
#: Lines of a failed job's log shown with its error.
LOG_TAIL = 12
#: Seconds an interrupted job's fit has to save its checkpoint before it is killed.
STOP_GRACE = 120.0


class ManifestError(Sync4dError, ValueError):
    """A manifest that cannot be used; the message names the file and the key."""


@dataclass(frozen=True)
class Job:
    """One fit of the sweep: its run `name`, dataset `data`, `config`, `overrides` (--set),
    `seed`, `phases`, `iters` (None: the config's), CPU `threads`, `queries` annotation file
    (None: none), `resolution_scale`."""

    name: str
    data: str
    config: str | None = None
    overrides: tuple[str, ...] = ()
    seed: int = 42
    phases: str = "1,2"
    iters: int | None = None
    threads: int = 1
    queries: str | None = None
    resolution_scale: float | None = None

    def fit_args(self, run: Path) -> list[str]:
        """The `fit` command line of this job into `run`."""
        args = ["fit", self.data, "--out", str(run), "--threads", str(self.threads),
                "--phases", self.phases, "--set", f"phase1.seed={self.seed}"]  # fmt: skip
        if self.config:
            args += ["--config", self.config]
        if self.iters:
            args += ["--iters", str(self.iters)]
        if self.resolution_scale:
            args += ["--resolution-scale", str(self.resolution_scale)]
        for kv in self.overrides:
            args += ["--set", kv]
        return args


def _check(path: Path, where: str, entry: dict) -> None:
    unknown = sorted(set(entry) - set(JOB_KEYS))
    if unknown:
        raise ManifestError(f"{path}: {where} has unknown keys {unknown} (known: "
                            f"{', '.join(JOB_KEYS)})")  # fmt: skip


def read_manifest(path: str | Path) -> dict:
    """The manifest at `path` as a dict, its keys checked; ManifestError naming the file."""
    path = Path(path)
    try:
        doc = tomllib.loads(path.read_text(encoding="utf-8"))
    except FileNotFoundError:
        raise ManifestError(f"{path}: no such manifest") from None
    except OSError as e:  # a folder, a name too long, no permission
        raise ManifestError(f"{str(path)[:200]}: cannot read the manifest ({e.strerror or e}); "
                            "give the path of a MANIFEST.toml file") from None
    except (tomllib.TOMLDecodeError, UnicodeDecodeError) as e:
        raise ManifestError(f"{path}: not valid TOML ({e})") from None
    extra = sorted(set(doc) - {"defaults", "job", "grid"})
    if extra:
        raise ManifestError(f"{path}: unknown sections {extra} (expected [defaults], [[job]], "
                            "[grid])")  # fmt: skip
    _check(path, "[defaults]", doc.get("defaults", {}))
    _check(path, "[grid]", doc.get("grid", {}))
    for i, job in enumerate(doc.get("job", [])):
        _check(path, f"[[job]] {i + 1}", job)
    if not doc.get("job") and not doc.get("grid"):
        raise ManifestError(f"{path}: no jobs: add [[job]] entries or a [grid]")
    return doc


def _slug(text: str) -> str:
    return "".join(c if c.isalnum() or c in "-_." else "-" for c in text).strip("-")


def expand(doc: dict, path: Path) -> list[Job]:
    """Every (job, seed) of a manifest `doc` (read from `path`: relative dataset paths are from
    its folder), in the manifest's order, grid jobs after the listed ones."""
    base = doc.get("defaults", {})
    entries = [dict(base, **j) for j in doc.get("job", [])]
    grid = doc.get("grid", {})
    if grid:
        keys = list(grid)
        values = [v if isinstance(v, list) else [v] for v in grid.values()]
        entries += [dict(base, **dict(zip(keys, combo, strict=True)))
                    for combo in itertools.product(*values)]  # fmt: skip
    jobs, names = [], set()
    for i, e in enumerate(entries):
        if "data" not in e:
            raise ManifestError(f"{path}: job {i + 1} names no dataset (data = \"...\")")
        data = Path(str(e["data"]))
        data = data if data.is_absolute() else (path.parent / data)
        seeds = e.get("seeds", [42])
        seeds = seeds if isinstance(seeds, list) else [seeds]
        for seed in seeds:
            iters = None if e.get("iters") is None else f"{e['iters']}it"
            parts = (data.name, e.get("config"), *map(str, e.get("set", [])), iters)
            stem = e.get("name") or "-".join(x for x in parts if x)
            name = _slug(f"{stem}-s{seed}")
            if name in names:
                raise ManifestError(f"{path}: two jobs are both named {name!r}; give one a name")
            names.add(name)
            jobs.append(Job(
                name=name, data=str(data), config=e.get("config"),
                overrides=tuple(str(x) for x in e.get("set", [])), seed=int(seed),
                phases=str(e.get("phases", "1,2")), iters=e.get("iters"),
                threads=int(e.get("threads", 1)),
                queries=None if not e.get("queries") else str(
                    Path(e["queries"]) if Path(e["queries"]).is_absolute()
                    else path.parent / e["queries"]),
                resolution_scale=e.get("resolution_scale"),
            ))  # fmt: skip
    return jobs


def _finished(run: Path) -> bool:
    """The run folder holds its final evaluation (written at the end of `fit`)."""
    return (run / EVAL_FILE).is_file() and (run / CHECKPOINT_NAME).is_file()


def _call(args: list[str], log, threads: int) -> int:
    env = {**os.environ, "OMP_NUM_THREADS": str(threads), "MKL_NUM_THREADS": str(threads),
           "RAYON_NUM_THREADS": str(threads), "PYTHONUNBUFFERED": "1"}  # fmt: skip
    log.write(f"$ sync4d {' '.join(args)}\n")
    log.flush()
    with subprocess.Popen([sys.executable, "-m", "sync4d", *args], stdout=log,
                          stderr=subprocess.STDOUT, env=env) as proc:  # fmt: skip
        try:
            return proc.wait()
        except KeyboardInterrupt:  # Ctrl-C, or a cancelled task: fit saves, then stops
            proc.send_signal(signal.SIGINT)  # fit ignores a second one while it stops
            try:
                proc.wait(timeout=STOP_GRACE)
            except subprocess.TimeoutExpired:
                proc.kill()
            raise


def run_job(job: Job, out: Path) -> dict:
    """Run one job (fit, then eval --queries when asked) into ``out/runs/NAME``; its result:
    status ("done", "skipped": finished before, "failed"), error and log tail, seconds."""
    run, log_path = out / "runs" / job.name, out / "logs" / f"{job.name}.log"
    log_path.parent.mkdir(parents=True, exist_ok=True)
    result = {"name": job.name, "threads": job.threads, "machine": platform.node()}
    if _finished(run):
        return {**result, "status": "skipped"}
    t0 = time.time()
    with open(log_path, "a", encoding="utf-8") as log:
        args = job.fit_args(run)
        if (run / CHECKPOINT_NAME).is_file():  # interrupted: the run folder's own resume
            args = ["fit", "--out", str(run), "--resume", "--threads", str(job.threads)]
        code = _call(args, log, job.threads)
        if code == 0 and job.queries:
            code = _call(["eval", str(run), "--queries", job.queries, "--threads",
                          str(job.threads)], log, job.threads)  # fmt: skip
    result["seconds"] = time.time() - t0
    if code != 0:
        lines = log_path.read_text(encoding="utf-8", errors="replace").splitlines()
        err = next((ln for ln in reversed(lines) if ln.startswith(("fit:", "eval:", "Error"))),
                   lines[-1] if lines else "")  # fmt: skip
        return {**result, "status": "failed", "exit": code, "error": err,
                "log_tail": lines[-LOG_TAIL:], "log": str(log_path)}  # fmt: skip
    return {**result, "status": "done"}


def _row(job: Job, out: Path, result: dict) -> dict:
    """The table row of a job: its settings and the metrics its run folder holds."""
    run = out / "runs" / job.name
    row = {"name": job.name, "scene": Path(job.data).name, "config": job.config or "default",
           "overrides": " ".join(job.overrides), "seed": job.seed, "threads": job.threads,
           "status": result["status"]}  # fmt: skip
    try:
        ev = json.loads((run / EVAL_FILE).read_text())
        rec = json.loads((run / RUN_FILE).read_text())
        done = [e for e in read_events(run / EVENTS_FILE, ("PhaseDone",)) if e["phase"] == "fit"]
        last = done[-1]["summary"] if done else {}
        cfg = rec.get("config", {})
        row.update(iterations=cfg.get("phase1", {}).get("iterations"),
                   train_seconds=last.get("train_seconds"), psnr=ev["mean"].get("psnr"),
                   ssim=ev["mean"].get("ssim"), lpips=ev["mean"].get("lpips"),
                   gaussians=ev.get("gaussians"), machine=result.get("machine"))  # fmt: skip
    except (OSError, ValueError, KeyError, IndexError):
        pass
    if job.queries:
        summary = run / "phase3" / f"eval-{Path(job.queries).stem}.json"
        try:
            q = json.loads(summary.read_text())
            full = q.get("scorers", {}).get("full") or next(iter(q.get("scorers", {}).values()))
            row.update(query_acc=full.get("acc"), query_viou=full.get("viou"),
                       query_tiou=full.get("tiou"))  # fmt: skip
        except (OSError, ValueError, StopIteration, AttributeError):
            pass
    if result["status"] == "failed":
        row["error"] = result.get("error", "")
    return row


def _write_table(rows: list[dict], out: Path) -> str:
    cols = ["name", "scene", "config", "seed", "threads", "iterations", "train_seconds", "psnr",
            "ssim", "lpips", "gaussians", "query_tiou", "status"]  # fmt: skip
    keys = list(dict.fromkeys(cols + [k for r in rows for k in r]))
    with open(out / "results.csv", "w", newline="", encoding="utf-8") as f:
        w = csv.DictWriter(f, fieldnames=keys)
        w.writeheader()
        w.writerows(rows)
    write_text_atomic(out / "results.json", json.dumps(rows, indent=1) + "\n")

    def fmt(v, spec: str) -> str:
        return "-" if v is None else format(v, spec)

    table = align_table(
        ["run", "scene", "seed", "thr", "iters", "train s", "PSNR", "SSIM", "LPIPS", "#G",
         "tIoU", "status"],
        [[r["name"], r["scene"], str(r["seed"]), str(r["threads"]), str(r.get("iterations") or "-"),
          fmt(r.get("train_seconds"), ".0f"), fmt(r.get("psnr"), ".2f"), fmt(r.get("ssim"), ".4f"),
          fmt(r.get("lpips"), ".4f"), str(r.get("gaussians") or "-"),
          fmt(r.get("query_tiou"), ".3f"), r["status"]] for r in rows],
        left=(0, 1, 11),
    )  # fmt: skip
    _plot(rows, out / "psnr-time.png")
    return table


def _plot(rows: list[dict], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6, 4))
    for scene in sorted({r["scene"] for r in rows}):
        pts = sorted((r["train_seconds"], r["psnr"]) for r in rows if r["scene"] == scene
                     and r.get("psnr") is not None and r.get("train_seconds") is not None)
        if pts:
            ax.plot([p[0] for p in pts], [p[1] for p in pts], "o-", label=scene)
    ax.set_xlabel("training time (s)")
    ax.set_ylabel("test PSNR (dB)")
    ax.grid(alpha=0.3)
    if ax.get_legend_handles_labels()[0]:
        ax.legend()
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def run_sweep(jobs: list[Job], out: Path, address: str | None = None,
              cpus: int | None = None) -> list[dict]:  # fmt: skip
    """Run `jobs` on Ray (local, or the cluster at `address`) into `out`; their results, in
    the jobs' order. Prints progress (done, running, failed, ETA) as tasks finish."""
    import ray

    out.mkdir(parents=True, exist_ok=True)
    # no --address: a Ray of its own ("local"), never a cluster that happens to run here
    ray.init(address=address or "local", num_cpus=None if address else cpus,
             include_dashboard=False, log_to_driver=False, configure_logging=False)  # fmt: skip
    try:
        remote = ray.remote(run_job)
        pending = {remote.options(num_cpus=j.threads).remote(j, out): i
                   for i, j in enumerate(jobs)}  # fmt: skip
        results: list[dict | None] = [None] * len(jobs)
        t0, finished, failed = time.time(), 0, 0
        while pending:
            ready, _ = ray.wait(list(pending), num_returns=1)
            i = pending.pop(ready[0])
            try:
                results[i] = ray.get(ready[0])
            except Exception as e:  # noqa: BLE001 - a task that Ray itself lost
                results[i] = {"name": jobs[i].name, "status": "failed", "error": str(e)}
            finished += 1
            failed += results[i]["status"] == "failed"
            elapsed = time.time() - t0
            eta = elapsed / finished * len(pending)
            print(f"sweep: {finished}/{len(jobs)} done ({failed} failed), {len(pending)} running "
                  f"or queued, ETA {eta:.0f}s: {jobs[i].name} {results[i]['status']}",
                  flush=True)  # fmt: skip
            if results[i]["status"] == "failed":
                r = results[i]
                print(f"sweep: {jobs[i].name} failed: {r.get('error', '')}\n  " +
                      "\n  ".join(r.get("log_tail", [])), flush=True)  # fmt: skip
        return [r for r in results if r is not None]
    finally:
        ray.shutdown()


def main(args: argparse.Namespace) -> int:
    """Run `sweep` with parsed `args`; the exit status (1 when a job failed)."""
    try:
        manifest = Path(args.manifest)
        jobs = expand(read_manifest(manifest), manifest)
    except ManifestError as e:
        print(f"sweep: {e}", file=sys.stderr)
        return 2
    try:
        import ray  # noqa: F401
    except ImportError:
        print("sweep: the sweep runs on Ray: install it with pip install 'sync4d[sweep]' (or "
              "pip install ray)", file=sys.stderr)  # fmt: skip
        return 2
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    write_text_atomic(out / "jobs.json", json.dumps([asdict(j) for j in jobs], indent=1) + "\n")
    try:
        results = run_sweep(jobs, out, args.address, args.cpus)
    except ConnectionError as e:  # --address names no cluster Ray can join
        print(f"sweep: cannot join the Ray cluster at {args.address}: {e}; check --address "
              "(HOST:PORT of a head started with `ray start --head`, or auto)", file=sys.stderr)
        return 2
    rows = [_row(j, out, r) for j, r in zip(jobs, results, strict=True)]
    print(_write_table(rows, out))
    print(f"sweep: results in {out / 'results.csv'}, {out / 'results.json'} and "
          f"{out / 'psnr-time.png'}")
    return 1 if any(r["status"] == "failed" for r in results) else 0

