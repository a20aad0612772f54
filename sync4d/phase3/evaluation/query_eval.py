"""Evaluating temporal queries on a run's field (Appendix F): Acc, vIoU and tIoU per query and
scorer, from 4D LangSplat's annotations or our own query file (`annotations`).

Each query is answered by each scorer (`query.SCORERS`, in their order; one that needs named
objects only when they are named); the top-ranked object's activation is scored against the
ground truth (`query_metrics.evaluate_query`: a wrong object counts as no overlap). Predicted masks
for vIoU are the chosen object's pixels in an occlusion-aware render of every Gaussian's object
label (the pixel's dominant label), from the frame's training view.
Ground-truth masks come from 4D LangSplat's polygons or, for our format, from the dataset's
instance masks when it has them and the query names a label.

Rows go to ``RUN/phase3/eval-<name>-<scorer>.csv`` and ``.json``
(`query_metrics.write_rows`), with a summary over scorers in ``RUN/phase3/eval-<name>.json``.
"""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import numpy as np
import torch

from sync4d import raster
from sync4d.data import Scene
from sync4d.data.synthetic import GROUND_TRUTH, load_ground_truth
from sync4d.files import write_text_atomic
from sync4d.phase3.encoders.encoder import Encoder
from sync4d.phase3.evaluation.annotations import (
    AnnotationError,
    Query,
    frame_map,
    read_4dlangsplat,
    read_queries,
)
from sync4d.phase3.evaluation.query_metrics import evaluate_query, write_rows
from sync4d.phase3.query import SCORER_TABLE, SCORERS, TextCache, answer
from sync4d.phase3.store import Field, load_field
from sync4d.runs import Run, load_run
from sync4d.runs.names import (
    EMBEDDED_QUERIES_FILE,
    FIELD_DIR,
    query_eval_files,
    query_eval_summary,
)

__all__ = ["evaluate_queries", "label_masks", "state_queries"]


def _views(field: Field, scene: Scene) -> list[int]:
    """Index into `scene.train` of the first training view at each field frame (-1: none)."""
    out = []
    for t in field.times:
        hits = [i for i, fr in enumerate(scene.train) if abs(fr.time - t) < 1e-6]
        out.append(hits[0] if hits else -1)
    return out


@torch.no_grad()
def label_masks(run: Run, scene: Scene, field: Field, frames: list[int], label: int,
                threads: int | None = None) -> list[np.ndarray | None]:  # fmt: skip
    """Predicted masks (bool [H, W]) of object `label` at field `frames` (None elsewhere): the
    pixels whose dominant rendered label is `label` with alpha of at least 0.5."""
    views = _views(field, scene)
    labels = torch.as_tensor(run.labels, dtype=torch.long)
    k = int(run.motion.num_objects)
    onehot = torch.zeros(len(labels), k)
    onehot[torch.arange(len(labels)), labels] = 1.0
    opac = torch.sigmoid(run.model.opacity_logits)
    out: list[np.ndarray | None] = [None] * len(field.times)
    for f in frames:
        vi = views[f]
        if vi < 0:
            continue
        cam = scene.train[vi].camera
        means, quats, scales = run.model.at_time(float(field.times[f]))
        r = raster.rasterize(
            means, quats, scales, opac, onehot, torch.as_tensor(cam.viewmat, dtype=torch.float32),
            torch.as_tensor(cam.K, dtype=torch.float32), cam.width, cam.height,
            background=torch.zeros(k), near=run.model.near, threads=threads,
        )  # fmt: skip
        img = r.features.numpy()
        out[f] = (img.argmax(-1) == label) & (r.alpha.numpy()[..., 0] >= 0.5)
    return out


def _dataset_masks(scene: Scene, field: Field, q: Query) -> tuple | None:
    """GT masks of `q`'s label from the dataset's instance masks (None without masks)."""
    if q.label is None or not scene.has_masks:
        return None
    views = _views(field, scene)
    masks = []
    for vi in views:
        if vi < 0:
            masks.append(None)
            continue
        m = scene.train[vi].load_mask()
        masks.append(None if m is None else np.asarray(m) == q.label)
    return tuple(masks)


def state_queries(ground_truth: str | Path) -> dict:
    """Our query format from the embedded scene's ``ground_truth.json``: one query per
    (object, state), "the <object> <state>", over the state's time ranges."""
    gt = load_ground_truth(Path(ground_truth).parent)
    name_of = dict(zip(gt.ids, gt.names, strict=True))
    merged: dict[tuple[int, str], list[list[float]]] = {}
    for label, state, t0, t1 in gt.states:
        merged.setdefault((label, state), []).append([t0, t1])
    return {"version": 1, "scene": "embedded synthetic scene", "queries": [
        {"query": f"the {name_of[label]} {state}", "object": name_of[label], "times": spans}
        for (label, state), spans in merged.items()]}  # fmt: skip


def _is_ground_truth(path: Path) -> bool:
    """Whether `path` is the embedded scene's ground_truth.json."""
    if path.name != GROUND_TRUTH or not path.is_file():
        return False
    try:
        return "states" in json.loads(path.read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return False


def _read(path: Path, field: Field, run: Run, scene: Scene | None) -> list[Query]:
    """The queries of `path` in either format, checked against the run; the embedded scene's
    ground_truth.json is turned into our format first (RUN/phase3/queries-embedded.json)."""
    num = int(run.motion.num_objects) if run.motion is not None else 1
    names = [run.names.get(j, f"object {j}") for j in range(num)]
    t = len(field.times)
    if _is_ground_truth(path):
        path = write_text_atomic(run.path / FIELD_DIR / EMBEDDED_QUERIES_FILE,
                                 json.dumps(state_queries(path), indent=1) + "\n")  # fmt: skip
    video = path / "video_annotations.json" if path.is_dir() else None
    if (video is not None and video.exists()) or (path.is_dir() and
                                                  (path / "annotations").is_dir()):  # fmt: skip
        size = frames = None
        if scene is not None and scene.train:
            size = (scene.train[0].camera.width, scene.train[0].camera.height)
            every = scene.train + scene.test
            frames = frame_map([fr.image_path.name for fr in every], [fr.time for fr in every],
                               field.times)  # fmt: skip
        return read_4dlangsplat(path, t, image_size=size, object_names=names, frame_of=frames)
    if path.is_file():
        return read_queries(path, t, frame_times=field.times, object_names=names)
    raise AnnotationError(path, "no such annotation file or folder",
                          "give our query JSON or 4D LangSplat's annotations folder")


def evaluate_queries(
    run_dir: str | Path, annotations: str | Path, *, scorers: tuple[str, ...] = SCORERS,
    rule: str | None = None, data: str | Path | None = None, threads: int | None = None,
    encoder: Encoder | str | None = None,
) -> dict:  # fmt: skip
    """Acc / vIoU / tIoU of every query in `annotations` for each of `scorers` on the field of
    the run in `run_dir`; writes the rows (CSV and JSON) and a summary into RUN/phase3 and
    returns the summary {scorer: mean row}. `encoder`: the field's encoder if it moved (or a
    loaded one)."""
    run_dir = Path(run_dir)
    field = load_field(run_dir)
    run = load_run(run_dir)
    scene = run.scene(data)
    path = Path(annotations)
    queries = _read(path, field, run, scene)
    if not queries:
        raise AnnotationError(f"{path}: holds no query")
    named = not all(n.startswith("object ") for n in field.names)
    scorers = tuple(s for s in scorers if named or s not in SCORER_TABLE
                    or not SCORER_TABLE[s].needs_names)  # fmt: skip
    cache = TextCache(run_dir, field, encoder)
    gt_masks = {}
    for i, q in enumerate(queries):
        m = q.gt_masks
        if m is None and scene is not None:
            m = _dataset_masks(scene, field, q)
        gt_masks[i] = m
    mask_cache: dict[tuple[int, tuple[int, ...]], list] = {}
    name = path.stem if path.is_file() else path.name
    summary: dict[str, dict] = {}
    out_dir = run_dir / FIELD_DIR
    for scorer in scorers:
        rows = []
        for i, q in enumerate(queries):
            ans = answer(field, q.text, cache=cache, scorer=scorer, rule=rule)
            top = ans["objects"][0]
            frames = [f for f in range(len(field.times)) if gt_masks[i] is not None
                      and gt_masks[i][f] is not None]  # fmt: skip
            pred = None
            if frames and scene is not None:
                key = (top["label"], tuple(frames))
                if key not in mask_cache:
                    mask_cache[key] = label_masks(run, scene, field, frames, top["label"],
                                                  threads)  # fmt: skip
                pred = mask_cache[key]
            qq = q if gt_masks[i] is q.gt_masks else _with_masks(q, gt_masks[i])
            rows.append(evaluate_query(
                qq, ans["timeline"][top["name"]], ans["rule"], object=top["label"],
                pred_masks=pred, active=np.asarray(ans["active"][top["name"]], bool)))
        csv_name, json_name = query_eval_files(name, scorer)
        mean = write_rows(rows, out_dir / csv_name, out_dir / json_name)
        judged = [r.object_correct for r in rows if r.object_correct is not None]
        mean["object_accuracy"] = float(np.mean(judged)) if judged else None
        summary[scorer] = mean
    write_text_atomic(out_dir / query_eval_summary(name), json.dumps(
        {"annotations": str(path), "queries": len(queries), "scorers": summary,
         "encoder": field.encoder}, indent=1) + "\n")  # fmt: skip
    return summary


def _with_masks(q: Query, masks: tuple | None) -> Query:
    """`q` with other ground-truth masks."""
    return dataclasses.replace(q, gt_masks=masks)

