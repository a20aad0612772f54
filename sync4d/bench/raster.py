"""Rasterizer benchmark: ``python -m sync4d bench raster``.

Times :func:`sync4d.raster.rasterize` — forward under ``torch.no_grad`` and forward+backward
(``loss = features.sum() + alpha.sum()``, gradients w.r.t. means, quats, scales, opacities and
colours) — on seeded random scenes, over a grid of scene sizes x resolutions x thread counts,
side by side with gsplat 1.5.3's pure-torch pipeline run on the CPU
(:func:`sync4d.reference.gsplat.gsplat_render`) on the same scene with the same thread
count. Prints an aligned table and writes everything (machine, versions, allocators,
environment, per-call times, memory, work counters) as JSON.

Method:

* **Scene** — :func:`bench_scene`: ``N`` Gaussians in front of an identity camera with
  ``fx = fy = 0.8 W``, ``cx = W / 2``, ``cy = H / 2``; depth ``z ~ U(2, 6)``; ``x``, ``y``
  uniform over the frustum widened by 10% at that depth; quaternions ``~ N(0, 1)``; scales
  ``exp(N(log 0.012, 0.5))`` per axis; opacities ``~ U(0.05, 0.95)``; RGB ``~ U(0, 1)``;
  float32, ``torch.Generator`` seeded with 0.
* **Timing** — untimed warm-up calls, then the median of ``repeats`` timed calls
  (``time.perf_counter``). sync4d: 2 warm-ups, 5 repeats (3 for N >= 1M). Reference: 1 warm-up,
  2 repeats (1 for N >= 100k). ``--quick`` uses fewer.
* **Threads** — ``threads=T`` on the op (its rayon pool) and ``torch.set_num_threads(T)`` for
  the torch side (sync4d's glue and the whole reference).
* **Memory** — peak resident set size per measurement (warm-up + timed calls of one mode).
  Preferred: ``gc.collect()`` + ``malloc_trim(0)``, read ``VmRSS`` (the baseline), reset the
  kernel's high-water mark (``echo 5 > /proc/self/clear_refs``), run, read ``VmHWM`` (the
  peak). When ``/proc/self/clear_refs`` is not writable, each measurement runs in its own
  child process and the peak is that child's ``ru_maxrss``. The JSON records which.
* **Reference** — for N <= 100k only (larger scenes take minutes and tens of GB). Every
  reference config runs in a child process, so its heap never inflates the sync4d numbers, and
  a watchdog kills the child if its RSS passes ``--reference-max-gb`` (default 18 GiB, capped
  at the memory available minus 1.5 GiB); larger configs at that thread count are then
  skipped. The reference uses gsplat's own conventions (alpha clamp 0.999) and sync4d its
  defaults (0.99): these are timings, parity is tested in ``tests/raster/test_parity_gsplat.py``.
* **Contention** — each measurement records ``other_load_cores``, the CPU cores other
  processes kept busy meanwhile (``/proc/stat`` minus this process and its children); above
  0.15 the progress line and the summary flag the timing as disturbed.

Units: ms are milliseconds; MB are MiB (2**20 bytes); GB are GiB.
"""

from __future__ import annotations

import argparse
import datetime as _dt
import importlib.metadata
import importlib.util
import json
import math
import os
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import torch
from torch import Tensor

import sync4d
from sync4d import _core
from sync4d.bench.measure import (
    MEMORY_METHODS,
    METHOD_CLEAR_REFS,
    METHOD_SUBPROCESS,
    OtherLoad,
    Timing,
    clear_refs_available,
    machine_info,
    measure,
    mem_available_gb,
    proc_status_kb,
)
from sync4d.options import positive_float, positive_int, resolution, thread_count
from sync4d.report import align_table

__all__ = [
    "BenchScene",
    "Timing",
    "add_arguments",
    "bench_scene",
    "main",
    "parse_resolution",
]

SCHEMA = "sync4d.bench.raster/1"
DEFAULT_SIZES: tuple[int, ...] = (10_000, 100_000, 1_000_000)
DEFAULT_RESOLUTIONS: tuple[tuple[int, int], ...] = ((256, 256), (800, 800), (960, 536))
DEFAULT_THREADS: tuple[int, ...] = (1, 2)
QUICK_SIZES: tuple[int, ...] = (10_000,)
QUICK_RESOLUTIONS: tuple[tuple[int, int], ...] = ((256, 256),)
DEFAULT_OUT = "bench-raster.json"
#: The reference is only run up to this many Gaussians.
REFERENCE_MAX_N = 100_000
#: Default RSS limit for a reference child process (GiB).
REFERENCE_MAX_GB = 18.0
#: Memory left to the rest of the machine when capping the reference limit (GiB).
MEMORY_RESERVE_GB = 1.5
#: Wall-clock limit of one child process (s).
CHILD_TIMEOUT_S = 1800.0

#: Warn when other processes used more than this many cores during a measurement.
LOAD_WARN_CORES = 0.15

MODES = ("forward", "forward_backward")
ALLOCATORS = {
    "sync4d": "Rust system allocator (glibc malloc) with per-context buffer reuse "
    "(RasterContext pool)",
    "torch": "torch default CPU allocator (glibc malloc)",
}
ENV_PREFIXES = ("OMP_", "MKL_", "OPENBLAS_", "RAYON_", "KMP_", "GOMP_", "MALLOC_", "PYTORCH_")
ENV_KEYS = ("LD_PRELOAD", "SYNC4D_THREADS", "CUDA_VISIBLE_DEVICES")

_MIB = 1024.0 * 1024.0
_GIB = 1024.0 * _MIB


# --------------------------------------------------------------------------------------------
# Scene
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class BenchScene:
    """A benchmark scene: float32 Gaussians and an identity pinhole camera."""

    means: Tensor  # [N, 3]
    quats: Tensor  # [N, 4] (w, x, y, z), unnormalised
    scales: Tensor  # [N, 3] standard deviations
    opacities: Tensor  # [N]
    colors: Tensor  # [N, 3] RGB
    viewmat: Tensor  # [4, 4] identity
    K: Tensor  # [3, 3]
    width: int
    height: int

    def gaussians(self) -> tuple[Tensor, Tensor, Tensor, Tensor, Tensor]:
        """``(means, quats, scales, opacities, colors)``, the differentiable inputs."""
        return self.means, self.quats, self.scales, self.opacities, self.colors


def bench_scene(n: int, width: int, height: int, seed: int = 0) -> BenchScene:
    """The benchmark's seeded random scene of ``n`` Gaussians in front of the camera (float32).

    Identity view matrix, ``fx = fy = 0.8 * width``, ``cx = width / 2``, ``cy = height / 2``.
    Depths ``z ~ U(2, 6)``; ``x`` and ``y`` uniform over the frustum widened by 10% at that
    depth (``|x| <= 1.1 z W / (2 fx)``, ``|y| <= 1.1 z H / (2 fy)``); quaternions ``~ N(0, 1)``;
    scales ``exp(N(log 0.012, 0.5))`` per axis; opacities ``~ U(0.05, 0.95)``; colours
    ``~ U(0, 1)``. Same arguments, same tensors.
    """
    if n < 1 or width < 1 or height < 1:
        raise ValueError(f"need n, width, height >= 1, got {n}, {width}, {height}")
    gen = torch.Generator().manual_seed(seed)
    f32 = torch.float32
    fx = fy = 0.8 * width
    cx, cy = width / 2.0, height / 2.0
    z = torch.empty(n, dtype=f32).uniform_(2.0, 6.0, generator=gen)
    u = torch.empty(n, dtype=f32).uniform_(-1.0, 1.0, generator=gen)
    v = torch.empty(n, dtype=f32).uniform_(-1.0, 1.0, generator=gen)
    x = u * (1.1 * width / (2.0 * fx)) * z
    y = v * (1.1 * height / (2.0 * fy)) * z
    means = torch.stack([x, y, z], dim=1)
    quats = torch.randn(n, 4, generator=gen, dtype=f32)
    scales = torch.exp(torch.randn(n, 3, generator=gen, dtype=f32) * 0.5 + math.log(0.012))
    opacities = torch.empty(n, dtype=f32).uniform_(0.05, 0.95, generator=gen)
    colors = torch.rand(n, 3, generator=gen, dtype=f32)
    K = torch.tensor([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]], dtype=f32)
    return BenchScene(
        means=means.contiguous(),
        quats=quats,
        scales=scales,
        opacities=opacities,
        colors=colors,
        viewmat=torch.eye(4, dtype=f32),
        K=K,
        width=width,
        height=height,
    )


def parse_resolution(text: str) -> tuple[int, int]:
    """``"800x536"`` -> ``(800, 536)`` (width, height)."""
    parts = text.lower().split("x")
    if len(parts) != 2 or not all(p.strip().isdigit() for p in parts):
        raise ValueError(f"expected WIDTHxHEIGHT such as 800x800, got {text!r}")
    width, height = int(parts[0]), int(parts[1])
    if width < 1 or height < 1:
        raise ValueError(f"width and height must be >= 1, got {text!r}")
    return width, height


def _leaves(scene: BenchScene) -> list[Tensor]:
    return [t.detach().clone().requires_grad_(True) for t in scene.gaussians()]


def _sync4d_calls(
    scene: BenchScene, threads: int, counters: dict[str, int], backend: str = "cpu"
) -> dict[str, Callable[[], None]]:
    """sync4d forward / forward+backward closures on `backend`; the forward stores the work
    counters."""
    from sync4d.raster import rasterize

    cam = (scene.viewmat, scene.K, scene.width, scene.height)
    leaves = _leaves(scene)

    def forward() -> None:
        with torch.no_grad():
            out = rasterize(*scene.gaussians(), *cam, threads=threads, backend=backend)
        counters.clear()
        counters.update({k: int(v) for k, v in out.counters.items()})

    def forward_backward() -> None:
        out = rasterize(*leaves, *cam, threads=threads, backend=backend)
        loss = out.features.sum() + out.alpha.sum()
        torch.autograd.grad(loss, leaves)

    return {"forward": forward, "forward_backward": forward_backward}


def _reference_calls(scene: BenchScene) -> dict[str, Callable[[], None]]:
    """gsplat reference forward / forward+backward closures (gsplat's own defaults)."""
    from sync4d.reference.gsplat import gsplat_render

    cam = (scene.viewmat, scene.K, scene.width, scene.height)
    leaves = _leaves(scene)

    def forward() -> None:
        with torch.no_grad():
            gsplat_render(*scene.gaussians(), *cam)

    def forward_backward() -> None:
        image, alpha, _ = gsplat_render(*leaves, *cam)
        loss = image.sum() + alpha.sum()
        torch.autograd.grad(loss, leaves)

    return {"forward": forward, "forward_backward": forward_backward}


def run_job(
    impl: str,
    n: int,
    width: int,
    height: int,
    seed: int,
    threads: int,
    modes: Sequence[str],
    warmup: int,
    repeats: int,
    memory_method: str,
) -> dict[str, Any]:
    """Build the scene and measure ``modes`` of ``impl`` ("sync4d", "wgpu": sync4d on the wgpu
    backend, or "reference").

    Returns ``{"modes": {mode: Timing as dict}, "counters": {...}}`` (counters: sync4d only).
    Sets ``torch.set_num_threads(threads)`` (and restores it).
    """
    saved_threads = torch.get_num_threads()
    torch.set_num_threads(threads)
    try:
        scene = bench_scene(n, width, height, seed)
        counters: dict[str, int] = {}
        if impl in ("sync4d", "wgpu"):
            calls = _sync4d_calls(scene, threads, counters, "cpu" if impl == "sync4d" else "wgpu")
        elif impl == "reference":
            calls = _reference_calls(scene)
        else:
            raise ValueError(f"unknown impl {impl!r}")
        results = {
            mode: asdict(measure(calls[mode], warmup, repeats, memory_method)) for mode in modes
        }
        if impl == "sync4d" and "forward" not in modes:
            calls["forward"]()  # counters only
        return {"modes": results, "counters": counters}
    finally:
        torch.set_num_threads(saved_threads)


# --------------------------------------------------------------------------------------------
# Child processes (reference isolation, memory fallback) with an RSS watchdog
# --------------------------------------------------------------------------------------------

_CHILD_CODE = (
    "import sys; from sync4d.bench.raster import _child_main; sys.exit(_child_main(sys.argv[1:]))"
)


def _child_main(argv: Sequence[str]) -> int:
    """Child entry point: ``argv = [job_json, result_path]``; writes the job's result JSON."""
    job = json.loads(argv[0])
    result = run_job(**job)
    Path(argv[1]).write_text(json.dumps(result))
    return 0


@dataclass
class ChildOutcome:
    """What came back from a child process."""

    status: str  # "ok", "aborted (...)", "failed (...)"
    result: dict[str, Any] | None
    seconds: float
    watchdog_max_rss_mb: float  # largest VmRSS the watchdog sampled (every 20 ms, after exec)
    stderr_tail: str = ""


def _is_child_cmdline(pid: int) -> bool:
    """Whether ``pid`` already runs the child code (has exec'd)."""
    try:
        with open(f"/proc/{pid}/cmdline", "rb") as fh:
            return b"_child_main" in fh.read()
    except OSError:
        return False


def _child_env() -> dict[str, str]:
    env = dict(os.environ)
    root = str(Path(sync4d.__file__).resolve().parent.parent)
    env["PYTHONPATH"] = os.pathsep.join(p for p in (root, env.get("PYTHONPATH", "")) if p)
    return env


def run_child(
    job: dict[str, Any], limit_gb: float | None, timeout_s: float = CHILD_TIMEOUT_S
) -> ChildOutcome:
    """Run :func:`run_job` in a child process; kill it if its RSS passes ``limit_gb`` GiB."""
    t0 = time.monotonic()
    max_rss_kb = 0
    status = ""
    with tempfile.TemporaryDirectory(prefix="sync4d-bench-") as tmp:
        result_path = Path(tmp) / "result.json"
        err_path = Path(tmp) / "stderr.txt"
        with open(err_path, "wb") as err:
            proc = subprocess.Popen(
                [sys.executable, "-c", _CHILD_CODE, json.dumps(job), str(result_path)],
                stdin=subprocess.DEVNULL,
                stdout=err,
                stderr=subprocess.STDOUT,
                env=_child_env(),
            )
            execed = False  # before exec, the forked child still counts the parent's pages
            try:
                while proc.poll() is None:
                    execed = execed or _is_child_cmdline(proc.pid)
                    rss_kb = proc_status_kb(proc.pid).get("VmRSS", 0) if execed else 0
                    max_rss_kb = max(max_rss_kb, rss_kb)
                    if limit_gb is not None and rss_kb > limit_gb * 1024 * 1024:
                        status = f"aborted (RSS > {limit_gb:.3g} GB limit)"
                        break
                    if time.monotonic() - t0 > timeout_s:
                        status = f"aborted (timeout {timeout_s:.0f} s)"
                        break
                    time.sleep(0.02)
            finally:
                if proc.poll() is None:
                    proc.kill()
                proc.wait()
        seconds = time.monotonic() - t0
        tail = err_path.read_text(errors="replace")[-2000:]
        result = None
        if not status:
            if proc.returncode == 0 and result_path.exists():
                status = "ok"
                result = json.loads(result_path.read_text())
            else:
                last = tail.strip().splitlines()[-1:] or [""]
                status = f"failed (exit {proc.returncode}: {last[0][:120]})"
    return ChildOutcome(status, result, round(seconds, 3), round(max_rss_kb / 1024.0, 1), tail)


def _env_info() -> dict[str, str]:
    return {
        k: v for k, v in sorted(os.environ.items()) if k.startswith(ENV_PREFIXES) or k in ENV_KEYS
    }


# --------------------------------------------------------------------------------------------
# Progress
# --------------------------------------------------------------------------------------------


def _hms(seconds: float) -> str:
    s = int(round(max(seconds, 0.0)))
    return f"{s // 3600}:{s // 60 % 60:02d}:{s % 60:02d}"


class _Progress:
    """Step counter with elapsed time and an ETA from a crude cost model.

    A step's estimated cost is ``calls * (N + 0.45 W H) / threads**0.8`` units (times a prior
    of 12 for the reference); seconds per unit are learnt per kind as steps finish.
    """

    PRIOR = {"sync4d": 1.0, "wgpu": 8.0, "reference": 12.0}

    def __init__(self, steps: list[tuple[str, float]], stream: Any = sys.stdout) -> None:
        self.units = [units * self.PRIOR[kind] for kind, units in steps]
        self.kinds = [kind for kind, _ in steps]
        self.done_time: dict[str, float] = {}
        self.done_units: dict[str, float] = {}
        self.index = 0
        self.t0 = time.monotonic()
        self.stream = stream

    def elapsed(self) -> float:
        return time.monotonic() - self.t0

    def _rate(self, kind: str) -> float | None:
        if self.done_units.get(kind):
            return self.done_time[kind] / self.done_units[kind]
        units = sum(self.done_units.values())
        return sum(self.done_time.values()) / units if units else None

    def eta(self) -> str:
        remaining = 0.0
        for kind, units in zip(self.kinds[self.index :], self.units[self.index :], strict=True):
            rate = self._rate(kind)
            if rate is None:
                return "?"
            remaining += units * rate
        return _hms(remaining)

    def prefix(self) -> str:
        width = len(str(len(self.units)))
        return f"[{self.index + 1:>{width}}/{len(self.units)}] {_hms(self.elapsed())}"

    def say(self, text: str) -> None:
        print(f"{self.prefix()}  {text}", file=self.stream, flush=True)

    def finish(self, text: str, seconds: float) -> None:
        kind = self.kinds[self.index]
        self.done_time[kind] = self.done_time.get(kind, 0.0) + seconds
        self.done_units[kind] = self.done_units.get(kind, 0.0) + self.units[self.index]
        line = f"{self.prefix()}  {text}  ({seconds:.1f} s)"
        self.index += 1
        if self.index < len(self.units):
            line += f"  ETA {self.eta()}"
        print(line, file=self.stream, flush=True)


def _step_units(n: int, width: int, height: int, threads: int, calls: int) -> float:
    return calls * (n + 0.45 * width * height) / threads**0.8


# --------------------------------------------------------------------------------------------
# Table
# --------------------------------------------------------------------------------------------


def _fmt_ms(v: float | None) -> str:
    if v is None:
        return "-"
    if v < 10:
        return f"{v:.2f}"
    if v < 1000:
        return f"{v:.1f}"
    return f"{v:,.0f}"


def _fmt_mb(t: dict[str, Any] | None) -> str:
    if not t or t.get("rss_peak_mb") is None:
        return "-"
    s = f"{t['rss_peak_mb']:,.0f}"
    if t.get("rss_delta_mb") is not None:
        s += f" (+{max(t['rss_delta_mb'], 0.0):,.0f})"
    return s


def _fmt_load(d: dict[str, Any]) -> str:
    """Progress-line warning when other processes used a noticeable share of the CPU."""
    load = d.get("other_load_cores")
    if load is None or load < LOAD_WARN_CORES:
        return ""
    return f"  [other processes used {load:.2f} cores: timings disturbed]"


def _fmt_count(v: int | None) -> str:
    if v is None:
        return "-"
    for div, suffix in ((1e9, "G"), (1e6, "M"), (1e3, "k")):
        if v >= div:
            return f"{v / div:.3g}{suffix}"
    return str(v)


def _ratio(a: float | None, b: float | None) -> float | None:
    if a is None or b is None or b <= 0:
        return None
    return a / b


def _fmt_ratio(v: float | None) -> str:
    return "-" if v is None else (f"{v:.1f}x" if v >= 10 else f"{v:.2f}x")


def _get(d: dict[str, Any] | None, *keys: str) -> Any:
    for k in keys:
        if not isinstance(d, dict):
            return None
        d = d.get(k)
    return d


def format_table(rows: list[dict[str, Any]]) -> str:
    """The aligned results table (one line per config)."""
    header = [
        "N",
        "res",
        "thr",
        "s4d fwd ms",
        "s4d f+b ms",
        "s4d peak MB",
        "wgpu fwd ms",
        "wgpu f+b ms",
        "wgpu/s4d f+b",
        "ref fwd ms",
        "ref f+b ms",
        "ref peak MB",
        "speed-up",
        "op mem ratio",
        "RSS ratio",
        "visible",
        "isects",
        "evaluated",
        "blended",
    ]
    lines = [header]
    for r in rows:
        s4d, ref = r["sync4d"], r["reference"]
        wg = r.get("wgpu", {})
        counters = s4d.get("counters", {})
        if ref["status"] == "ok":
            ref_cells = [
                _fmt_ms(_get(ref, "forward", "median_ms")),
                _fmt_ms(_get(ref, "forward_backward", "median_ms")),
                _fmt_mb(ref.get("forward_backward")),
            ]
        else:
            ref_cells = [ref["status"], "-", "-"]
        lines.append(
            [
                f"{r['n']:,}",
                r["resolution"],
                str(r["threads"]),
                _fmt_ms(_get(s4d, "forward", "median_ms")),
                _fmt_ms(_get(s4d, "forward_backward", "median_ms")),
                _fmt_mb(s4d.get("forward_backward")),
                _fmt_ms(_get(wg, "forward", "median_ms")),
                _fmt_ms(_get(wg, "forward_backward", "median_ms")),
                _fmt_ratio(
                    _ratio(
                        _get(wg, "forward_backward", "median_ms"),
                        _get(s4d, "forward_backward", "median_ms"),
                    )
                ),
                *ref_cells,
                _fmt_ratio(r.get("speedup_forward_backward")),
                _fmt_ratio(r.get("memory_delta_ratio")),
                _fmt_ratio(r.get("memory_ratio")),
                *(_fmt_count(counters.get(k)) for k in ("visible", "intersections")),
                *(_fmt_count(counters.get(k)) for k in ("evaluated", "blended")),
            ]
        )
    return align_table(header, lines[1:], left=(1,))


def thread_scaling(rows: list[dict[str, Any]]) -> list[dict[str, Any]]:
    """Per (N, resolution): speed-up of T threads over 1 thread (sync4d; reference if run)."""
    by_key: dict[tuple[int, str], dict[int, dict[str, Any]]] = {}
    for r in rows:
        by_key.setdefault((r["n"], r["resolution"]), {})[r["threads"]] = r
    out = []
    for (n, res), per_t in by_key.items():
        if 1 not in per_t:
            continue
        one = per_t[1]
        for t, r in sorted(per_t.items()):
            if t == 1:
                continue
            entry: dict[str, Any] = {"n": n, "resolution": res, "threads": t, "vs_threads": 1}
            for impl in ("sync4d", "reference"):
                for mode in MODES:
                    a = _get(one, impl, mode, "median_ms")
                    b = _get(r, impl, mode, "median_ms")
                    entry[f"{impl}_{mode}_speedup"] = _ratio(a, b)
            out.append(entry)
    return out


def format_scaling(entries: list[dict[str, Any]]) -> str:
    """Text block for :func:`thread_scaling`."""
    lines = []
    for e in entries:
        s = (
            f"  N={e['n']:>9,}  {e['resolution']:>9}  {e['threads']} vs 1 threads: "
            f"sync4d fwd+bwd {_fmt_ratio(e['sync4d_forward_backward_speedup'])}, "
            f"fwd {_fmt_ratio(e['sync4d_forward_speedup'])}"
        )
        if e.get("reference_forward_backward_speedup") is not None:
            s += f"; reference fwd+bwd {_fmt_ratio(e['reference_forward_backward_speedup'])}"
        lines.append(s)
    return "\n".join(lines)


# --------------------------------------------------------------------------------------------
# Driver
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class _Plan:
    sizes: tuple[int, ...]
    resolutions: tuple[tuple[int, int], ...]
    threads: tuple[int, ...]
    quick: bool
    repeats: int | None
    seed: int
    reference: bool
    reference_note: str
    reference_max_gb: float
    memory_method: str
    out: Path
    #: The wgpu adapter timed beside the CPU path ("" when skipped).
    wgpu_adapter: str = ""
    wgpu_note: str = ""

    def sync4d_repeats(self, n: int) -> tuple[int, int]:
        """(warm-up, timed) calls per sync4d measurement."""
        if self.quick:
            return 1, self.repeats or 3
        return 2, self.repeats or (3 if n >= 1_000_000 else 5)

    def reference_repeats(self, n: int) -> tuple[int, int]:
        """(warm-up, timed) calls per reference measurement."""
        if self.quick:
            return 1, 1
        return 1, (1 if n >= 100_000 else 2)


def add_arguments(p: argparse.ArgumentParser) -> None:
    """The description and arguments of ``sync4d bench raster`` (`sync4d.cli`)."""
    p.description = (
        "Time sync4d.raster (forward and backward) on seeded random scenes or, given RUN, on "
        "the run's own Gaussians at its test cameras."
    )
    p.add_argument(
        "run",
        nargs="?",
        default=None,
        metavar="RUN",
        help="time the rasterizer on this trained run's own Gaussians at its test cameras "
        "instead of the random scenes (one thread count: the first of --thread-counts)",
    )
    p.add_argument(
        "--out",
        metavar="FILE.json",
        default=None,
        help="where to write the results as JSON (default: bench-raster.json in the cwd)",
    )
    p.add_argument(
        "--sizes",
        nargs="+",
        type=positive_int,
        metavar="N",
        default=None,
        help="scene sizes as Gaussian counts, e.g. --sizes 1000 10000 "
        "(default: 10000 100000 1000000)",
    )
    p.add_argument(
        "--resolutions",
        nargs="+",
        type=resolution,
        metavar="WxH",
        default=None,
        help="image sizes, e.g. --resolutions 800x800 960x536 (default: 256x256 800x800 960x536)",
    )
    p.add_argument(
        "--thread-counts",
        dest="threads",
        nargs="+",
        type=thread_count,
        metavar="T",
        default=None,
        help="thread counts to time (rayon on the op, torch.set_num_threads for torch), "
        "e.g. --thread-counts 1 2 (default: 1 2)",
    )
    p.add_argument(
        "--repeats",
        type=positive_int,
        metavar="K",
        default=None,
        help="timed sync4d calls per measurement, median reported "
        "(default: 5, 3 for N >= 1M, 3 with --quick)",
    )
    p.add_argument(
        "--reference-max-gb",
        type=positive_float,
        metavar="GB",
        default=None,
        help="kill a reference run whose RSS passes this many GiB (default: 18, and never more "
        "than the memory available minus 1.5 GiB)",
    )
    p.add_argument(
        "--memory-method",
        choices=("auto", "clear_refs", "subprocess"),
        default="auto",
        help="peak-memory method: reset VmHWM via /proc/self/clear_refs, or run each "
        "measurement in a child process and read its ru_maxrss (default: auto)",
    )
    p.add_argument(
        "--no-reference",
        action="store_true",
        help="skip the gsplat torch reference timings",
    )
    p.add_argument(
        "--no-wgpu",
        action="store_true",
        help="skip the wgpu backend timings (default: timed when a wgpu adapter opens, "
        "e.g. lavapipe)",
    )
    p.add_argument(
        "--quick",
        action="store_true",
        help="N=10000 at 256x256 only, fewer repeats (smoke run); --sizes/--resolutions win",
    )
    p.add_argument(
        "--frames",
        type=positive_int,
        metavar="K",
        default=3,
        help="with RUN: test frames timed, evenly spread over the split (default: 3)",
    )
    p.add_argument(
        "--data",
        metavar="DATA",
        default=None,
        help="with RUN: the run's dataset folder, when it moved since the run",
    )
    p.add_argument(
        "--variant",
        action="append",
        default=None,
        metavar="NAME:KEY=VALUE,...",
        help="with RUN: also time rasterize with these keyword arguments (alpha_max, eps2d, "
        "antialiased, backend), frame by frame beside the default (repeatable)",
    )


def _as_namespace(args: argparse.Namespace | Sequence[str] | None) -> argparse.Namespace:
    if isinstance(args, argparse.Namespace):
        return args
    parser = argparse.ArgumentParser(prog="python -m sync4d bench raster")
    add_arguments(parser)
    return parser.parse_args(list(args or []))


def _plan(args: argparse.Namespace) -> _Plan:
    quick = bool(getattr(args, "quick", False))
    sizes = getattr(args, "sizes", None) or (QUICK_SIZES if quick else DEFAULT_SIZES)
    resolutions = getattr(args, "resolutions", None) or (
        QUICK_RESOLUTIONS if quick else DEFAULT_RESOLUTIONS
    )
    resolutions = tuple(
        parse_resolution(r) if isinstance(r, str) else tuple(r) for r in resolutions
    )
    threads = getattr(args, "threads", None) or DEFAULT_THREADS

    reference, note = True, ""
    if getattr(args, "no_reference", False):
        reference, note = False, "skipped (--no-reference)"
    elif importlib.util.find_spec("gsplat") is None:
        reference, note = False, "skipped (gsplat not installed)"

    method = getattr(args, "memory_method", None) or "auto"
    if method == "auto":
        method = METHOD_CLEAR_REFS if clear_refs_available() else METHOD_SUBPROCESS
    elif method == METHOD_CLEAR_REFS and not clear_refs_available():
        raise SystemExit("--memory-method clear_refs: /proc/self/clear_refs is not writable here")

    out = Path(getattr(args, "out", None) or DEFAULT_OUT)
    adapter, wgpu_note = "", ""
    if getattr(args, "no_wgpu", False):
        wgpu_note = "skipped (--no-wgpu)"
    else:
        try:
            adapter = _core.wgpu_adapter()
        except RuntimeError as e:
            wgpu_note = f"skipped ({e})"
    return _Plan(
        sizes=tuple(int(n) for n in sizes),
        resolutions=tuple((int(w), int(h)) for w, h in resolutions),
        threads=tuple(int(t) for t in threads),
        quick=quick,
        repeats=getattr(args, "repeats", None),
        seed=int(getattr(args, "seed", 0) or 0),
        reference=reference,
        reference_note=note,
        reference_max_gb=float(getattr(args, "reference_max_gb", None) or REFERENCE_MAX_GB),
        memory_method=method,
        out=out,
        wgpu_adapter=adapter,
        wgpu_note=wgpu_note,
    )


def _reference_skip(
    plan: _Plan, n: int, width: int, height: int, threads: int, aborted: list[tuple[int, int, int]]
) -> str | None:
    """Why the reference is not run for this config (None: run it)."""
    if not plan.reference:
        return plan.reference_note
    if n > REFERENCE_MAX_N:
        return "skipped (N > 100k)"
    for an, apix, at in aborted:
        if an <= n and apix <= width * height and at == threads:
            return "skipped (memory limit hit by a smaller config)"
    return None


def _write_json(path: Path, doc: dict[str, Any]) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_text(json.dumps(doc, indent=2) + "\n")
    os.replace(tmp, path)


def _run_sync4d(plan: _Plan, n: int, width: int, height: int, threads: int) -> dict[str, Any]:
    warmup, repeats = plan.sync4d_repeats(n)
    job = dict(
        impl="sync4d", n=n, width=width, height=height, seed=plan.seed, threads=threads,
        warmup=warmup, repeats=repeats, memory_method=plan.memory_method,
    )  # fmt: skip
    if plan.memory_method == METHOD_CLEAR_REFS:
        res = run_job(modes=MODES, **job)  # type: ignore[arg-type]
        return {"status": "ok", "in_process": True, **res["modes"], "counters": res["counters"]}
    out: dict[str, Any] = {"status": "ok", "in_process": False}
    for mode in MODES:
        child = run_child(dict(job, modes=[mode]), limit_gb=None)
        if child.status != "ok" or child.result is None:
            raise RuntimeError(f"sync4d {mode} child {child.status}:\n{child.stderr_tail}")
        out[mode] = child.result["modes"][mode]
        out["counters"] = child.result["counters"]
    return out


def _run_wgpu(plan: _Plan, n: int, width: int, height: int, threads: int) -> dict[str, Any]:
    """The sync4d op on the wgpu backend, in this process (times only; the adapter's memory
    is not the process's)."""
    warmup, repeats = plan.sync4d_repeats(n)
    res = run_job(
        impl="wgpu", n=n, width=width, height=height, seed=plan.seed, threads=threads,
        modes=MODES, warmup=warmup, repeats=repeats, memory_method=plan.memory_method,
    )  # fmt: skip
    return {"status": "ok", "adapter": plan.wgpu_adapter, **res["modes"],
            "counters": res["counters"]}  # fmt: skip


def _run_reference(plan: _Plan, n: int, width: int, height: int, threads: int) -> dict[str, Any]:
    warmup, repeats = plan.reference_repeats(n)
    available = mem_available_gb()
    limit = plan.reference_max_gb
    if available is not None:
        if available - MEMORY_RESERVE_GB < 1.0:
            return {"status": f"skipped (only {available:.1f} GB available)"}
        limit = min(limit, available - MEMORY_RESERVE_GB)
    job = dict(
        impl="reference", n=n, width=width, height=height, seed=plan.seed, threads=threads,
        warmup=warmup, repeats=repeats, memory_method=plan.memory_method,
    )  # fmt: skip
    mode_sets = [list(MODES)] if plan.memory_method == METHOD_CLEAR_REFS else [[m] for m in MODES]
    out: dict[str, Any] = {"status": "ok", "rss_limit_gb": round(limit, 2), "children": []}
    for modes in mode_sets:
        child = run_child(dict(job, modes=modes), limit_gb=limit)
        out["children"].append(
            {"modes": modes, "status": child.status, "seconds": child.seconds,
             "watchdog_max_rss_mb": child.watchdog_max_rss_mb}
        )  # fmt: skip
        if child.status != "ok" or child.result is None:
            out["status"] = child.status
            if child.status.startswith("failed"):
                out["stderr_tail"] = child.stderr_tail
            break
        out.update(child.result["modes"])
    return out


def _summarise(row: dict[str, Any]) -> None:
    """Add the speed-ups and memory ratios (reference / sync4d) to a result row."""
    for mode in MODES:
        row[f"speedup_{mode}"] = _ratio(
            _get(row, "reference", mode, "median_ms"), _get(row, "sync4d", mode, "median_ms")
        )
    row["memory_ratio"] = _ratio(
        _get(row, "reference", "forward_backward", "rss_peak_mb"),
        _get(row, "sync4d", "forward_backward", "rss_peak_mb"),
    )
    row["memory_delta_ratio"] = _ratio(
        _get(row, "reference", "forward_backward", "rss_delta_mb"),
        _get(row, "sync4d", "forward_backward", "rss_delta_mb"),
    )


def main(args: argparse.Namespace | Sequence[str] | None = None) -> int:
    """Run the benchmark grid, print the table and write the JSON; returns the exit code.

    ``args`` is the CLI's namespace (``python -m sync4d bench raster ...``) or a list of that
    command's arguments (e.g. ``["--quick", "--no-reference"]``).
    """
    ns = _as_namespace(args)
    if getattr(ns, "run", None):
        from sync4d.bench import raster_run

        return raster_run.main(ns)
    plan = _plan(ns)
    configs = [
        (n, w, h, t) for n in plan.sizes for (w, h) in plan.resolutions for t in plan.threads
    ]
    steps: list[tuple[str, float]] = []
    for n, w, h, t in configs:
        wu, rep = plan.sync4d_repeats(n)
        steps.append(("sync4d", _step_units(n, w, h, t, (wu + rep) * 1.45)))
        if plan.wgpu_adapter:
            steps.append(("wgpu", _step_units(n, w, h, t, (wu + rep) * 1.45)))
        if _reference_skip(plan, n, w, h, t, []) is None:
            wu, rep = plan.reference_repeats(n)
            steps.append(("reference", _step_units(n, w, h, t, (wu + rep) * 1.45)))

    doc: dict[str, Any] = {
        "schema": SCHEMA,
        "complete": False,
        "created": _dt.datetime.now(_dt.UTC).isoformat(timespec="seconds"),
        "command": [sys.executable, *sys.argv],
        "machine": machine_info(),
        "loadavg_at_start": list(os.getloadavg()) if hasattr(os, "getloadavg") else None,
        "allocators": dict(ALLOCATORS),
        "env": _env_info(),
        "settings": {
            "sizes": list(plan.sizes),
            "resolutions": [f"{w}x{h}" for w, h in plan.resolutions],
            "threads": list(plan.threads),
            "quick": plan.quick,
            "seed": plan.seed,
            "scene": "bench_scene: identity viewmat, fx = fy = 0.8 W, cx = W/2, cy = H/2, "
            "z ~ U(2, 6), x/y uniform over the frustum widened 10%, quats ~ N(0, 1), "
            "scales = exp(N(log 0.012, 0.5)), opacities ~ U(0.05, 0.95), RGB ~ U(0, 1), float32",
            "loss": "features.sum() + alpha.sum(); grads w.r.t. means, quats, scales, "
            "opacities, colors (torch.autograd.grad)",
            "sync4d_call": "sync4d.raster.rasterize(..., threads=T) with its defaults "
            "(alpha_max 0.99); forward under torch.no_grad",
            "reference_call": "sync4d.reference.gsplat.gsplat_render (gsplat 1.5.3 torch "
            "pipeline, fast_isect, CPU substitutes; alpha clamp 0.999) in a child process",
            "torch_threads": "torch.set_num_threads(T) for every measurement",
            "repeats": {
                "sync4d": {str(n): list(plan.sync4d_repeats(n)) for n in plan.sizes},
                "reference": {str(n): list(plan.reference_repeats(n)) for n in plan.sizes},
                "format": "[warm-up calls, timed calls]; median of the timed calls",
            },
            "wgpu_adapter": plan.wgpu_adapter or None,
            "wgpu_note": plan.wgpu_note or None,
            "reference_enabled": plan.reference,
            "reference_note": plan.reference_note or None,
            "reference_max_n": REFERENCE_MAX_N,
            "reference_max_gb": plan.reference_max_gb,
            "memory_method": plan.memory_method,
            "memory_method_description": MEMORY_METHODS[plan.memory_method],
            "units": {"time": "ms", "memory": "MB = MiB (2**20 bytes); GB = GiB"},
        },
        "results": [],
    }
    print(
        f"sync4d {sync4d.__version__} bench raster: {len(configs)} configs "
        f"(N {list(plan.sizes)}, {[f'{w}x{h}' for w, h in plan.resolutions]}, "
        f"threads {list(plan.threads)}); wgpu: {plan.wgpu_adapter or plan.wgpu_note}; "
        f"reference: "
        f"{'N <= 100k' if plan.reference else plan.reference_note}; "
        f"memory: {plan.memory_method}; json: {plan.out}",
        flush=True,
    )
    progress = _Progress(steps)
    aborted: list[tuple[int, int, int]] = []
    saved_threads = torch.get_num_threads()
    rows: list[dict[str, Any]] = doc["results"]
    try:
        for n, w, h, t in configs:
            label = f"N={n:,} {w}x{h} threads={t}"
            row: dict[str, Any] = {
                "n": n, "width": w, "height": h, "resolution": f"{w}x{h}", "threads": t,
            }  # fmt: skip
            progress.say(f"sync4d     {label} ...")
            t0, load = time.monotonic(), OtherLoad()
            row["sync4d"] = _run_sync4d(plan, n, w, h, t)
            s4d = row["sync4d"]
            s4d["seconds"] = round(time.monotonic() - t0, 3)
            s4d["other_load_cores"] = load.cores()
            progress.finish(
                f"sync4d     {label}: fwd {_fmt_ms(s4d['forward']['median_ms'])} ms, "
                f"fwd+bwd {_fmt_ms(s4d['forward_backward']['median_ms'])} ms, "
                f"peak {_fmt_mb(s4d['forward_backward'])} MB{_fmt_load(s4d)}",
                s4d["seconds"],
            )
            if plan.wgpu_adapter:
                progress.say(f"wgpu       {label} ...")
                t0, load = time.monotonic(), OtherLoad()
                wg = row["wgpu"] = _run_wgpu(plan, n, w, h, t)
                wg["seconds"] = round(time.monotonic() - t0, 3)
                wg["other_load_cores"] = load.cores()
                progress.finish(
                    f"wgpu       {label}: fwd {_fmt_ms(wg['forward']['median_ms'])} ms, "
                    f"fwd+bwd {_fmt_ms(wg['forward_backward']['median_ms'])} ms{_fmt_load(wg)}",
                    wg["seconds"],
                )
            else:
                row["wgpu"] = {"status": plan.wgpu_note}
            skip = _reference_skip(plan, n, w, h, t, aborted)
            if skip is None:
                progress.say(f"reference  {label} ...")
                t0, load = time.monotonic(), OtherLoad()
                row["reference"] = _run_reference(plan, n, w, h, t)
                ref = row["reference"]
                ref["seconds"] = round(time.monotonic() - t0, 3)
                ref["other_load_cores"] = load.cores()
                if ref["status"] == "ok":
                    text = (
                        f"fwd {_fmt_ms(ref['forward']['median_ms'])} ms, "
                        f"fwd+bwd {_fmt_ms(ref['forward_backward']['median_ms'])} ms, "
                        f"peak {_fmt_mb(ref['forward_backward'])} MB{_fmt_load(ref)}"
                    )
                else:
                    text = ref["status"]
                    if ref["status"].startswith("aborted (RSS"):
                        aborted.append((n, w * h, t))
                    if ref.get("stderr_tail"):
                        print(ref["stderr_tail"], file=sys.stderr)
                progress.finish(f"reference  {label}: {text}", ref["seconds"])
            else:
                row["reference"] = {"status": skip}
            _summarise(row)
            rows.append(row)
            doc["total_seconds"] = round(progress.elapsed(), 3)
            _write_json(plan.out, doc)
    finally:
        torch.set_num_threads(saved_threads)

    doc["thread_scaling"] = thread_scaling(rows)
    doc["complete"] = True
    doc["total_seconds"] = round(progress.elapsed(), 3)
    _write_json(plan.out, doc)

    print()
    print(format_table(rows))
    print(
        "\nms: median wall time; wgpu: the same op with backend='wgpu' (wgpu/s4d: its fwd+bwd "
        "time over the CPU path's);\npeak MB: peak RSS of the process during fwd+bwd (+ growth "
        "over the RSS before it);\nspeed-up: reference fwd+bwd / sync4d fwd+bwd; op mem ratio: "
        "reference growth / sync4d growth\n(the memory each op adds on top of the Python + torch "
        "process); RSS ratio: reference peak RSS / sync4d peak RSS;\ncounters: sync4d forward "
        "work (visible Gaussians, tile "
        "intersections, evaluated and blended pairs)."
    )
    disturbed = [
        f"{r['n']:,} {r['resolution']} t={r['threads']} {impl}"
        for r in rows
        for impl in ("sync4d", "reference")
        if (_get(r, impl, "other_load_cores") or 0.0) >= LOAD_WARN_CORES
    ]
    if disturbed:
        print(
            f"\nwarning: other processes used >= {LOAD_WARN_CORES} cores during "
            f"{len(disturbed)} measurement(s) ({'; '.join(disturbed)}): those timings are "
            "disturbed (see other_load_cores in the JSON)."
        )
    scaling = doc["thread_scaling"]
    if scaling:
        print("\nThread scaling (median time at 1 thread / at T threads):")
        print(format_scaling(scaling))
    print(f"\nwrote {plan.out} ({_hms(doc['total_seconds'])} total)")
    return 0
