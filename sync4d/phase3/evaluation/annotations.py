"""Ground truth of Phase 3's temporal queries (Appendix F): two annotation formats, one structure.

Design notes
------------
Every reader returns ``list[Query]``: the query text, its target object (a name and/or a label
id into the run's object names), ``gt_active`` (bool over the run's frames 0..T-1),
``evaluated`` (bool [T], the frames the query is scored on) and optional per-frame GT masks
(T entries, bool [H, W] at the run's image size, or None). Bad input raises one
`AnnotationError` (a ValueError) naming the file, the problem and what to do.

**4D LangSplat's format** (`read_4dlangsplat`), as its released ``eval/eval.py`` reads it
(github.com/zrporz/4DLangSplat; read in the mirror ``pouyaardehkhani/4DLangSplat``:
``eval/eval.py`` ``eval_gt_lerfdata`` and the ``__main__`` block, ``eval/eval_utils.py``
``polygon_to_mask``, ``scripts/eval-hypernerf.sh``, ``README.md``)::

    data/hypernerf/<scene>/annotations/
        train/_annotations.coco.json   Roboflow COCO export: per-frame object polygons
        video_annotations.json         {object: {query: [[start, end], ...]}}
        README

* COCO ``categories`` [{id, name}], ``images`` [{id, file_name, width, height}],
  ``annotations`` [{image_id, category_id, segmentation: [[x1, y1, x2, y2, ...], ...], bbox}]
  with polygon vertices in pixels of that image. Several annotations of one category in one
  image are merged (their ``stack_mask``).
* The frame of an image comes from its file name: 4D LangSplat takes
  ``int(file_name.split("_")[0])`` (Roboflow names such as ``000123_png.rf.<hash>.jpg``) and
  subtracts 1 for HyperNeRF, whose images are numbered from 1 (``000001.png``), not for Neu3D.
  Here: the first run of digits in the file name (also accepts ``frame_00123.jpg``), minus
  `file_number_base` (default 1, HyperNeRF; pass 0 for Neu3D). With `frame_of` (what
  ``eval --queries`` passes when it has the dataset) the number is looked up by name instead:
  the dataset image whose file name carries the same number (``000123.png``, HyperNeRF id
  ``000123``) gives its time, and the run frame at that time is the annotation's frame, so
  annotations of a subset of the images, or of ids that do not start at 1, land on the right
  frames.
* ``video_annotations.json`` maps an object, which must be a category name (its masks are the
  query's GT masks: 4D LangSplat copies the category's masks to each of its queries), to its
  time-dependent queries, each with inclusive frame ranges in the same 0-based frame index.
* 4D LangSplat scores a query only on the frames whose image has a mask of its object (the
  prompts of an image are the labels annotated on it); ``evaluated`` reproduces that.
* Polygons: 4D LangSplat fills only ``segmentation[0]`` with ``cv2.fillPoly`` on int32
  (truncated) vertices. Here every polygon of an annotation is filled (a multi-part object
  keeps all its parts; Roboflow writes one polygon per annotation, so results agree), with
  Pillow's ``ImageDraw.polygon`` (its fill includes the boundary pixels, like fillPoly),
  after scaling the vertices by run size / annotation size and truncating them to integers.
  Boundary pixels of slanted edges may differ from OpenCV's by one pixel.

**Our own format** (`read_queries`; see ``docs/phase3-queries.md``)::

    {"version": 1,                                    # optional; only 1
     "scene": "bouncingballs",                        # optional, free text
     "queries": [
       {"query": "the red ball while it is falling",
        "object": "red ball",                         # a run object name, or its label id
        "frames": [[0, 4], [9, 9]]},                  # inclusive 0-based run frames, or
       {"query": "...", "object": 2,
        "times": [[0.0, 0.35]]}]}                     # run-normalised time [0, 1], inclusive

A frame is GT-active under ``times`` when its time (`frame_times`, the run's normalised time of
each frame) lies in one [t0, t1] (within 1e-9). Every frame is evaluated; there are no masks
(vIoU needs GT masks: use the 4D LangSplat format or fill ``Query.gt_masks``). Unknown keys
are errors, to catch typos ("frame" for "frames").
"""

from __future__ import annotations

import json
import re
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from PIL import Image, ImageDraw

from sync4d.errors import Sync4dError
from sync4d.phase3.activation import from_intervals

__all__ = [
    "COCO_FILE",
    "VIDEO_FILE",
    "AnnotationError",
    "Query",
    "frame_map",
    "frame_number",
    "load_queries",
    "rasterize_polygons",
    "read_4dlangsplat",
    "read_queries",
]

#: 4D LangSplat's file names inside ``<scene>/annotations``.
COCO_FILE = "_annotations.coco.json"
VIDEO_FILE = "video_annotations.json"

#: Slack when a frame time is compared with a [t0, t1] range of our format.
TIME_EPS = 1e-9


class AnnotationError(Sync4dError, ValueError):
    """An annotation file that cannot be used; the message names the file, the problem and
    what to do. `path` is the file."""

    def __init__(self, path: str | Path, problem: str, fix: str = "") -> None:
        self.path = Path(path)
        self.problem = problem
        super().__init__(f"{path}: {problem}" + (f"; {fix}" if fix else ""))


@dataclass(frozen=True, eq=False)
class Query:
    """One temporal query's ground truth over a run of T frames.

    `text`: the query; `object` / `label`: the target object's name and label id (either may be
    None when not known); `gt_active` bool [T]: frames where the query holds; `evaluated` bool
    [T]: frames it is scored on; `gt_masks`: None, or T entries each a bool [H, W] mask of the
    object at the run's image size or None (frame without a mask); `source`: the file read."""

    text: str
    object: str | None
    label: int | None
    gt_active: np.ndarray
    evaluated: np.ndarray
    gt_masks: tuple[np.ndarray | None, ...] | None
    source: str

    @property
    def n_frames(self) -> int:
        """T, the run's frame count."""
        return int(self.gt_active.size)


def _read_json(path: Path) -> Any:
    try:
        text = path.read_text(encoding="utf-8")
    except FileNotFoundError:
        raise AnnotationError(path, "file not found", "check the path") from None
    except (OSError, UnicodeDecodeError) as e:
        raise AnnotationError(path, f"cannot read ({e})", "check the file") from None
    try:
        return json.loads(text)
    except json.JSONDecodeError as e:
        raise AnnotationError(
            path, f"not JSON ({e.msg} at line {e.lineno} column {e.colno})",
            "fix the file or point to the right one",
        ) from None  # fmt: skip


def _is_int(v: Any) -> bool:
    return isinstance(v, int) and not isinstance(v, bool)


def _is_number(v: Any) -> bool:
    return isinstance(v, (int, float)) and not isinstance(v, bool) and np.isfinite(v)


def frame_number(file_name: str) -> int:
    """The first run of decimal digits in the base name of `file_name` ("000123.png" -> 123,
    "frame_00123.jpg" -> 123, "000045_png.rf.9f1c.jpg" -> 45). ValueError if it has none."""
    m = re.search(r"\d+", Path(file_name).name)
    if m is None:
        raise ValueError(f"no digits in file name {file_name!r}")
    return int(m.group())


def rasterize_polygons(
    polygons: Sequence[Sequence[float]],
    image_size: tuple[int, int],
    source_size: tuple[int, int] | None = None,
) -> np.ndarray:
    """The union of the filled `polygons` (each flat [x1, y1, x2, y2, ...] in pixels of an image
    of `source_size` (width, height); default `image_size`) as a bool mask [H, W] at
    `image_size` (width, height). Vertices are scaled by image / source size and truncated to
    integers; boundary pixels are inside (like OpenCV's fillPoly)."""
    w, h = int(image_size[0]), int(image_size[1])
    sw, sh = (w, h) if source_size is None else (int(source_size[0]), int(source_size[1]))
    if min(w, h, sw, sh) <= 0:
        raise ValueError(f"image sizes must be positive, got {image_size} and {source_size}")
    im = Image.new("L", (w, h), 0)
    draw = ImageDraw.Draw(im)
    for poly in polygons:
        xy = np.asarray(poly, dtype=np.float64)
        if xy.ndim != 1 or xy.size % 2 or xy.size < 6:
            raise ValueError(f"a polygon needs an even count >= 6 of coordinates, got {xy.size}")
        pts = np.trunc(xy.reshape(-1, 2) * (w / sw, h / sh)).astype(np.int64)
        draw.polygon([(int(x), int(y)) for x, y in pts], fill=1)
    return np.asarray(im) > 0


def _resolve_object(
    obj: Any, object_names: Sequence[str] | None, path: Path, where: str
) -> tuple[str | None, int | None]:
    """(name, label) of an object given by name or label id, checked against the run's names."""
    if isinstance(obj, str):
        name = obj.strip()
        if not name:
            raise AnnotationError(path, f"{where}: empty object name", "name a run object")
        if object_names is None:
            return name, None
        if name not in object_names:
            raise AnnotationError(
                path, f"{where}: unknown object {name!r}",
                f"use one of the run's objects {list(object_names)} (or its label id)",
            )  # fmt: skip
        return name, list(object_names).index(name)
    if _is_int(obj):
        if obj < 0 or (object_names is not None and obj >= len(object_names)):
            known = "" if object_names is None else f" 0..{len(object_names) - 1}"
            raise AnnotationError(
                path, f"{where}: object label {obj} out of range",
                f"use a label id{known} of the run's objects",
            )  # fmt: skip
        return (None if object_names is None else object_names[obj]), obj
    raise AnnotationError(
        path, f"{where}: 'object' must be a name or a label id, got {obj!r}", "fix the entry"
    )


def _frame_ranges(value: Any, n_frames: int, path: Path, where: str) -> np.ndarray:
    """bool [n_frames] of a list of inclusive [start, end] frame ranges, validated."""
    if not isinstance(value, list):
        raise AnnotationError(
            path, f"{where}: frame ranges must be a list of [start, end], got {value!r}",
            "write e.g. [[0, 4], [9, 12]]",
        )  # fmt: skip
    for r in value:
        if not (isinstance(r, list) and len(r) == 2 and all(_is_int(v) for v in r)):
            raise AnnotationError(
                path, f"{where}: frame range {r!r} is not [start, end] of integers",
                "write e.g. [[0, 4], [9, 12]]",
            )  # fmt: skip
        s, e = r
        if s > e:
            raise AnnotationError(
                path, f"{where}: frame range [{s}, {e}] is reversed", "write [start, end]"
            )
        if s < 0 or e >= n_frames:
            raise AnnotationError(
                path, f"{where}: frame range [{s}, {e}] lies outside the run's frames "
                f"0..{n_frames - 1}",
                "frames are 0-based and inclusive; check the annotation matches this run",
            )  # fmt: skip
    return from_intervals(value, n_frames)


def _time_ranges(
    value: Any, frame_times: np.ndarray, path: Path, where: str
) -> np.ndarray:
    """bool [T]: frames whose time lies in one of the inclusive [t0, t1] ranges of `value`."""
    if not isinstance(value, list):
        raise AnnotationError(
            path, f"{where}: 'times' must be a list of [t0, t1], got {value!r}",
            "write e.g. [[0.0, 0.35]]",
        )  # fmt: skip
    out = np.zeros(frame_times.size, dtype=bool)
    for r in value:
        if not (isinstance(r, list) and len(r) == 2 and all(_is_number(v) for v in r)):
            raise AnnotationError(
                path, f"{where}: time range {r!r} is not [t0, t1] of numbers",
                "write e.g. [[0.0, 0.35]]",
            )  # fmt: skip
        t0, t1 = float(r[0]), float(r[1])
        if t0 > t1:
            raise AnnotationError(path, f"{where}: time range [{t0}, {t1}] is reversed",
                                  "write [t0, t1]")  # fmt: skip
        if t0 < 0.0 or t1 > 1.0:
            raise AnnotationError(
                path, f"{where}: time range [{t0}, {t1}] lies outside [0, 1]",
                "times are the run's normalised time in [0, 1]",
            )  # fmt: skip
        hit = (frame_times >= t0 - TIME_EPS) & (frame_times <= t1 + TIME_EPS)
        if not hit.any():
            raise AnnotationError(
                path, f"{where}: time range [{t0}, {t1}] contains no frame time",
                "widen it to cover at least one frame, or use 'frames'",
            )  # fmt: skip
        out |= hit
    return out


def _query_text(value: Any, path: Path, where: str, seen: set[str]) -> str:
    if not isinstance(value, str) or not value.strip():
        raise AnnotationError(path, f"{where}: empty query string", "write the query text")
    text = value.strip()
    if text in seen:
        raise AnnotationError(path, f"{where}: query {text!r} appears twice",
                              "give each query once, with all its frame ranges")  # fmt: skip
    seen.add(text)
    return text


_TOP_KEYS = {"version", "scene", "comment", "queries"}
_QUERY_KEYS = {"query", "object", "frames", "times", "comment"}


def read_queries(
    path: str | Path,
    n_frames: int,
    frame_times: np.ndarray | Sequence[float] | None = None,
    object_names: Sequence[str] | None = None,
) -> list[Query]:
    """Read our query file (format in the module notes) for a run of `n_frames` frames.

    `frame_times` [n_frames]: the run's normalised time of each frame, needed for ``times``;
    `object_names`: the run's object names (label id = index) to check ``object`` against.
    Every frame is evaluated; no masks. Raises AnnotationError naming the file."""
    path = Path(path)
    if n_frames <= 0:
        raise ValueError(f"n_frames must be positive, got {n_frames}")
    times = None
    if frame_times is not None:
        times = np.asarray(frame_times, dtype=np.float64)
        if times.shape != (n_frames,):
            raise ValueError(f"frame_times must have {n_frames} entries, got {list(times.shape)}")
    doc = _read_json(path)
    if not isinstance(doc, dict) or "queries" not in doc:
        raise AnnotationError(path, "missing key 'queries'",
                              'write {"queries": [{"query": ..., "object": ..., '
                              '"frames": [[s, e]]}]}')  # fmt: skip
    extra = set(doc) - _TOP_KEYS
    if extra:
        raise AnnotationError(path, f"unknown top-level keys {sorted(extra)}",
                              f"use only {sorted(_TOP_KEYS)}")  # fmt: skip
    if doc.get("version", 1) != 1:
        raise AnnotationError(path, f"unsupported version {doc['version']!r}",
                              "this reader knows version 1")  # fmt: skip
    entries = doc["queries"]
    if not isinstance(entries, list) or not entries:
        raise AnnotationError(path, "'queries' must be a non-empty list", "add queries")
    out: list[Query] = []
    seen: set[str] = set()
    for j, q in enumerate(entries):
        where = f"queries[{j}]"
        if not isinstance(q, dict):
            raise AnnotationError(path, f"{where} is not an object", "write {\"query\": ...}")
        for key in ("query", "object"):
            if key not in q:
                raise AnnotationError(path, f"{where}: missing key '{key}'", "add it")
        extra = set(q) - _QUERY_KEYS
        if extra:
            raise AnnotationError(path, f"{where}: unknown keys {sorted(extra)}",
                                  f"use only {sorted(_QUERY_KEYS)}")  # fmt: skip
        text = _query_text(q["query"], path, where, seen)
        where = f"{where} ({text!r})"
        name, label = _resolve_object(q["object"], object_names, path, where)
        if ("frames" in q) == ("times" in q):
            raise AnnotationError(
                path, f"{where}: give exactly one of 'frames' and 'times'",
                "frames: 0-based run frames; times: normalised [0, 1]",
            )  # fmt: skip
        if "frames" in q:
            gt = _frame_ranges(q["frames"], n_frames, path, where)
        else:
            if times is None:
                raise AnnotationError(path, f"{where}: uses 'times' but no frame times were "
                                      "given", "pass the run's frame_times")  # fmt: skip
            gt = _time_ranges(q["times"], times, path, where)
        out.append(Query(text, name, label, gt, np.ones(n_frames, dtype=bool), None, str(path)))
    return out


def _find_4dlangsplat_files(root: Path, split: str) -> tuple[Path, Path]:
    """(COCO json, video_annotations.json) under a scene or annotations folder."""
    if not root.is_dir():
        raise AnnotationError(root, "not a folder",
                              "pass 4D LangSplat's <scene>/annotations folder")  # fmt: skip
    if not (root / VIDEO_FILE).exists() and (root / "annotations").is_dir():
        root = root / "annotations"
    video = root / VIDEO_FILE
    if not video.is_file():
        raise AnnotationError(video, "file not found",
                              "4D LangSplat's temporal queries live in "
                              "<scene>/annotations/video_annotations.json")  # fmt: skip
    folder = root / split
    coco = folder / COCO_FILE
    if not coco.is_file():
        found = sorted(folder.glob("*.json")) if folder.is_dir() else []
        if len(found) != 1:
            raise AnnotationError(
                coco, "file not found" + (f" (and {len(found)} other json files)" if found
                                          else ""),
                f"expected the Roboflow COCO export at <annotations>/{split}/{COCO_FILE}",
            )  # fmt: skip
        coco = found[0]
    return coco, video


def _positive_int(v: Any) -> bool:
    return _is_int(v) and v > 0


def read_4dlangsplat(
    annotations: str | Path,
    n_frames: int,
    image_size: tuple[int, int] | None = None,
    object_names: Sequence[str] | None = None,
    file_number_base: int = 1,
    split: str = "train",
    frame_of: dict[int, int] | None = None,
) -> list[Query]:
    """Read 4D LangSplat's annotations (layout and rules in the module notes) for a run of
    `n_frames` frames: one Query per (object, query) of ``video_annotations.json``.

    `annotations`: the ``<scene>/annotations`` folder (or the scene folder holding it);
    `image_size` (width, height): the run's image size, masks are rasterised at it (default:
    the annotation's own size, which must then be the same for every image); `object_names`:
    the run's object names to check the objects against (label id = index);
    `file_number_base`: the file number of frame 0 (1 for HyperNeRF, 0 for Neu3D);
    `frame_of`: file number -> run frame, from the dataset's image names (`frame_map`): when
    given, frames are mapped by file name and `file_number_base` is not used.
    Raises AnnotationError naming the file."""
    if n_frames <= 0:
        raise ValueError(f"n_frames must be positive, got {n_frames}")
    coco_path, video_path = _find_4dlangsplat_files(Path(annotations), split)
    coco = _read_json(coco_path)
    if not isinstance(coco, dict):
        raise AnnotationError(coco_path, "not a COCO object", "point to a COCO export")
    for key in ("images", "annotations", "categories"):
        if not isinstance(coco.get(key), list):
            raise AnnotationError(coco_path, f"missing key '{key}' (a list)",
                                  "point to a COCO export with polygon segmentations")  # fmt: skip

    names: dict[Any, str] = {}
    for j, c in enumerate(coco["categories"]):
        if not (isinstance(c, dict) and _is_int(c.get("id")) and isinstance(c.get("name"), str)):
            raise AnnotationError(coco_path, f"categories[{j}] needs an integer 'id' and a 'name'",
                                  "fix the COCO export")  # fmt: skip
        names[c["id"]] = c["name"]

    frames: dict[Any, int] = {}
    sizes: dict[Any, tuple[int, int]] = {}
    by_frame: dict[int, str] = {}
    for j, im in enumerate(coco["images"]):
        if not (isinstance(im, dict) and _is_int(im.get("id"))
                and isinstance(im.get("file_name"), str)):
            raise AnnotationError(coco_path, f"images[{j}] needs an integer 'id' and a "
                                  "'file_name'",
                                  "fix the COCO export")  # fmt: skip
        fname = im["file_name"]
        if not (_positive_int(im.get("width")) and _positive_int(im.get("height"))):
            raise AnnotationError(coco_path, f"image {fname!r}: 'width' and 'height' must be "
                                  "positive integers", "fix the COCO export")  # fmt: skip
        try:
            number = frame_number(fname)
        except ValueError:
            raise AnnotationError(
                coco_path, f"image {fname!r}: no digits in the file name, so no frame index",
                "name images by frame number (e.g. 000123.png or frame_00123.jpg)",
            ) from None  # fmt: skip
        if frame_of is not None:
            if number not in frame_of:
                raise AnnotationError(
                    coco_path, f"image {fname!r}: no dataset image is numbered {number} at a "
                    "time of the run's frames",
                    "annotate the dataset's own images (e.g. rgb/2x/000123.png as 000123.png)",
                )  # fmt: skip
            f = frame_of[number]
        else:
            f = number - file_number_base
        if not 0 <= f < n_frames:
            raise AnnotationError(
                coco_path, f"image {fname!r} maps to frame {f}, outside the run's frames "
                f"0..{n_frames - 1}",
                f"check n_frames and file_number_base (now {file_number_base}: 1 for HyperNeRF, "
                "0 for Neu3D)",
            )  # fmt: skip
        if f in by_frame:
            raise AnnotationError(coco_path, f"images {by_frame[f]!r} and {fname!r} both map "
                                  f"to frame {f}", "keep one image per frame")  # fmt: skip
        by_frame[f] = fname
        frames[im["id"]] = f
        sizes[im["id"]] = (im["width"], im["height"])
    if image_size is None:
        distinct = set(sizes.values())
        if len(distinct) > 1:
            raise AnnotationError(coco_path, f"images of different sizes {sorted(distinct)}",
                                  "pass the run's image_size to rasterise them at")  # fmt: skip
        target = distinct.pop() if distinct else None
    else:
        target = (int(image_size[0]), int(image_size[1]))

    masks: dict[str, dict[int, np.ndarray]] = {}
    for j, a in enumerate(coco["annotations"]):
        where = f"annotations[{j}]"
        if not isinstance(a, dict) or not all(k in a for k in ("image_id", "category_id",
                                                               "segmentation")):
            raise AnnotationError(coco_path, f"{where} needs 'image_id', 'category_id' and "
                                  "'segmentation'", "fix the COCO export")  # fmt: skip
        if a["image_id"] not in frames:
            raise AnnotationError(coco_path, f"{where}: unknown image_id {a['image_id']!r}",
                                  "fix the COCO export")  # fmt: skip
        if a["category_id"] not in names:
            raise AnnotationError(coco_path, f"{where}: unknown category_id "
                                  f"{a['category_id']!r}", "fix the COCO export")  # fmt: skip
        seg = a["segmentation"]
        if not isinstance(seg, list) or not seg:
            raise AnnotationError(coco_path, f"{where}: 'segmentation' must be a non-empty "
                                  "list of polygons (RLE is not supported)",
                                  "export polygons [[x1, y1, x2, y2, ...], ...]")  # fmt: skip
        for k, poly in enumerate(seg):
            if not (isinstance(poly, list) and all(_is_number(v) for v in poly)):
                raise AnnotationError(coco_path, f"{where}: polygon {k} is not a list of "
                                      "numbers", "write [x1, y1, x2, y2, ...]")  # fmt: skip
            if len(poly) % 2:
                raise AnnotationError(coco_path, f"{where}: polygon {k} has an odd number "
                                      f"({len(poly)}) of coordinates",
                                      "give x, y pairs")  # fmt: skip
            if len(poly) < 6:
                raise AnnotationError(coco_path, f"{where}: polygon {k} has fewer than 3 "
                                      "points", "give at least 3 x, y pairs")  # fmt: skip
        assert target is not None
        m = rasterize_polygons(seg, target, sizes[a["image_id"]])
        per = masks.setdefault(names[a["category_id"]], {})
        f = frames[a["image_id"]]
        per[f] = per[f] | m if f in per else m

    video = _read_json(video_path)
    if not isinstance(video, dict) or not video:
        raise AnnotationError(video_path, "must map objects to {query: [[start, end], ...]}",
                              'write {"object": {"query": [[s, e]]}}')  # fmt: skip
    categories = sorted(set(names.values()))
    out: list[Query] = []
    seen: set[str] = set()
    for obj, queries in video.items():
        if obj not in categories:
            raise AnnotationError(video_path, f"object {obj!r} is not a category of {coco_path}",
                                  f"use one of {categories}")  # fmt: skip
        if obj not in masks:
            raise AnnotationError(video_path, f"object {obj!r} has no mask in any image of "
                                  f"{coco_path}", "annotate it, or drop its queries")  # fmt: skip
        name, label = _resolve_object(obj, object_names, video_path, f"object {obj!r}")
        if not isinstance(queries, dict) or not queries:
            raise AnnotationError(video_path, f"object {obj!r} must map queries to frame "
                                  "ranges", 'write {"query": [[s, e]]}')  # fmt: skip
        per = masks[obj]
        evaluated = np.zeros(n_frames, dtype=bool)
        evaluated[list(per)] = True
        gt_masks = tuple(per.get(f) for f in range(n_frames))
        for q, ranges in queries.items():
            where = f"object {obj!r}"
            text = _query_text(q, video_path, where, seen)
            gt = _frame_ranges(ranges, n_frames, video_path, f"{where}, query {text!r}")
            out.append(Query(text, name, label, gt, evaluated, gt_masks, str(video_path)))
    return out


def frame_map(
    names: Sequence[str], times: Sequence[float], frame_times: Sequence[float],
    tolerance: float = 1e-6,
) -> dict[int, int] | None:
    """File number -> run frame, for mapping annotation images by name: `names` and `times` are
    the dataset's image file names and their times, `frame_times` the run's frame times. An
    image whose time is no run frame's (within `tolerance`), or whose name has no digits, is
    left out. None when one number names images at different frames (ambiguous names, e.g.
    per-camera folders numbering from 0 each)."""
    ft = np.asarray(frame_times, dtype=np.float64)
    out: dict[int, int] = {}
    for name, t in zip(names, times, strict=True):
        try:
            number = frame_number(name)
        except ValueError:
            continue
        hit = np.flatnonzero(np.abs(ft - float(t)) <= tolerance)
        if not hit.size:
            continue
        f = int(hit[0])
        if out.setdefault(number, f) != f:
            return None
    return out


def load_queries(
    path: str | Path,
    n_frames: int,
    frame_times: np.ndarray | Sequence[float] | None = None,
    object_names: Sequence[str] | None = None,
    image_size: tuple[int, int] | None = None,
    file_number_base: int = 1,
) -> list[Query]:
    """`read_4dlangsplat` for a folder, `read_queries` for a file."""
    p = Path(path)
    if p.is_dir():
        return read_4dlangsplat(p, n_frames, image_size, object_names, file_number_base)
    return read_queries(p, n_frames, frame_times, object_names)
