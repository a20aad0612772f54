"""The SigLIP-ONNX encoder round trip: a tiny randomly initialised SiglipModel and an offline
tokenizer are exported with `export_siglip`, loaded with `SiglipOnnxEncoder`, and its embeddings
compared with the torch model's on the same inputs; preprocessing against transformers' SigLIP
image processor and tokenizer; every bad directory gets one EncoderError naming its file."""

from __future__ import annotations

import io
import json
import shutil
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
import torch
import torch.nn.functional as F
import transformers  # the test extra: make setup installs it with onnx and sentencepiece

from sync4d.cli import main
from sync4d.phase3.encoders.encoder import ENCODER_ENV, EncoderError, load_encoder
from sync4d.phase3.encoders.siglip import (
    MANIFEST,
    SiglipOnnxEncoder,
    export_pretrained,
    export_siglip,
    file_sha256,
)

S = 32  # image size (px)
L = 16  # text length (tokens)
MEAN = [0.48, 0.46, 0.41]
STD = [0.27, 0.26, 0.28]
SPECIAL = ["<pad>", "</s>", "<unk>"]
WORDS = ["a", "photo", "of", "the", "red", "blue", "cube", "sphere", "cat", "dog", "moves", "left",
         "right", "and", "two", "dogs", "!", ","]  # fmt: skip
TEXTS = ["a photo of a cat", "The RED cube moves left!", "two dogs and a blue sphere",
         "zebra quantum", "a " * 30 + "cat"]  # fmt: skip


@pytest.fixture(scope="module", autouse=True)
def _quiet_transformers():
    """SiglipConfig checks CLIP's token ids against a default text config: quiet that log."""
    level = transformers.logging.get_verbosity()
    transformers.logging.set_verbosity_error()
    yield
    transformers.logging.set_verbosity(level)


def _tiny_model(seed: int, hidden: int = 32) -> torch.nn.Module:
    """A randomly initialised SigLIP: 2 layers, 2 heads, `hidden` wide, S px, L tokens."""
    from transformers import SiglipConfig, SiglipModel

    torch.manual_seed(seed)
    layers = dict(hidden_size=hidden, intermediate_size=2 * hidden, num_hidden_layers=2,
                  num_attention_heads=2)  # fmt: skip
    cfg = SiglipConfig(
        text_config=dict(vocab_size=64, max_position_embeddings=L, pad_token_id=0,
                         bos_token_id=1, eos_token_id=1, **layers),
        vision_config=dict(image_size=S, patch_size=8, **layers),
    )  # fmt: skip
    return SiglipModel(cfg).eval()


def _tiny_tokenizer():
    """A word-level tokenizer over WORDS (lower case, "</s>" appended), as a HF fast one."""
    from tokenizers import Tokenizer, models, normalizers, pre_tokenizers, processors
    from transformers import PreTrainedTokenizerFast

    vocab = {t: i for i, t in enumerate(SPECIAL + WORDS)}
    tk = Tokenizer(models.WordLevel(vocab, unk_token="<unk>"))
    tk.normalizer = normalizers.Lowercase()
    tk.pre_tokenizer = pre_tokenizers.Whitespace()
    tk.post_processor = processors.TemplateProcessing(single="$A </s>",
                                                      special_tokens=[("</s>", 1)])  # fmt: skip
    return PreTrainedTokenizerFast(tokenizer_object=tk, pad_token="<pad>", eos_token="</s>",
                                   unk_token="<unk>", model_max_length=L)  # fmt: skip


def _export(model, tokenizer, out: Path) -> dict:
    return export_siglip(model, tokenizer, out, image_size=S, mean=MEAN, std=STD, max_length=L,
                         resample="bicubic", name="tiny-siglip")  # fmt: skip


@pytest.fixture(scope="module")
def exported(tmp_path_factory: pytest.TempPathFactory) -> SimpleNamespace:
    """The tiny SigLIP exported (D = 32), and a second one of D = 16 for mismatches."""
    root = tmp_path_factory.mktemp("siglip")
    model, tok = _tiny_model(0), _tiny_tokenizer()
    manifest = _export(model, tok, root / "enc")
    _export(_tiny_model(1, hidden=16), tok, root / "enc16")
    return SimpleNamespace(dir=root / "enc", dir16=root / "enc16", model=model, tok=tok,
                           manifest=manifest)  # fmt: skip


def _pil_processor(**kwargs):
    """transformers' SigLIP image processor on the PIL backend (before 5.x split the backends,
    the plain SiglipImageProcessor was the PIL one)."""
    try:
        from transformers import SiglipImageProcessorPil as cls
    except ImportError:
        from transformers import SiglipImageProcessor as cls
    return cls(**kwargs)


def _unit(x: torch.Tensor) -> np.ndarray:
    x = x.double()
    return (x / x.norm(dim=-1, keepdim=True)).numpy()


def _images(rng: np.random.Generator, shapes: list[tuple[int, int]]) -> list[np.ndarray]:
    """Smooth random RGB images in [0, 1] (bilinear upsampling of 6 x 6 noise)."""
    out = []
    for h, w in shapes:
        base = torch.from_numpy(rng.random((1, 3, 6, 6)).astype(np.float32))
        img = F.interpolate(base, size=(h, w), mode="bilinear", align_corners=False)
        out.append(img[0].permute(1, 2, 0).numpy())
    return out


def test_images_round_trip(exported: SimpleNamespace) -> None:
    enc = SiglipOnnxEncoder(exported.dir, threads=1, batch_size=4)  # 9 images: 3 runs
    rng = np.random.default_rng(1)
    imgs = [rng.random((S, S, 3)).astype(np.float32) for _ in range(9)]
    px = np.stack([((im - MEAN) / STD).transpose(2, 0, 1) for im in imgs]).astype(np.float32)
    np.testing.assert_allclose(enc.preprocess(imgs), px, atol=1e-6)
    with torch.no_grad():
        ref = _unit(exported.model.get_image_features(pixel_values=torch.from_numpy(px))
                    .pooler_output)  # fmt: skip
    got = enc.encode_images(imgs)
    assert got.dtype == np.float32 and got.shape == (9, 32) == (9, enc.dim)
    np.testing.assert_allclose(np.linalg.norm(got, axis=1), 1.0, atol=1e-6)
    assert np.abs(ref[0] - ref[1]).max() > 1e-2  # the images are told apart
    err = float(np.abs(got - ref).max())
    print(f"image embeddings: max |onnx - torch| = {err:.2e}")
    assert err < 1e-4


def test_images_of_any_size(exported: SimpleNamespace) -> None:
    enc = SiglipOnnxEncoder(exported.dir, threads=1)
    shapes = [(20, 70), (50, 40), (S, S), (7, 9), (200, 150)]
    imgs = _images(np.random.default_rng(2), shapes)
    px = []
    for im in imgs:
        x = torch.from_numpy(im).permute(2, 0, 1)[None]
        if x.shape[-2:] != (S, S):
            x = F.interpolate(x, size=(S, S), mode="bicubic", antialias=True, align_corners=False)
        x = x[0].clamp(0, 1).numpy()
        px.append((x - np.reshape(MEAN, (3, 1, 1))) / np.reshape(STD, (3, 1, 1)))
    px = np.stack(px).astype(np.float32)
    np.testing.assert_allclose(enc.preprocess(imgs), px, atol=1e-5)
    with torch.no_grad():
        ref = _unit(exported.model.get_image_features(pixel_values=torch.from_numpy(px))
                    .pooler_output)  # fmt: skip
    got = enc.encode_images(imgs)
    assert got.shape == (len(shapes), 32)
    err = float(np.abs(got - ref).max())
    print(f"resized image embeddings: max |onnx - torch| = {err:.2e}")
    assert err < 1e-4


def test_preprocessing_matches_siglip_image_processor(exported: SimpleNamespace) -> None:
    """Against transformers' SigLIP processor (PIL backend, bicubic) on the 8-bit image: equal
    up to the 8-bit rounding (2/255 after std 0.5); a bilinear resize is 0.04-0.08 off."""
    from PIL import Image

    enc = SiglipOnnxEncoder(exported.dir, threads=1)
    proc = _pil_processor(size={"height": S, "width": S}, resample=3, image_mean=MEAN,
                          image_std=STD)  # fmt: skip
    shapes = [(50, 40), (20, 70), (200, 150), (17, 23), (S, S)]
    for img in _images(np.random.default_rng(3), shapes):
        u = np.round(img * 255).astype(np.uint8)
        ref = proc(images=Image.fromarray(u), return_tensors="np")["pixel_values"][0]
        mine = enc.preprocess([u.astype(np.float32) / 255])[0]
        assert np.abs(mine - ref).max() < 0.012 * 0.5 / min(STD), img.shape


def test_texts_round_trip(exported: SimpleNamespace) -> None:
    enc = SiglipOnnxEncoder(exported.dir, threads=1, batch_size=2)
    ref_ids = exported.tok(TEXTS, padding="max_length", truncation=True, max_length=L,
                           return_tensors="np")["input_ids"]  # fmt: skip
    ids = enc.tokenize(TEXTS)
    assert ids.dtype == np.int64 and ids.shape == (len(TEXTS), L)
    np.testing.assert_array_equal(ids, ref_ids)
    assert ids[0, 5] == 1 and (ids[0, 6:] == 0).all()  # "</s>", then "<pad>" to L
    assert ids[4, -1] == 1  # truncated: the end token kept
    with torch.no_grad():
        ref = _unit(exported.model.get_text_features(input_ids=torch.from_numpy(ref_ids))
                    .pooler_output)  # fmt: skip
    got = enc.encode_texts(TEXTS)
    assert got.dtype == np.float32 and got.shape == (len(TEXTS), enc.dim)
    assert np.abs(ref[0] - ref[2]).max() > 1e-2
    err = float(np.abs(got - ref).max())
    print(f"text embeddings: max |onnx - torch| = {err:.2e}")
    assert err < 1e-4


def test_manifest_and_fingerprint(exported: SimpleNamespace, tmp_path: Path) -> None:
    m = json.loads((exported.dir / MANIFEST).read_text())
    assert m == exported.manifest
    assert (m["kind"], m["dim"], m["image_size"], m["max_length"], m["pad_id"]) == (
        "siglip", 32, S, L, 0)  # fmt: skip
    assert m["mean"] == MEAN and m["std"] == STD and m["resize"]["resample"] == "bicubic"
    for f, digest in m["files"].items():
        assert file_sha256(exported.dir / f) == digest
    a = SiglipOnnxEncoder(exported.dir)
    shutil.copytree(exported.dir, tmp_path / "copy")
    b = SiglipOnnxEncoder(tmp_path / "copy")
    assert a.fingerprint == b.fingerprint and len(a.fingerprint) == 64
    assert SiglipOnnxEncoder(exported.dir16).fingerprint != a.fingerprint
    assert SiglipOnnxEncoder(exported.dir16).dim == 16
    d = a.describe()
    assert d["kind"] == "siglip" and d["dim"] == 32 and not d["closed_vocabulary"]
    assert a.encode_images([]).shape == (0, 32) and a.encode_texts([]).shape == (0, 32)


def _copy(exported: SimpleNamespace, tmp_path: Path) -> Path:
    d = tmp_path / "enc"
    shutil.copytree(exported.dir, d)
    return d


def _set_manifest(d: Path, **changes) -> None:
    m = json.loads((d / MANIFEST).read_text())
    for k, v in changes.items():
        if v is None:
            del m[k]
        else:
            m[k] = v
    (d / MANIFEST).write_text(json.dumps(m))


def _replace_file(d: Path, name: str, data: bytes) -> None:
    """Overwrite `name` and record its new digest (so only the content is wrong)."""
    (d / name).write_bytes(data)
    m = json.loads((d / MANIFEST).read_text())
    m["files"][name] = file_sha256(d / name)
    (d / MANIFEST).write_text(json.dumps(m))


@pytest.mark.parametrize("name", ["vision.onnx", "text.onnx", "tokenizer.json", MANIFEST])
def test_missing_file(exported: SimpleNamespace, tmp_path: Path, name: str) -> None:
    d = _copy(exported, tmp_path)
    (d / name).unlink()
    with pytest.raises(EncoderError, match=rf"{name}: missing.*encoder convert"):
        SiglipOnnxEncoder(d)


def test_bad_directories(exported: SimpleNamespace, tmp_path: Path) -> None:
    with pytest.raises(EncoderError, match="nowhere: no such encoder directory"):
        SiglipOnnxEncoder(tmp_path / "nowhere")

    d = _copy(exported, tmp_path)
    (d / MANIFEST).write_text("{not json")
    with pytest.raises(EncoderError, match=r"encoder\.json: not a JSON manifest"):
        SiglipOnnxEncoder(d)

    shutil.copy(exported.dir / MANIFEST, d / MANIFEST)
    _set_manifest(d, dim=None, pad_id=None)
    with pytest.raises(EncoderError, match=r"encoder\.json: lacks dim, pad_id"):
        SiglipOnnxEncoder(d)

    shutil.copy(exported.dir / MANIFEST, d / MANIFEST)
    _set_manifest(d, mean=[0.5, 0.5])
    with pytest.raises(EncoderError, match=r"encoder\.json: mean = .* three numbers"):
        SiglipOnnxEncoder(d)

    shutil.copy(exported.dir / MANIFEST, d / MANIFEST)
    with open(d / "tokenizer.json", "a") as f:
        f.write(" ")
    with pytest.raises(EncoderError, match=r"tokenizer\.json: sha256 .* differs"):
        SiglipOnnxEncoder(d)
    shutil.copy(exported.dir / "tokenizer.json", d / "tokenizer.json")

    # The manifest's dim disagrees with the graphs.
    _set_manifest(d, dim=16)
    with pytest.raises(EncoderError, match=r"vision\.onnx: output .*'n', 32.* not \[n, 16\]"):
        SiglipOnnxEncoder(d)
    shutil.copy(exported.dir / MANIFEST, d / MANIFEST)

    # A text graph of another model (D = 16) with a correct digest.
    _replace_file(d, "text.onnx", (exported.dir16 / "text.onnx").read_bytes())
    with pytest.raises(EncoderError, match=r"text\.onnx: output .*'n', 16.* not \[n, 32\]"):
        SiglipOnnxEncoder(d)

    _replace_file(d, "vision.onnx", b"not an onnx graph")
    with pytest.raises(EncoderError, match=r"vision\.onnx: onnxruntime cannot load it"):
        SiglipOnnxEncoder(d)


def test_bad_queries_and_images(exported: SimpleNamespace) -> None:
    enc = SiglipOnnxEncoder(exported.dir, threads=1)
    for texts in ([""], ["a cat", "   "]):
        with pytest.raises(EncoderError, match="empty query"):
            enc.encode_texts(texts)
    with pytest.raises(EncoderError, match="list of strings"):
        enc.encode_texts("a cat")
    ok = np.full((8, 8, 3), 0.5, np.float32)
    bad = {
        "dtype uint8": np.zeros((8, 8, 3), np.uint8),
        r"shape \(8, 8\)": np.zeros((8, 8), np.float32),
        r"shape \(8, 8, 4\)": np.zeros((8, 8, 4), np.float32),
        r"values in \[200, 200\], not \[0, 1\] \(divide by 255\)":
            np.full((8, 8, 3), 200.0, np.float32),
        "not finite": np.full((8, 8, 3), np.nan, np.float32),
    }
    for what, img in bad.items():
        with pytest.raises(EncoderError, match=rf"image 1: {what}"):
            enc.encode_images([ok, img])


def test_load_encoder_dispatches_to_siglip(exported: SimpleNamespace, tmp_path: Path,
                                           monkeypatch: pytest.MonkeyPatch) -> None:  # fmt: skip
    assert isinstance(load_encoder(exported.dir), SiglipOnnxEncoder)
    monkeypatch.setenv(ENCODER_ENV, str(exported.dir))
    enc = load_encoder()
    assert isinstance(enc, SiglipOnnxEncoder) and enc.dim == 32
    with pytest.raises(EncoderError, match="no such encoder directory"):
        load_encoder(tmp_path / "nowhere")


def test_cli_encoder_info(exported: SimpleNamespace, tmp_path: Path, capsys) -> None:
    assert main(["encoder", "info", str(exported.dir)]) == 0
    out = capsys.readouterr().out
    assert "siglip" in out and "tiny-siglip" in out
    assert [ln.split()[1] for ln in out.splitlines() if ln.startswith("dim")] == ["32"]
    for f in ("vision.onnx", "text.onnx", "tokenizer.json", MANIFEST):
        assert f in out
    assert SiglipOnnxEncoder(exported.dir).fingerprint in out

    d = _copy(exported, tmp_path)
    (d / "text.onnx").unlink()
    assert main(["encoder", "info", str(d)]) == 2
    assert "text.onnx: missing" in capsys.readouterr().err
    # export refuses to overwrite an encoder without --force (before any download)
    assert main(["encoder", "convert", "--model", "none/such", "--out", str(exported.dir)]) == 2
    assert "already holds an encoder" in capsys.readouterr().err


def test_export_needs_transformers(monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> None:
    monkeypatch.setitem(__import__("sys").modules, "transformers", None)
    with pytest.raises(EncoderError, match=r"pip install 'sync4d\[export\]'"):
        export_pretrained("google/siglip-base-patch16-224", tmp_path / "enc")


def test_export_pretrained_siglip_tokenizer(tmp_path: Path, capsys) -> None:
    """`encoder convert` on a local save_pretrained folder laid out like a Hub SigLIP (a
    SentencePiece SiglipTokenizer, a SiglipImageProcessor config): the converted tokenizer.json
    gives SiglipTokenizer's ids (case, punctuation, whitespace, truncation), and the text
    embeddings match the torch model's."""
    import sentencepiece as spm
    from transformers import SiglipTokenizer

    corpus = ["a photo of a cat", "a photo of a dog", "the red cube moves left",
              "a blue sphere rolls", "two cats and a dog", "the cup falls off the table"]
    buf = io.BytesIO()
    spm.SentencePieceTrainer.train(
        sentence_iterator=iter(corpus * 20), model_writer=buf, vocab_size=60,
        model_type="unigram", pad_id=0, eos_id=1, unk_id=2, bos_id=-1,
        character_coverage=1.0, hard_vocab_limit=False, minloglevel=2,
    )  # fmt: skip
    (tmp_path / "spiece.model").write_bytes(buf.getvalue())
    tok = SiglipTokenizer(str(tmp_path / "spiece.model"), model_max_length=L)
    hub = tmp_path / "hub"
    model = _tiny_model(2)
    model.save_pretrained(hub)
    tok.save_pretrained(hub)
    _pil_processor(size={"height": S, "width": S}, resample=3, image_mean=[0.5] * 3,
                   image_std=[0.5] * 3).save_pretrained(hub)  # fmt: skip

    out = tmp_path / "enc"
    assert main(["encoder", "convert", "--model", str(hub), "--out", str(out)]) == 0
    assert "dim 32" in capsys.readouterr().out
    enc = SiglipOnnxEncoder(out, threads=1)
    m = enc.manifest
    assert (m["image_size"], m["max_length"], m["pad_id"], m["resize"]["resample"]) == (
        S, L, tok.pad_token_id, "bicubic")  # fmt: skip
    assert m["mean"] == [0.5] * 3 and m["std"] == [0.5] * 3

    texts = ["a photo of a cat", "A Photo, of a CAT!", "  leading  space", "tab\tand\nnewline",
             "café ＡＢＣ ünïcode", "▁marker▁", "hello-world's", "the cup falls off " * 6]
    ref_ids = tok(texts, padding="max_length", truncation=True, max_length=L,
                  return_tensors="np")["input_ids"]  # fmt: skip
    np.testing.assert_array_equal(enc.tokenize(texts), ref_ids)
    with pytest.raises(EncoderError, match="empty query"):
        enc.encode_texts(["!?!"])  # nothing left after SigLIP's canonicalisation
    with torch.no_grad():
        ref = _unit(model.get_text_features(input_ids=torch.from_numpy(ref_ids)).pooler_output)
    err = float(np.abs(enc.encode_texts(texts) - ref).max())
    print(f"SiglipTokenizer export, text embeddings: max |onnx - torch| = {err:.2e}")
    assert err < 1e-4
