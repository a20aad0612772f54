"""SigLIP through onnxruntime: the paper's image-text encoder (Sec. 3.5, E_img and E_txt).

Design. Exporting and running are split so that running needs neither transformers nor a
network. `export_pretrained` (the ``export`` extra, internet once) loads a Hugging Face SigLIP
and hands it to `export_siglip`, which writes one self-contained directory:

* ``vision.onnx``: ``pixel_values`` [n, 3, S, S] float32 -> ``image_embeds`` [n, D], the pooled
  image embedding of ``SiglipModel.get_image_features`` (the multihead-attention pooling head).
* ``text.onnx``: ``input_ids`` [n, L] int64 -> ``text_embeds`` [n, D], the pooled text
  embedding of ``get_text_features`` (last position, then the linear head).
* ``tokenizer.json``: a `tokenizers.Tokenizer` that reproduces the model's tokenizer, SigLIP's
  text canonicalisation (lower case, punctuation removed, whitespace collapsed) included.
* ``encoder.json``: the manifest, written last: kind, model name, D, S, mean, std, the resize
  rule, L, the pad id and the sha256 of every file above.

`SiglipOnnxEncoder` loads such a directory with onnxruntime (CPU) and `tokenizers`, checks each
file against its digest and each graph against the manifest, and preprocesses like
``SiglipImageProcessor``: images resized to S x S with the model's resampling (bicubic for
SigLIP; antialiased, as torchvision and PIL do, and clamped to [0, 1] as an 8-bit image is),
normalised with the manifest's mean and std, channels first; texts padded to L with the pad id
and truncated to L (``padding="max_length"``, as SigLIP was trained; its text pooling reads the
last position). Rows come back L2-normalised, float32. The inputs are already floats in [0, 1],
so there is no 8-bit rounding: against the processor on the 8-bit version of an image the pixel
values agree to that rounding (about 2/255 after normalising by std 0.5).
"""

from __future__ import annotations

import hashlib
import json
import math
import os
import re
import string
import warnings
from pathlib import Path
from typing import Any

import numpy as np

from sync4d.files import write_atomic, write_text_atomic
from sync4d.phase3.encoders.encoder import (
    CONVERT_COMMAND,
    Encoder,
    EncoderError,
    file_sha256,
    normalise_rows,
)

__all__ = [
    "FILES",
    "MANIFEST",
    "RESAMPLING",
    "SiglipOnnxEncoder",
    "export_pretrained",
    "export_siglip",
    "file_sha256",
    "read_manifest",
    "siglip_tokenizer_json",
]

#: The manifest of an encoder directory.
MANIFEST = "encoder.json"
#: The files the manifest lists with their sha256, in the order they are written.
FILES = ("vision.onnx", "text.onnx", "tokenizer.json")
#: Version of the directory layout that `SiglipOnnxEncoder` reads.
FORMAT = 1
#: Resampling filters for the resize, by name: their PIL numbers (as in image processor configs).
RESAMPLING = {"nearest": 0, "bilinear": 2, "bicubic": 3}
#: Images per onnxruntime run (and texts per run) unless the encoder is given another.
BATCH = 32

_EXPORT_HINT = "pip install 'sync4d[export]'"
_REEXPORT = f"convert it again with `{CONVERT_COMMAND} --model NAME --out DIR`"
_REQUIRED = ("format", "kind", "dim", "image_size", "mean", "std", "resize", "max_length",
             "pad_id", "files")  # fmt: skip


# --------------------------------------------------------------------------------------------
# Export (needs torch, transformers, onnx)
# --------------------------------------------------------------------------------------------


def siglip_tokenizer_json(tokenizer: Any) -> tuple[Any, int]:
    """A `tokenizers.Tokenizer` equivalent to `tokenizer` and the pad id.

    `tokenizer` is a fast Hugging Face tokenizer (its backend is copied as it is), a
    ``SiglipTokenizer`` (SentencePiece; converted: its canonicalisation, lower case when
    ``do_lower_case``, punctuation removed, whitespace collapsed, becomes the normaliser, and
    the end-of-sequence token is appended), or a `tokenizers.Tokenizer` with padding enabled.
    The one known difference from ``SiglipTokenizer``: text that follows a special token spelt
    out in a query (a literal ``</s>``) gets a word-start marker the slow tokenizer omits."""
    import tokenizers

    if isinstance(tokenizer, tokenizers.Tokenizer):
        pad = tokenizer.padding
        if not pad:
            raise EncoderError("the tokenizers.Tokenizer has no padding: call enable_padding("
                               "pad_id=..., pad_token=...) first, or pass the HF tokenizer")
        return tokenizers.Tokenizer.from_str(tokenizer.to_str()), int(pad["pad_id"])
    pad_id = getattr(tokenizer, "pad_token_id", None)
    if pad_id is None:
        raise EncoderError(f"{type(tokenizer).__name__}: the tokenizer has no pad token")
    backend = getattr(tokenizer, "backend_tokenizer", None)
    if backend is not None:
        return tokenizers.Tokenizer.from_str(backend.to_str()), int(pad_id)
    vocab_file = getattr(tokenizer, "vocab_file", None)
    if vocab_file and str(vocab_file).endswith(".model"):
        return _convert_sentencepiece(tokenizer), int(pad_id)
    raise EncoderError(f"{type(tokenizer).__name__}: not a fast tokenizer nor a SentencePiece "
                       "one; cannot write tokenizer.json")  # fmt: skip


def _convert_sentencepiece(tok: Any) -> Any:
    """``SiglipTokenizer`` (slow, SentencePiece) as a `tokenizers.Tokenizer`."""
    from tokenizers import AddedToken, Regex, normalizers, processors

    try:
        from transformers.convert_slow_tokenizer import SpmConverter, import_protobuf

        proto = import_protobuf().ModelProto()
    except ImportError as e:
        raise EncoderError(f"converting the SentencePiece tokenizer needs protobuf ({e}); "
                           f"{_EXPORT_HINT}") from None  # fmt: skip
    with open(tok.vocab_file, "rb") as f:
        proto.ParseFromString(f.read())
    if proto.trainer_spec.model_type == 1:  # unigram
        vocab: Any = [(p.piece, p.score) for p in proto.pieces]
    elif proto.trainer_spec.model_type == 2:  # BPE
        vocab = {p.piece: i for i, p in enumerate(proto.pieces)}
    else:
        raise EncoderError(f"{tok.vocab_file}: SentencePiece model type "
                           f"{proto.trainer_spec.model_type} is neither unigram nor BPE")
    # legacy=True: the word-start marker on every chunk, whatever whitespace the text began
    # with, like SiglipTokenizer (which prefixes "▁" itself and strips).
    tk = SpmConverter.build_tokenizer_from_spm_proto(proto, vocab, legacy=True)
    # SiglipTokenizer.canonicalize_text, before SentencePiece's own normalisation.
    canon = [normalizers.Replace("▁", " ")]
    if getattr(tok, "do_lower_case", True):
        canon.append(normalizers.Lowercase())
    canon += [
        normalizers.Replace(Regex("[" + re.escape(string.punctuation) + "]"), ""),
        normalizers.Replace(Regex(r"\s+"), " "),
        normalizers.Strip(),
    ]
    tk.normalizer = normalizers.Sequence([*canon, tk.normalizer])
    specials = []
    for t in (tok.pad_token, tok.eos_token, tok.unk_token):
        if t is not None and str(t) not in specials:
            specials.append(str(t))
    tk.add_special_tokens([AddedToken(t, special=True, normalized=False) for t in specials])
    eos = str(tok.eos_token)
    tk.post_processor = processors.TemplateProcessing(
        single=f"$A {eos}", pair=f"$A {eos} $B {eos}",
        special_tokens=[(eos, int(tok.eos_token_id))],
    )  # fmt: skip
    return tk


def _pooled(out: Any) -> Any:
    """The embedding tensor of get_*_features: a tensor (transformers 4) or the pooler_output
    of a BaseModelOutputWithPooling (transformers 5)."""
    import torch

    if isinstance(out, torch.Tensor):
        return out
    pooled = getattr(out, "pooler_output", None)
    if pooled is None:
        raise EncoderError(f"get_*_features returned {type(out).__name__} without pooler_output")
    return pooled


def export_siglip(
    model: Any,
    tokenizer: Any,
    out_dir: str | Path,
    *,
    image_size: int,
    mean: list[float],
    std: list[float],
    max_length: int,
    resample: str = "bicubic",
    name: str = "",
    opset: int = 17,
) -> dict:
    """Write the encoder directory `out_dir` of a SigLIP `model` (a torch module with
    ``get_image_features(pixel_values=)`` and ``get_text_features(input_ids=)``) and its
    `tokenizer` (see `siglip_tokenizer_json`), and return the manifest.

    `image_size` S (pixels), `mean` and `std` (3 values each, on [0, 1] pixels) and `resample`
    (a `RESAMPLING` name) are the image processor's; `max_length` L is the text length the model
    was trained with. The graphs are traced (``dynamo=False``) with a dynamic batch axis, then
    run once with onnxruntime against torch on a probe batch: a difference over 1e-3 raises.
    Every file is written atomically; the manifest goes last."""
    import torch

    out = Path(out_dir)
    image_size, max_length, mean, std = _check_preprocessing(image_size, max_length, mean, std,
                                                             resample)  # fmt: skip
    tk, pad_id = siglip_tokenizer_json(tokenizer)
    model = model.eval()
    dtypes = {p.dtype for p in model.parameters() if p.is_floating_point()}
    if dtypes - {torch.float32}:
        raise EncoderError(f"the model's parameters are {sorted(map(str, dtypes))}: export a "
                           "float32 model (model.float())")  # fmt: skip
    (out / MANIFEST).unlink(missing_ok=True)  # the directory is incomplete until it is rewritten

    class _Vision(torch.nn.Module):
        def __init__(self) -> None:
            super().__init__()
            self.m = model

        def forward(self, pixel_values: torch.Tensor) -> torch.Tensor:
            return _pooled(self.m.get_image_features(pixel_values=pixel_values))

    class _Text(torch.nn.Module):
        def __init__(self) -> None:
            super().__init__()
            self.m = model

        def forward(self, input_ids: torch.Tensor) -> torch.Tensor:
            return _pooled(self.m.get_text_features(input_ids=input_ids))

    # Traced on a batch of 2, checked on a batch of 3 (the batch axis must stay dynamic).
    g = torch.Generator().manual_seed(0)
    pixels = torch.rand(5, 3, image_size, image_size, generator=g) * 2 - 1
    vocab = max(1, min(tk.get_vocab_size(), _text_vocab(model)))
    ids = torch.randint(0, vocab, (5, max_length), generator=g, dtype=torch.int64)
    graphs = {
        "vision.onnx": (_Vision(), pixels, "pixel_values", "image_embeds"),
        "text.onnx": (_Text(), ids, "input_ids", "text_embeds"),
    }
    expected: dict[str, np.ndarray] = {}
    with torch.no_grad():
        for fname, (module, probe, _, _) in graphs.items():
            expected[fname] = module(probe[2:]).float().numpy()
    dims = {f: int(e.shape[-1]) for f, e in expected.items()}
    if len(set(dims.values())) != 1:
        raise EncoderError(f"image and text embeddings differ in size ({dims}): not a SigLIP")
    dim = dims["vision.onnx"]

    for fname, (module, probe, in_name, out_name) in graphs.items():
        def write(tmp: Path, module=module, probe=probe, in_name=in_name,
                  out_name=out_name) -> None:  # fmt: skip
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")  # tracer and deprecation chatter
                torch.onnx.export(
                    module, (probe[:2],), str(tmp), input_names=[in_name],
                    output_names=[out_name],
                    dynamic_axes={in_name: {0: "n"}, out_name: {0: "n"}},
                    opset_version=opset, dynamo=False, do_constant_folding=True,
                )  # fmt: skip

        write_atomic(out / fname, write)
    write_text_atomic(out / "tokenizer.json", tk.to_str())
    for fname in FILES:
        os.chmod(out / fname, 0o644)  # readable by all, like a downloaded model (mkstemp: 0600)

    check = {}
    for fname, (_, probe, in_name, _) in graphs.items():
        got = _session(out / fname, 1).run(None, {in_name: probe[2:].numpy()})[0]
        err = float(np.abs(got - expected[fname]).max())
        scale = float(np.abs(expected[fname]).max()) or 1.0
        if not err <= 1e-3 * max(1.0, scale):
            raise EncoderError(f"{out / fname}: onnxruntime differs from torch by {err:.3g} on "
                               "the probe batch; the export is wrong")  # fmt: skip
        check[fname] = err

    versions = {"torch": torch.__version__}
    try:
        import transformers

        versions["transformers"] = transformers.__version__
    except ImportError:
        pass
    manifest = {
        "format": FORMAT,
        "kind": "siglip",
        "model": name or getattr(getattr(model, "config", None), "_name_or_path", "") or "",
        "dim": dim,
        "image_size": image_size,
        "mean": mean,
        "std": std,
        "resize": {"resample": resample, "antialias": True, "clamp": [0.0, 1.0],
                   "as": "torch.nn.functional.interpolate(align_corners=False), i.e. "
                   "torchvision's resize, on [0, 1] floats"},  # fmt: skip
        "max_length": max_length,
        "pad_id": pad_id,
        "padding": "max_length",
        "opset": opset,
        "export_check_max_abs": check,
        "versions": versions,
        "files": {f: file_sha256(out / f) for f in FILES},
    }
    write_text_atomic(out / MANIFEST, json.dumps(manifest, indent=2) + "\n")
    os.chmod(out / MANIFEST, 0o644)
    return manifest


def _text_vocab(model: Any) -> int:
    cfg = getattr(getattr(model, "config", None), "text_config", None)
    return int(getattr(cfg, "vocab_size", 0) or 1 << 30)


def _check_preprocessing(image_size: Any, max_length: Any, mean: Any, std: Any,
                         resample: Any) -> tuple[int, int, list[float], list[float]]:  # fmt: skip
    if not isinstance(image_size, int) or image_size < 1:
        raise EncoderError(f"image_size {image_size!r}: a positive integer")
    if not isinstance(max_length, int) or max_length < 1:
        raise EncoderError(f"max_length {max_length!r}: a positive integer")
    if resample not in RESAMPLING:
        raise EncoderError(f"resample {resample!r}: one of {', '.join(RESAMPLING)}")
    try:
        m = [float(v) for v in mean]
        s = [float(v) for v in std]
    except (TypeError, ValueError):
        raise EncoderError(f"mean {mean!r} / std {std!r}: three numbers each") from None
    if len(m) != 3 or len(s) != 3 or not all(math.isfinite(v) for v in m + s) or min(s) <= 0:
        raise EncoderError(f"mean {mean!r} / std {std!r}: three numbers each, std > 0")
    return image_size, max_length, m, s


def export_pretrained(name: str, out_dir: str | Path) -> dict:
    """Download the SigLIP `name` (a Hugging Face id such as ``google/siglip-base-patch16-224``,
    or a local folder written by ``save_pretrained``) and write its encoder directory `out_dir`
    with `export_siglip`; the manifest. The image size, mean, std and resampling come from the
    model's image processor config; the text length from its tokenizer (``model_max_length``,
    at most the text model's position embeddings). Needs the ``export`` extra."""
    try:
        from transformers import AutoImageProcessor, AutoModel, AutoTokenizer
    except ImportError as e:
        raise EncoderError(f"exporting needs transformers ({e}); {_EXPORT_HINT}") from None
    try:
        import onnx  # noqa: F401  (torch.onnx.export needs it)
    except ImportError as e:
        raise EncoderError(f"exporting needs onnx ({e}); {_EXPORT_HINT}") from None
    try:
        import torch

        model = AutoModel.from_pretrained(name, dtype=torch.float32)
        processor = AutoImageProcessor.from_pretrained(name)
        tokenizer = AutoTokenizer.from_pretrained(name)
    except (OSError, ValueError, ImportError) as e:
        raise EncoderError(f"{name}: cannot load the model, image processor or tokenizer "
                           f"({e}); check the name and the network, or {_EXPORT_HINT}") from None
    kind = getattr(model.config, "model_type", "")
    if kind != "siglip":
        raise EncoderError(f"{name}: a {kind or type(model).__name__} model; only SigLIP "
                           "(model_type 'siglip') exports to this encoder")  # fmt: skip
    size = getattr(processor, "size", None) or {}
    size = dict(size) if not isinstance(size, int) else {"height": size, "width": size}
    h, w = size.get("height"), size.get("width")
    if h is None or h != w:
        raise EncoderError(f"{name}: image processor size {size}; a square height x width is "
                           "needed")  # fmt: skip
    if getattr(processor, "do_resize", True) is False:
        raise EncoderError(f"{name}: the image processor does not resize; not supported")
    rescale = float(getattr(processor, "rescale_factor", 1 / 255))
    if getattr(processor, "do_rescale", True) and not math.isclose(rescale, 1 / 255, rel_tol=1e-6):
        raise EncoderError(f"{name}: rescale_factor {rescale}; only 1/255 (8-bit images) is "
                           "supported")  # fmt: skip
    if getattr(processor, "do_normalize", True):
        mean, std = list(processor.image_mean), list(processor.image_std)
    else:
        mean, std = [0.0, 0.0, 0.0], [1.0, 1.0, 1.0]
    resample = _resample_name(getattr(processor, "resample", 2))
    positions = int(model.config.text_config.max_position_embeddings)
    max_length = int(getattr(tokenizer, "model_max_length", positions) or positions)
    max_length = min(max_length, positions)
    manifest = export_siglip(model, tokenizer, out_dir, image_size=int(h), mean=mean, std=std,
                             max_length=max_length, resample=resample, name=str(name))
    return manifest


def _resample_name(resample: Any) -> str:
    """A `RESAMPLING` name from a PIL resampling number/enum or a torchvision mode."""
    value = getattr(resample, "value", resample)
    if isinstance(value, str):
        value = value.lower()
        if value in RESAMPLING:
            return value
    for k, v in RESAMPLING.items():
        if value == v:
            return k
    raise EncoderError(f"image resampling {resample!r} is not supported "
                       f"({', '.join(RESAMPLING)} are)")  # fmt: skip


# --------------------------------------------------------------------------------------------
# Running (numpy, torch for the resize, onnxruntime, tokenizers)
# --------------------------------------------------------------------------------------------


def _threads(threads: int | None) -> int:
    """onnxruntime intra-op threads: `threads`, else $OMP_NUM_THREADS, else 0 (its default)."""
    if threads:
        return int(threads)
    try:
        return max(0, int(os.environ.get("OMP_NUM_THREADS", "0")))
    except ValueError:
        return 0


def _session(path: Path, threads: int | None) -> Any:
    import onnxruntime as ort

    so = ort.SessionOptions()
    so.intra_op_num_threads = _threads(threads)
    so.inter_op_num_threads = 1
    so.log_severity_level = 3
    try:
        return ort.InferenceSession(str(path), so, providers=["CPUExecutionProvider"])
    except Exception as e:  # onnxruntime raises its own exception types
        raise EncoderError(f"{path}: onnxruntime cannot load it ({str(e).strip()[:300]}); "
                           f"{_REEXPORT}") from None  # fmt: skip


def read_manifest(folder: str | Path) -> dict:
    """The checked manifest (``encoder.json``) of the encoder directory `folder`; EncoderError
    names the file and the problem (missing, not JSON, a key missing or of the wrong type)."""
    folder = Path(folder)
    path = folder / MANIFEST
    if not folder.is_dir():
        raise EncoderError(f"{folder}: no such encoder directory; {_REEXPORT}")
    if not path.is_file():
        raise EncoderError(f"{path}: missing, so {folder} is not a complete encoder directory "
                           f"(the manifest is written last); {_REEXPORT}")  # fmt: skip
    try:
        m = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as e:
        raise EncoderError(f"{path}: not a JSON manifest ({e}); {_REEXPORT}") from None
    if not isinstance(m, dict):
        raise EncoderError(f"{path}: not a JSON object; {_REEXPORT}")
    missing = [k for k in _REQUIRED if k not in m]
    if missing:
        raise EncoderError(f"{path}: lacks {', '.join(missing)}; {_REEXPORT}")

    def bad(key: str, what: str) -> EncoderError:
        return EncoderError(f"{path}: {key} = {m[key]!r} is not {what}; {_REEXPORT}")

    if m["format"] != FORMAT:
        raise bad("format", f"{FORMAT} (this sync4d reads layout {FORMAT})")
    if m["kind"] != "siglip":
        raise bad("kind", "'siglip'")
    for key in ("dim", "image_size", "max_length"):
        if not isinstance(m[key], int) or isinstance(m[key], bool) or m[key] < 1:
            raise bad(key, "a positive integer")
    if not isinstance(m["pad_id"], int) or isinstance(m["pad_id"], bool) or m["pad_id"] < 0:
        raise bad("pad_id", "a token id")
    for key in ("mean", "std"):
        v = m[key]
        if (not isinstance(v, list) or len(v) != 3
                or not all(isinstance(x, int | float) and math.isfinite(x) for x in v)):
            raise bad(key, "a list of three numbers")
    if min(m["std"]) <= 0:
        raise bad("std", "positive")
    r = m["resize"]
    if not isinstance(r, dict) or r.get("resample") not in RESAMPLING:
        raise bad("resize", f"an object with resample one of {', '.join(RESAMPLING)}")
    files = m["files"]
    if not isinstance(files, dict) or any(
        not isinstance(files.get(f), str) or not re.fullmatch(r"[0-9a-f]{64}", files[f])
        for f in FILES
    ):
        raise bad("files", f"a sha256 for each of {', '.join(FILES)}")
    return m


class SiglipOnnxEncoder(Encoder):
    """A SigLIP encoder directory (written by `export_siglip`) run with onnxruntime on the CPU.

    Loading checks every file against the manifest's sha256 and each graph's input and output
    shapes against the manifest. `threads` is onnxruntime's intra-op thread count (default
    $OMP_NUM_THREADS, else onnxruntime's choice); `batch_size` images or texts go per run."""

    kind = "siglip"
    closed_vocabulary = False

    def __init__(self, folder: str | Path, *, threads: int | None = None,
                 batch_size: int = BATCH) -> None:  # fmt: skip
        import tokenizers

        self.folder = Path(folder)
        self.manifest = m = read_manifest(self.folder)
        if batch_size < 1:
            raise EncoderError(f"batch_size {batch_size}: at least 1")
        self.batch_size = int(batch_size)
        for fname in FILES:
            path = self.folder / fname
            if not path.is_file():
                raise EncoderError(f"{path}: missing from the encoder directory; {_REEXPORT}")
            digest = file_sha256(path)
            if digest != m["files"][fname]:
                raise EncoderError(f"{path}: sha256 {digest[:12]}... differs from the "
                                   f"manifest's {m['files'][fname][:12]}... (a changed or "
                                   f"damaged file); {_REEXPORT}")  # fmt: skip
        self._dim = int(m["dim"])
        self.image_size = int(m["image_size"])
        self.max_length = int(m["max_length"])
        self.pad_id = int(m["pad_id"])
        self.mean = np.asarray(m["mean"], dtype=np.float32).reshape(3, 1, 1)
        self.std = np.asarray(m["std"], dtype=np.float32).reshape(3, 1, 1)
        self.resample = str(m["resize"]["resample"])
        self._fingerprint = hashlib.sha256(
            "".join(f"{f} {m['files'][f]}\n" for f in FILES).encode()
        ).hexdigest()

        tok_path = self.folder / "tokenizer.json"
        try:
            tk = tokenizers.Tokenizer.from_file(str(tok_path))
        except Exception as e:  # tokenizers raises plain Exception subclasses
            raise EncoderError(f"{tok_path}: not a tokenizers file ({str(e)[:200]}); "
                               f"{_REEXPORT}") from None  # fmt: skip
        if self.pad_id >= tk.get_vocab_size():
            raise EncoderError(f"{self.folder / MANIFEST}: pad_id {self.pad_id} is outside "
                               f"{tok_path}'s vocabulary of {tk.get_vocab_size()}")
        tk.enable_truncation(self.max_length)
        tk.enable_padding(length=self.max_length, pad_id=self.pad_id,
                          pad_token=tk.id_to_token(self.pad_id) or "")  # fmt: skip
        self.tokenizer = tk

        self._vision = _session(self.folder / "vision.onnx", threads)
        self._text = _session(self.folder / "text.onnx", threads)
        self._check_graph("vision.onnx", self._vision, "pixel_values",
                          ["n", 3, self.image_size, self.image_size])  # fmt: skip
        self._check_graph("text.onnx", self._text, "input_ids", ["n", self.max_length])

    def _check_graph(self, fname: str, sess: Any, in_name: str, in_shape: list) -> None:
        path = self.folder / fname
        ins, outs = sess.get_inputs(), sess.get_outputs()
        if len(ins) != 1 or ins[0].name != in_name or len(ins[0].shape) != len(in_shape):
            got = [(i.name, i.shape) for i in ins]
            raise EncoderError(f"{path}: inputs {got}, not {in_name} {in_shape}; {_REEXPORT}")
        for have, want in zip(ins[0].shape[1:], in_shape[1:], strict=True):
            if isinstance(have, int) and have != want:
                raise EncoderError(f"{path}: input {in_name} has shape {ins[0].shape}, the "
                                   f"manifest says {in_shape}; {_REEXPORT}")  # fmt: skip
        shape = outs[0].shape if len(outs) == 1 else None
        if shape is None or len(shape) != 2 or shape[1] != self._dim:
            got = [(o.name, o.shape) for o in outs]
            raise EncoderError(f"{path}: output {got} is not [n, {self._dim}] (the manifest's "
                               f"dim); {_REEXPORT}")  # fmt: skip

    @property
    def dim(self) -> int:
        """Embedding dimension D (the manifest's, checked against both graphs)."""
        return self._dim

    @property
    def fingerprint(self) -> str:
        """sha256 (hex) over the manifest's digests of vision.onnx, text.onnx, tokenizer.json."""
        return self._fingerprint

    def describe(self) -> dict:
        """The base description plus the model name, image size and text length."""
        d = super().describe()
        d.update(model=self.manifest.get("model", ""), image_size=self.image_size,
                 max_length=self.max_length)  # fmt: skip
        return d

    def preprocess(self, images: list[np.ndarray]) -> np.ndarray:
        """``pixel_values`` [n, 3, S, S] float32 of `images` (each [H, W, 3] float in [0, 1]):
        resized with the manifest's filter (antialiased, align_corners=False; an image already
        S x S is left as it is), clamped to [0, 1], normalised (x - mean) / std."""
        import torch
        import torch.nn.functional as F

        s = self.image_size
        out = np.empty((len(images), 3, s, s), dtype=np.float32)
        for i, img in enumerate(images):
            a = _check_image(img, i)
            x = torch.from_numpy(np.ascontiguousarray(a.transpose(2, 0, 1)))[None]
            if x.shape[-2:] != (s, s):
                if self.resample == "nearest":
                    x = F.interpolate(x, size=(s, s), mode="nearest")
                else:
                    x = F.interpolate(x, size=(s, s), mode=self.resample, align_corners=False,
                                      antialias=True)  # fmt: skip
            x = x[0].clamp_(0.0, 1.0).numpy()
            out[i] = (x - self.mean) / self.std
        return out

    def tokenize(self, texts: list[str]) -> np.ndarray:
        """``input_ids`` [n, L] int64 of `texts`: the tokenizer's normalisation, then padded to
        L with the pad id and truncated to L (the end-of-sequence token kept). An empty query
        (nothing left after normalisation) raises EncoderError."""
        if isinstance(texts, str) or not all(isinstance(t, str) for t in texts):
            raise EncoderError("encode_texts takes a list of strings")
        encs = self.tokenizer.encode_batch(list(texts))
        ids = np.zeros((len(encs), self.max_length), dtype=np.int64)
        for i, (t, e) in enumerate(zip(texts, encs, strict=True)):
            content = sum(1 for m, s in zip(e.attention_mask, e.special_tokens_mask, strict=True)
                          if m and not s)  # fmt: skip
            if content == 0:
                raise EncoderError(f"empty query: text {i} ({t!r}) has no words to encode")
            ids[i] = e.ids
        return ids

    def encode_images(self, images: list[np.ndarray]) -> np.ndarray:
        """Embeddings [n, dim] (float32, unit rows) of `images`, each [H, W, 3] float in [0, 1]
        of any size; `batch_size` images per onnxruntime run. An empty list gives [0, dim]."""
        images = list(images)
        rows = [np.zeros((0, self._dim), np.float32)]
        for k in range(0, len(images), self.batch_size):
            px = self.preprocess(images[k:k + self.batch_size])
            rows.append(self._vision.run(None, {"pixel_values": px})[0])
        return normalise_rows(np.concatenate(rows))

    def encode_texts(self, texts: list[str]) -> np.ndarray:
        """Embeddings [n, dim] (float32, unit rows) of `texts`; `batch_size` texts per run.
        An empty list gives [0, dim]; an empty query raises EncoderError."""
        ids = self.tokenize(texts)
        rows = [np.zeros((0, self._dim), np.float32)]
        for k in range(0, len(ids), self.batch_size):
            rows.append(self._text.run(None, {"input_ids": ids[k:k + self.batch_size]})[0])
        return normalise_rows(np.concatenate(rows))


def _check_image(img: Any, i: int) -> np.ndarray:
    """Image `i` as float32 [H, W, 3] in [0, 1], or EncoderError saying what is wrong."""
    a = np.asarray(img)
    if a.ndim != 3 or a.shape[2] != 3 or a.shape[0] < 1 or a.shape[1] < 1:
        raise EncoderError(f"image {i}: shape {a.shape}, not [H, W, 3] (RGB, channels last)")
    if not np.issubdtype(a.dtype, np.floating):
        raise EncoderError(f"image {i}: dtype {a.dtype}; give floats in [0, 1] "
                           "(an 8-bit image divided by 255)")  # fmt: skip
    a = a.astype(np.float32, copy=False)
    if not np.isfinite(a).all():
        raise EncoderError(f"image {i}: not finite")
    lo, hi = float(a.min()), float(a.max())
    if lo < -1e-3 or hi > 1 + 1e-3:
        raise EncoderError(f"image {i}: values in [{lo:.3g}, {hi:.3g}], not [0, 1]"
                           + (" (divide by 255)" if hi > 2 else ""))  # fmt: skip
    return a
