"""Phase 3 temporal-query evaluation (Appendix F): activation rules, Acc / tIoU / vIoU, intervals,
both annotation formats and their errors, the results files. Expected values are hand-computed
in the comments."""

from __future__ import annotations

import copy
import csv
import json
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest

from sync4d.phase3.activation import activate, from_intervals, intervals
from sync4d.phase3.evaluation.annotations import (
    AnnotationError,
    Query,
    frame_number,
    load_queries,
    rasterize_polygons,
    read_4dlangsplat,
    read_queries,
)
from sync4d.phase3.evaluation.query_metrics import (
    QueryResult,
    evaluate_query,
    frame_accuracy,
    mask_iou,
    mean_row,
    temporal_iou,
    video_iou,
    write_rows,
)


def bools(*bits: int) -> np.ndarray:
    return np.array(bits, dtype=bool)


def box(h: int, w: int, rows: slice, cols: slice) -> np.ndarray:
    m = np.zeros((h, w), dtype=bool)
    m[rows, cols] = True
    return m


# ---------------------------------------------------------------------------------------------
# Activation rules


def test_half_peak_is_strict_and_keeps_the_literal_rule_for_a_positive_peak() -> None:
    s = [0.1, 0.2, 0.6, 0.8, 0.4, 0.41, 0.39, 0.0, -0.2, 0.8]
    # peak 0.8 -> threshold 0.4; 0.4 itself is not above it; -0.2 does not shift anything.
    expect = bools(0, 0, 1, 1, 0, 1, 0, 0, 0, 1)
    np.testing.assert_array_equal(activate(s, "half-peak"), expect)
    np.testing.assert_array_equal(activate(s), expect)  # the default is the paper's rule


def test_half_peak_with_a_negative_peak_uses_the_min_shifted_scores() -> None:
    s = np.array([-0.9, -0.5, -0.2, -0.3, -0.8])
    # The literal rule s > 0.5 * (-0.2) = -0.1 activates nothing:
    assert not (s > 0.5 * s.max()).any()
    # shifted: s - min = [0, 0.4, 0.7, 0.6, 0.1], half of its peak 0.35 -> frames 1, 2, 3.
    np.testing.assert_array_equal(activate(s), bools(0, 1, 1, 1, 0))


def test_half_peak_with_a_zero_peak_is_shifted_too() -> None:
    # peak 0: s - min = [0, 1, 0.6, 0.4], threshold 0.5 -> frames 1, 2.
    np.testing.assert_array_equal(activate([-1.0, 0.0, -0.4, -0.6]), bools(0, 1, 1, 0))


@pytest.mark.parametrize("rule", ["half-peak", "mean"])
@pytest.mark.parametrize("value", [0.3, 0.0, -0.3])
def test_constant_scores_activate_every_frame(rule: str, value: float) -> None:
    np.testing.assert_array_equal(activate([value] * 5, rule), np.ones(5, dtype=bool))


def test_mean_rule_is_at_least_the_mean() -> None:
    # mean of 0..9 is 4.5 -> frames 5..9
    np.testing.assert_array_equal(activate(np.arange(10.0), "mean"), np.arange(10) >= 5)
    # mean 2, equal counts (4D LangSplat: similarity >= threshold)
    np.testing.assert_array_equal(activate([1.0, 2.0, 3.0], "mean"), bools(0, 1, 1))
    # the rule differs from half-peak: [0.1, 0.5, 0.9, 0.95]: mean 0.6125 -> frames 2, 3;
    # half-peak 0.475 -> frames 1, 2, 3
    s = [0.1, 0.5, 0.9, 0.95]
    np.testing.assert_array_equal(activate(s, "mean"), bools(0, 0, 1, 1))
    np.testing.assert_array_equal(activate(s, "half-peak"), bools(0, 1, 1, 1))


@pytest.mark.parametrize(
    "scores, rule",
    [([], "half-peak"), ([[0.1, 0.2]], "half-peak"), ([0.1, float("nan")], "mean"),
     ([0.1, float("inf")], "half-peak"), ([0.1, 0.2], "median")],
)  # fmt: skip
def test_activate_rejects_bad_input(scores: list, rule: str) -> None:
    with pytest.raises(ValueError):
        activate(scores, rule)  # type: ignore[arg-type]


# ---------------------------------------------------------------------------------------------
# Metrics

PRED = bools(1, 1, 0, 0, 1, 0, 0, 0, 1, 1)  # P = {0, 1, 4, 8, 9}
GT = bools(1, 1, 1, 0, 0, 0, 0, 0, 1, 0)  # G = {0, 1, 2, 8}


def test_frame_accuracy() -> None:
    # equal on 0, 1, 3, 5, 6, 7, 8; differ on 2, 4, 9 -> 7 / 10
    assert frame_accuracy(PRED, GT) == pytest.approx(0.7)
    assert frame_accuracy(GT, GT) == 1.0
    assert frame_accuracy(~GT, GT) == 0.0
    with pytest.raises(ValueError):
        frame_accuracy(PRED, GT[:5])
    with pytest.raises(ValueError):
        frame_accuracy([], [])


def test_temporal_iou() -> None:
    # P & G = {0, 1, 8} (3), P | G = {0, 1, 2, 4, 8, 9} (6) -> 0.5
    assert temporal_iou(PRED, GT) == pytest.approx(0.5)
    none = np.zeros(10, dtype=bool)
    assert temporal_iou(none, none) == 1.0  # 0/0: both say "never"
    assert temporal_iou(none, GT) == 0.0
    assert temporal_iou(PRED, none) == 0.0
    with pytest.raises(ValueError):
        temporal_iou([0.5, 1.0], [True, False])  # not bool


A = box(4, 4, slice(0, 2), slice(0, 2))  # top-left 2x2, 4 pixels
Bm = box(4, 4, slice(0, 2), slice(1, 3))  # rows 0-1, columns 1-2, 4 pixels


def test_mask_iou() -> None:
    # A & B: column 1 of rows 0-1 (2 pixels); A | B: 6 pixels -> 1/3
    assert mask_iou(A, Bm) == pytest.approx(1 / 3)
    assert mask_iou(A, A) == 1.0
    assert mask_iou(A, ~A) == 0.0
    empty = np.zeros((4, 4), dtype=bool)
    assert mask_iou(empty, empty) == 1.0
    assert mask_iou(empty, A) == 0.0
    with pytest.raises(ValueError):
        mask_iou(A, np.zeros((4, 5), dtype=bool))


def test_video_iou_follows_4d_langsplat() -> None:
    pred = bools(1, 1, 0, 1, 0)
    gt = bools(1, 0, 1, 1, 0)
    pm = [A, A, None, Bm, None]
    gm = [Bm, A, A, Bm, A]
    # union frames 0..3: frame 0 both active IoU(A, B) = 1/3; frame 1 predicted only -> 0;
    # frame 2 GT only -> 0; frame 3 both active IoU(B, B) = 1; frame 4 outside the union.
    # (1/3 + 0 + 0 + 1) / 4 = 1/3
    assert video_iou(pred, gt, pm, gm) == pytest.approx(1 / 3)
    # frame 2 without a GT mask is not scored: (1/3 + 0 + 1) / 3 = 4/9
    gm2 = [Bm, A, None, Bm, A]
    assert video_iou(pred, gt, pm, gm2) == pytest.approx(4 / 9)
    # no predicted mask on a frame where both are active is an empty prediction:
    # (1/3 + 0 + 0 + 0) / 4 = 1/12
    assert video_iou(pred, gt, [A, A, None, None, None], gm) == pytest.approx(1 / 12)
    # no GT mask at all: not measurable
    assert video_iou(pred, gt, pm, [None] * 5) is None
    # nothing active on either side: 4D LangSplat's 0 by default
    none = np.zeros(5, dtype=bool)
    assert video_iou(none, none, pm, gm) == 0.0
    assert video_iou(none, none, pm, gm, empty_union=1.0) == 1.0
    with pytest.raises(ValueError):
        video_iou(pred, gt, pm[:4], gm)


# ---------------------------------------------------------------------------------------------
# Intervals


def test_intervals_and_back() -> None:
    a = bools(0, 1, 1, 0, 0, 1, 1, 1, 0, 1)
    assert intervals(a) == [(1, 2), (5, 7), (9, 9)]
    np.testing.assert_array_equal(from_intervals([(1, 2), (5, 7), (9, 9)], 10), a)
    assert intervals(np.ones(10, dtype=bool)) == [(0, 9)]
    assert intervals(np.zeros(10, dtype=bool)) == []
    assert intervals(bools(1)) == [(0, 0)]
    # overlapping ranges are a union
    np.testing.assert_array_equal(from_intervals([[0, 3], [2, 4]], 6), bools(1, 1, 1, 1, 1, 0))
    rng = np.random.default_rng(0)
    for _ in range(200):
        x = rng.random(int(rng.integers(1, 30))) < rng.random()
        np.testing.assert_array_equal(from_intervals(intervals(x), x.size), x)


@pytest.mark.parametrize("ranges", [[[3, 2]], [[-1, 2]], [[5, 10]], [[1, 2, 3]]])
def test_from_intervals_rejects_bad_ranges(ranges: list) -> None:
    with pytest.raises(ValueError):
        from_intervals(ranges, 10)


# ---------------------------------------------------------------------------------------------
# evaluate_query


def _query(gt: np.ndarray, evaluated: np.ndarray | None = None, masks=None,
           obj: str | None = "glass", label: int | None = 1) -> Query:  # fmt: skip
    ev = np.ones(gt.size, dtype=bool) if evaluated is None else evaluated
    return Query("glass being filled", obj, label, gt, ev, masks, "test")


def test_evaluate_query_scores_the_paper_rule() -> None:
    q = _query(from_intervals([[3, 6]], 10))
    s = [0.0, 0.1, 0.3, 0.6, 0.9, 1.0, 0.45, 0.2, 0.55, 0.1]
    # half-peak: > 0.5 -> frames 3, 4, 5, 8; GT 3..6.
    # Acc: differ on 6 and 8 -> 8/10; tIoU: {3, 4, 5} / {3, 4, 5, 6, 8} = 3/5
    r = evaluate_query(q, s, "half-peak")
    assert (r.acc, r.tiou, r.viou) == (pytest.approx(0.8), pytest.approx(0.6), None)
    assert r.pred_intervals == [(3, 5), (8, 8)]
    assert r.gt_intervals == [(3, 6)]
    assert (r.query, r.object, r.gt_object, r.rule, r.n_frames) == (
        "glass being filled", "glass (#1)", "glass (#1)", "half-peak", 10)
    assert r.object_correct is None
    # mean rule: mean 0.42 -> frames 3, 4, 5, 6, 8: Acc 9/10, tIoU 4/5
    r = evaluate_query(q, s, "mean")
    assert (r.acc, r.tiou) == (pytest.approx(0.9), pytest.approx(0.8))


def test_evaluate_query_scores_only_the_evaluated_frames() -> None:
    # 4D LangSplat: only frames annotated with the object's mask are scored, and the mean
    # threshold is the mean over those. Evaluated: even frames with scores 0, 1, 2, 3, 4
    # (mean 2 -> frames 4, 6, 8 active); over all frames the mean would be 52 (none active).
    s = [0, 100, 1, 100, 2, 100, 3, 100, 4, 100]
    ev = np.arange(10) % 2 == 0
    q = _query(from_intervals([[4, 9]], 10), ev)
    r = evaluate_query(q, s, "mean")
    assert (r.acc, r.tiou, r.n_frames) == (1.0, 1.0, 5)
    assert r.pred_intervals == [(4, 4), (6, 6), (8, 8)]
    assert r.gt_intervals == [(4, 4), (6, 6), (8, 8)]


def test_evaluate_query_with_masks() -> None:
    gm = (Bm, A, A, Bm, A)
    q = _query(bools(1, 0, 1, 1, 0), masks=gm)
    # half-peak: > 0.5 -> frames 0, 1, 3, as in test_video_iou_follows_4d_langsplat: 1/3
    r = evaluate_query(q, [0.9, 0.8, 0.1, 1.0, 0.2], pred_masks=[A, A, None, Bm, None])
    assert r.viou == pytest.approx(1 / 3)
    assert r.acc == pytest.approx(0.6)  # differ on 1, 2
    assert evaluate_query(q, [0.9, 0.8, 0.1, 1.0, 0.2]).viou is None  # no predicted masks


def test_evaluate_query_with_the_wrong_object_scores_active_frames_as_wrong() -> None:
    q = _query(bools(0, 1, 1, 0))
    s = [0.0, 1.0, 1.0, 0.0]  # active exactly on the GT frames 1, 2
    r = evaluate_query(q, s, object=1)
    assert (r.acc, r.tiou, r.object_correct) == (1.0, 1.0, True)
    assert evaluate_query(q, s, object="glass").object_correct is True
    # another object: frames 1, 2 are wrong answers, frames 0, 3 right -> Acc 1/2, tIoU 0
    for other in (2, "cup"):
        r = evaluate_query(q, s, object=other)
        assert (r.acc, r.tiou, r.object_correct) == (0.5, 0.0, False)
        assert r.pred_intervals == [(1, 2)]
    assert evaluate_query(q, s, object=2).object == "#2"
    with pytest.raises(ValueError):
        evaluate_query(q, s[:3])


# ---------------------------------------------------------------------------------------------
# Results files


def _rows() -> list[QueryResult]:
    r1 = QueryResult("a", "ball", "ball", "half-peak", 0.8, 0.6, 0.5, [(3, 5)], [(3, 6)], 10, True)
    r2 = QueryResult("b, with comma", "#2", "cup", "half-peak", 0.4, 0.2, None, [],
                     [(0, 1), (4, 4)], 10, None)  # fmt: skip
    return [r1, r2]


def test_mean_row() -> None:
    m = mean_row(_rows())
    # acc (0.8 + 0.4) / 2 = 0.6; tIoU (0.6 + 0.2) / 2 = 0.4; vIoU only row 1: 0.5
    assert m["acc"] == pytest.approx(0.6) and m["tiou"] == pytest.approx(0.4)
    assert (m["viou"], m["n_queries"], m["n_viou"]) == (0.5, 2, 1)
    with pytest.raises(ValueError):
        mean_row([])


def test_write_rows(tmp_path: Path) -> None:
    csv_path, json_path = tmp_path / "out" / "queries.csv", tmp_path / "out" / "queries.json"
    csv_path.parent.mkdir()
    csv_path.write_text("old")
    write_rows(_rows(), csv_path, json_path)
    with open(csv_path, newline="") as f:
        table = list(csv.DictReader(f))
    assert [r["query"] for r in table] == ["a", "b, with comma", "mean"]
    assert table[0]["viou"] == "0.5" and table[1]["viou"] == ""
    assert json.loads(table[1]["gt_intervals"]) == [[0, 1], [4, 4]]
    assert float(table[2]["acc"]) == pytest.approx(0.6)
    assert float(table[2]["tiou"]) == pytest.approx(0.4)
    assert table[2]["viou"] == "0.5" and table[2]["object"] == ""
    doc = json.loads(json_path.read_text())
    assert [q["query"] for q in doc["queries"]] == ["a", "b, with comma"]
    assert doc["queries"][1]["viou"] is None
    assert doc["queries"][0]["pred_intervals"] == [[3, 5]]
    assert doc["mean"]["acc"] == pytest.approx(0.6) and doc["mean"]["n_queries"] == 2
    assert sorted(p.name for p in csv_path.parent.iterdir()) == ["queries.csv", "queries.json"]


# ---------------------------------------------------------------------------------------------
# Polygons and file names


def test_rasterize_polygons() -> None:
    # a square with corners (1, 1) and (3, 3): boundary pixels are inside -> rows/cols 1..3
    np.testing.assert_array_equal(rasterize_polygons([[1, 1, 3, 1, 3, 3, 1, 3]], (4, 4)),
                                  box(4, 4, slice(1, 4), slice(1, 4)))  # fmt: skip
    # the same square drawn on an 8x8 annotation (corners 2, 6) scaled by 0.5 to 4x4
    np.testing.assert_array_equal(
        rasterize_polygons([[2, 2, 6, 2, 6, 6, 2, 6]], (4, 4), (8, 8)),
        box(4, 4, slice(1, 4), slice(1, 4)),
    )
    # a triangle (0,0), (3,0), (0,3): pixels with x + y <= 3 (4 + 3 + 2 + 1 = 10 of 16)
    tri = rasterize_polygons([[0, 0, 3, 0, 0, 3]], (4, 4))
    yy, xx = np.mgrid[:4, :4]
    np.testing.assert_array_equal(tri, xx + yy <= 3)
    # fractional vertices are truncated (OpenCV's int32 cast in 4D LangSplat): (0.6, 0.6) to
    # (2.7, 2.7) -> (0, 0) to (2, 2) -> rows/cols 0..2 (rounding would give 1..3)
    np.testing.assert_array_equal(
        rasterize_polygons([[0.6, 0.6, 2.7, 0.6, 2.7, 2.7, 0.6, 2.7]], (4, 4)),
        box(4, 4, slice(0, 3), slice(0, 3)),
    )
    # two polygons are a union; non-square: width 5, height 3 -> shape [3, 5]
    two = rasterize_polygons([[0, 0, 1, 0, 1, 1, 0, 1], [3, 1, 4, 1, 4, 2, 3, 2]], (5, 3))
    assert two.shape == (3, 5)
    np.testing.assert_array_equal(np.argwhere(two),
                                  [[0, 0], [0, 1], [1, 0], [1, 1], [1, 3], [1, 4], [2, 3],
                                   [2, 4]])  # fmt: skip
    with pytest.raises(ValueError):
        rasterize_polygons([[0, 0, 1, 0, 1]], (4, 4))


def test_frame_number() -> None:
    assert frame_number("000123.png") == 123
    assert frame_number("frame_00123.jpg") == 123
    assert frame_number("train/000045_png.rf.9f1c2e.jpg") == 45  # Roboflow's export names
    with pytest.raises(ValueError):
        frame_number("image.png")


# ---------------------------------------------------------------------------------------------
# 4D LangSplat's format

# Images are 8x8; the run is 4x4 (scale 0.5). HyperNeRF numbering: file 000003 is frame 2.
COCO = {
    "categories": [{"id": 0, "name": "cups-objects", "supercategory": "none"},
                   {"id": 1, "name": "glass", "supercategory": "cups-objects"},
                   {"id": 2, "name": "spoon", "supercategory": "cups-objects"}],
    "images": [{"id": 0, "file_name": "000003_png.rf.abc123.jpg", "width": 8, "height": 8},
               {"id": 1, "file_name": "000005_png.rf.77d.jpg", "width": 8, "height": 8},
               {"id": 2, "file_name": "000006_png.rf.e0.jpg", "width": 8, "height": 8}],
    "annotations": [
        # frame 2, glass: square (2,2)-(6,6) -> 4x4 rows/cols 1..3
        {"id": 0, "image_id": 0, "category_id": 1, "bbox": [2, 2, 4, 4],
         "segmentation": [[2, 2, 6, 2, 6, 6, 2, 6]]},
        # frame 4, glass in two annotations: (0,0)-(2,2) -> rows/cols 0..1, and
        # (4,4)-(8,8) -> rows/cols 2..3 (4 is outside the 4x4 image)
        {"id": 1, "image_id": 1, "category_id": 1, "bbox": [0, 0, 2, 2],
         "segmentation": [[0, 0, 2, 0, 2, 2, 0, 2]]},
        {"id": 2, "image_id": 1, "category_id": 1, "bbox": [4, 4, 4, 4],
         "segmentation": [[4, 4, 8, 4, 8, 8, 4, 8]]},
        # frame 5, spoon: the whole image
        {"id": 3, "image_id": 2, "category_id": 2, "bbox": [0, 0, 8, 8],
         "segmentation": [[0, 0, 8, 0, 8, 8, 0, 8]]},
    ],
}  # fmt: skip
VIDEO = {"glass": {"glass being filled": [[2, 3]], "empty glass": [[4, 9]]},
         "spoon": {"spoon in motion": [[0, 9]]}}  # fmt: skip


def _write_4dls(root: Path, coco=COCO, video=VIDEO) -> Path:
    """<root>/annotations/{train/_annotations.coco.json, video_annotations.json}; returns the
    annotations folder. A str is written verbatim."""
    ann = root / "annotations"
    (ann / "train").mkdir(parents=True)
    for path, doc in ((ann / "train" / "_annotations.coco.json", coco),
                      (ann / "video_annotations.json", video)):  # fmt: skip
        path.write_text(doc if isinstance(doc, str) else json.dumps(doc))
    return ann


def test_read_4dlangsplat(tmp_path: Path) -> None:
    ann = _write_4dls(tmp_path)
    qs = read_4dlangsplat(ann, 10, image_size=(4, 4), object_names=["background", "glass",
                                                                    "spoon"])  # fmt: skip
    assert [q.text for q in qs] == ["glass being filled", "empty glass", "spoon in motion"]
    assert [(q.object, q.label) for q in qs] == [("glass", 1), ("glass", 1), ("spoon", 2)]
    filled, empty, spoon = qs
    np.testing.assert_array_equal(filled.gt_active, np.isin(np.arange(10), [2, 3]))
    np.testing.assert_array_equal(empty.gt_active, np.arange(10) >= 4)
    np.testing.assert_array_equal(spoon.gt_active, np.ones(10, dtype=bool))
    # scored on the frames with a mask of the object only
    np.testing.assert_array_equal(filled.evaluated, np.isin(np.arange(10), [2, 4]))
    np.testing.assert_array_equal(spoon.evaluated, np.arange(10) == 5)
    assert filled.gt_masks is not None and spoon.gt_masks is not None
    assert [f for f, m in enumerate(filled.gt_masks) if m is not None] == [2, 4]
    np.testing.assert_array_equal(filled.gt_masks[2], box(4, 4, slice(1, 4), slice(1, 4)))
    np.testing.assert_array_equal(
        filled.gt_masks[4],
        box(4, 4, slice(0, 2), slice(0, 2)) | box(4, 4, slice(2, 4), slice(2, 4)),
    )
    np.testing.assert_array_equal(spoon.gt_masks[5], np.ones((4, 4), dtype=bool))
    assert filled.source.endswith("video_annotations.json") and filled.n_frames == 10
    # the scene folder works too, and without a run size the masks stay 8x8:
    # square (2,2)-(6,6) -> rows/cols 2..6
    qs8 = read_4dlangsplat(tmp_path, 10)
    assert qs8[0].label is None and qs8[0].gt_masks is not None
    np.testing.assert_array_equal(qs8[0].gt_masks[2], box(8, 8, slice(2, 7), slice(2, 7)))
    # Neu3D numbering (file 000003 is frame 3)
    shifted = read_4dlangsplat(ann, 10, file_number_base=0)
    np.testing.assert_array_equal(shifted[0].evaluated, np.isin(np.arange(10), [3, 5]))
    assert [q.text for q in load_queries(ann, 10)] == [q.text for q in qs]


def test_4dlangsplat_end_to_end_metrics(tmp_path: Path) -> None:
    (filled,) = [q for q in read_4dlangsplat(_write_4dls(tmp_path), 10, (4, 4))
                 if q.text == "glass being filled"]  # fmt: skip
    # evaluated frames 2 (GT active) and 4 (GT inactive); the scores elsewhere do not count.
    s = np.full(10, 5.0)
    s[2], s[4] = 0.9, 0.2  # half-peak over {0.9, 0.2}: frame 2 only -> Acc 1, tIoU 1
    pm: list[np.ndarray | None] = [None] * 10
    pm[2] = box(4, 4, slice(1, 4), slice(1, 3))  # 6 of the 9 GT pixels -> IoU 6/9
    r = evaluate_query(filled, s, pred_masks=pm)
    assert (r.acc, r.tiou, r.n_frames) == (1.0, 1.0, 2)
    assert r.viou == pytest.approx(2 / 3)


def _mutate(doc: dict, fn: Callable[[dict], None]) -> dict:
    out = copy.deepcopy(doc)
    fn(out)
    return out


def _set(path: list, value) -> Callable[[dict], None]:
    def fn(d: dict) -> None:
        for k in path[:-1]:
            d = d[k]
        d[path[-1]] = value
    return fn


BAD_4DLS = {
    "coco not JSON": ("coco", "{images: [", "not JSON"),
    "coco missing key": ("coco", _mutate(COCO, lambda d: d.pop("annotations")),
                         "missing key 'annotations'"),
    "no digits": ("coco", _mutate(COCO, _set(["images", 1, "file_name"], "image.png")),
                  "no digits"),
    "frame too late": ("coco", _mutate(COCO, _set(["images", 1, "file_name"], "000011.png")),
                       "outside the run's frames"),
    "same frame twice": ("coco", _mutate(COCO, _set(["images", 1, "file_name"], "000003.png")),
                         "both map to frame 2"),
    "odd polygon": ("coco", _mutate(COCO, _set(["annotations", 0, "segmentation"],
                                               [[2, 2, 6, 2, 6]])), "odd number"),
    "two points": ("coco", _mutate(COCO, _set(["annotations", 0, "segmentation"],
                                              [[2, 2, 6, 2]])), "fewer than 3 points"),
    "RLE": ("coco", _mutate(COCO, _set(["annotations", 0, "segmentation"],
                                       {"counts": [1, 2], "size": [8, 8]})), "RLE"),
    "unknown category id": ("coco", _mutate(COCO, _set(["annotations", 0, "category_id"], 9)),
                            "unknown category_id 9"),
    "unknown image id": ("coco", _mutate(COCO, _set(["annotations", 0, "image_id"], 9)),
                         "unknown image_id 9"),
    "video not JSON": ("video", "not json", "not JSON"),
    "object not a category": ("video", {"mug": {"mug being filled": [[0, 1]]}},
                              "'mug' is not a category"),
    "object without masks": ("video", {"cups-objects": {"cups moving": [[0, 1]]}},
                             "has no mask"),
    "range out of run": ("video", {"glass": {"glass being filled": [[2, 10]]}},
                         "outside the run's frames 0..9"),
    "reversed range": ("video", {"glass": {"glass being filled": [[3, 2]]}}, "reversed"),
    "empty query": ("video", {"glass": {"  ": [[0, 1]]}}, "empty query string"),
    "query twice": ("video", {"glass": {"moving": [[0, 1]]}, "spoon": {"moving": [[0, 1]]}},
                    "appears twice"),
    "ranges not a list": ("video", {"glass": {"glass being filled": "2-3"}}, "must be a list"),
}  # fmt: skip


@pytest.mark.parametrize("case", sorted(BAD_4DLS))
def test_4dlangsplat_errors_name_the_file(tmp_path: Path, case: str) -> None:
    which, doc, problem = BAD_4DLS[case]
    kw = {"coco": doc} if which == "coco" else {"video": doc}
    ann = _write_4dls(tmp_path, **kw)
    name = "_annotations.coco.json" if which == "coco" else "video_annotations.json"
    with pytest.raises(AnnotationError) as e:
        read_4dlangsplat(ann, 10, image_size=(4, 4))
    assert e.value.path.name == name
    assert str(ann) in str(e.value) and name in str(e.value)
    assert problem in str(e.value)
    assert "; " in str(e.value)  # and says what to do


def test_4dlangsplat_unknown_object_and_missing_files(tmp_path: Path) -> None:
    ann = _write_4dls(tmp_path)
    with pytest.raises(AnnotationError, match=r"video_annotations.json: .*unknown object 'glass'"
                       r".*\['ball', 'spoon'\]"):  # fmt: skip
        read_4dlangsplat(ann, 10, object_names=["ball", "spoon"])
    (ann / "video_annotations.json").unlink()
    with pytest.raises(AnnotationError, match="video_annotations.json: file not found"):
        read_4dlangsplat(ann, 10)
    with pytest.raises(AnnotationError, match="not a folder"):
        read_4dlangsplat(tmp_path / "nowhere", 10)


def test_4dlangsplat_mixed_image_sizes_need_a_run_size(tmp_path: Path) -> None:
    coco = _mutate(COCO, _set(["images", 2, "width"], 16))
    ann = _write_4dls(tmp_path, coco=coco)
    with pytest.raises(AnnotationError, match="different sizes.*pass the run's image_size"):
        read_4dlangsplat(ann, 10)
    spoon = read_4dlangsplat(ann, 10, image_size=(4, 4))[2]
    assert spoon.gt_masks is not None
    # spoon image 16x8: the full-width polygon (0..8 of 16) covers the left half -> cols 0..2
    np.testing.assert_array_equal(spoon.gt_masks[5], box(4, 4, slice(0, 4), slice(0, 3)))


# ---------------------------------------------------------------------------------------------
# Our own format

OURS = {
    "version": 1,
    "scene": "bouncingballs",
    "queries": [
        {"query": "the red ball while it is falling", "object": "red ball",
         "frames": [[0, 2], [7, 9]]},
        {"query": "the blue ball at rest", "object": 1, "times": [[0.1, 0.3]]},
    ],
}  # fmt: skip
NAMES = ["red ball", "blue ball"]
# linspace(0, 1, 11)[:10]: frame 3's time is 0.30000000000000004, inside [0.1, 0.3] within 1e-9
TIMES = np.linspace(0.0, 1.0, 11)[:10]


def _write_ours(tmp_path: Path, doc) -> Path:
    p = tmp_path / "queries.json"
    p.write_text(doc if isinstance(doc, str) else json.dumps(doc))
    return p


def test_read_queries(tmp_path: Path) -> None:
    p = _write_ours(tmp_path, OURS)
    assert TIMES[3] > 0.3  # the case the tolerance is for
    falling, rest = read_queries(p, 10, TIMES, NAMES)
    assert (falling.text, falling.object, falling.label) == (
        "the red ball while it is falling", "red ball", 0)
    np.testing.assert_array_equal(falling.gt_active, bools(1, 1, 1, 0, 0, 0, 0, 1, 1, 1))
    assert (rest.object, rest.label) == ("blue ball", 1)
    # times 0, 0.1, ..., 0.9: [0.1, 0.3] -> frames 1, 2, 3
    np.testing.assert_array_equal(rest.gt_active, np.isin(np.arange(10), [1, 2, 3]))
    assert falling.evaluated.all() and falling.gt_masks is None
    assert falling.source == str(p)
    # without the run's names: names and ids stay as written
    falling, rest = read_queries(p, 10, TIMES)
    assert (falling.object, falling.label, rest.object, rest.label) == ("red ball", None,
                                                                        None, 1)  # fmt: skip
    assert [q.text for q in load_queries(p, 10, TIMES)] == [falling.text, rest.text]
    # end to end: half-peak over ramps
    r = evaluate_query(rest, [0, 1, 1, 1, 0.5, 0, 0, 0, 0, 0])  # half-peak: > 0.5 -> 1, 2, 3
    assert (r.acc, r.tiou, r.gt_intervals) == (1.0, 1.0, [(1, 3)])


def _q(**entry) -> dict:
    base = {"query": "the red ball while it is falling", "object": "red ball",
            "frames": [[0, 2]]}  # fmt: skip
    base.update(entry)
    return {"queries": [{k: v for k, v in base.items() if v is not None}]}


BAD_OURS = {
    "not JSON": ('{"queries": [', "not JSON"),
    "not an object": ("[1, 2]", "missing key 'queries'"),
    "no queries key": ({"query": "x"}, "missing key 'queries'"),
    "empty queries": ({"queries": []}, "non-empty list"),
    "missing object": (_q(object=None), "missing key 'object'"),
    "missing query": (_q(query=None), "missing key 'query'"),
    "empty query": (_q(query="   "), "empty query string"),
    "unknown key": (_q(frame=[[0, 2]]), "unknown keys ['frame']"),
    "unknown top key": ({**_q(), "quries": []}, "unknown top-level keys"),
    "version": ({**_q(), "version": 2}, "unsupported version 2"),
    "unknown object": (_q(object="green ball"), "unknown object 'green ball'"),
    "label out of range": (_q(object=2), "object label 2 out of range"),
    "bool object": (_q(object=True), "must be a name or a label id"),
    "frames past the end": (_q(frames=[[8, 10]]), "outside the run's frames 0..9"),
    "negative frame": (_q(frames=[[-1, 2]]), "outside the run's frames"),
    "reversed frames": (_q(frames=[[5, 3]]), "[5, 3] is reversed"),
    "float frames": (_q(frames=[[0.5, 3]]), "not [start, end] of integers"),
    "both frames and times": (_q(times=[[0.0, 0.2]]), "exactly one of 'frames' and 'times'"),
    "neither": (_q(frames=None), "exactly one of 'frames' and 'times'"),
    "reversed times": (_q(frames=None, times=[[0.5, 0.2]]), "is reversed"),
    "times outside": (_q(frames=None, times=[[0.5, 1.2]]), "outside [0, 1]"),
    "times between frames": (_q(frames=None, times=[[0.31, 0.39]]), "contains no frame time"),
    "duplicate": ({"queries": _q()["queries"] * 2}, "appears twice"),
}  # fmt: skip


@pytest.mark.parametrize("case", sorted(BAD_OURS))
def test_query_file_errors_name_the_file(tmp_path: Path, case: str) -> None:
    doc, problem = BAD_OURS[case]
    p = _write_ours(tmp_path, doc)
    with pytest.raises(AnnotationError) as e:
        read_queries(p, 10, TIMES, NAMES)
    assert e.value.path == p and str(e.value).startswith(f"{p}: ")
    assert problem in str(e.value)
    assert "; " in str(e.value)  # and says what to do


def test_times_need_frame_times(tmp_path: Path) -> None:
    p = _write_ours(tmp_path, OURS)
    with pytest.raises(AnnotationError, match="no frame times were given; pass the run's"):
        read_queries(p, 10)
    with pytest.raises(AnnotationError, match="file not found"):
        read_queries(tmp_path / "missing.json", 10)
    with pytest.raises(ValueError):
        read_queries(p, 10, TIMES[:5])
