"""The offline default image-text encoder: ImageNet AlexNet features mapped linearly into
all-MiniLM-L6-v2's sentence space, the map fitted on generated renders of coloured shapes.

Design note (closed-vocabulary): nothing here is downloaded, and the only visual concepts the
image side has been taught are the colours and shapes of `sync4d.phase3.encoders.shapes` ("a red
ball"); a query outside that vocabulary gets an answer, but not a meaningful one. Use the
SigLIP encoder (`sync4d.phase3.encoders.siglip`) for open-vocabulary queries.

* Texts: MiniLM sentence embeddings (`sync4d.phase3.encoders.minilm`), unit rows of its
  ``dim`` (384).
* Images: padded to a square with their border colour, resized to 128x128 and passed through
  the AlexNet of `sync4d.metrics.lpips` (ImageNet weights; its input scaling is ImageNet's
  mean/std normalisation), on the image's contrast-normalised luminance (the "grey pass"):
  each conv layer's ReLU map is averaged globally (and conv4, conv5 over a 2x2 grid) and the
  square roots are kept. A colour-blind view of the shape keeps shape features from learning
  colour, so the linear map adds a colour part and a shape part and carries over to unseen
  colour-shape pairs (held-out pair accuracy 0.80 -> 0.86 on validation against the colour
  pass). Colour, the other half of the vocabulary, comes from simple colour statistics:
  a soft 4x4x4 RGB histogram, the mean RGB and brightness / saturation quantiles, all weighted
  towards the centre and away from the border colour (a crop's object fills its middle, the
  background touches its edges).
* The map: features standardised (training mean / std; the colour blocks then weighted x10,
  i.e. a 100 times weaker penalty), then ridge regression onto the caption embeddings
  ("a red ball") of the training images, in closed form (float64, deterministic); image
  embeddings are the mapped rows, L2-normalised, so images and texts are compared by cosine
  similarity in MiniLM's space.

The map is fitted on `shapes.train_pairs` only (a fifth of the colour-shape pairs stays out, for
`zero_shot_report`) and cached as an ``.npz`` under ``$SYNC4D_CACHE/offline-encoder/`` keyed by
the generator version, both weight digests and the settings (written atomically).
"""

from __future__ import annotations

import hashlib
import json
import logging
import sys
import time
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F

from sync4d.data.scene import cache_dir
from sync4d.files import write_atomic
from sync4d.phase3.encoders import shapes
from sync4d.phase3.encoders.encoder import Encoder, EncoderError, normalise_rows
from sync4d.phase3.encoders.minilm import MiniLM, load_minilm

__all__ = [
    "DEFAULT_SETTINGS",
    "FEATURE_VERSION",
    "OfflineEncoder",
    "OfflineSettings",
    "caption_targets",
    "colour_offsets",
    "feature_blocks",
    "fit_ridge",
    "select_features",
    "zero_shot_report",
]

#: Bumped whenever `feature_blocks` changes meaning.
FEATURE_VERSION = 1
_HIST_BINS = 4
_COLOUR_SIZE = 32


@dataclass(frozen=True)
class OfflineSettings:
    """How the map is fitted (defaults tuned on the validation pairs, see
    docs/results/offline-encoder.md). `per_pair` generated images of each training pair,
    `image_size` pixels square, `supersample` rays per pixel side, from generator seed `seed`;
    AlexNet input `input_size` pixels; `blocks` the feature blocks used (names from
    `feature_blocks`; a ``g`` prefix means the grey pass) and `weights` their scale after
    standardising (default 1); `ridge` the ridge penalty per sample (lambda / n); `templates`
    the caption templates averaged into each target (``{colour}``, ``{shape}``), over every
    synonym of the shape when `synonyms`; `colour_boost` how far each target is pushed along
    its colour's direction (`colour_offsets` of `colour_template`: MiniLM puts "a red ball"
    nearer "a blue ball" than "a red box", while a scene's objects mostly differ by colour, so
    this pulls images of different colours apart); `pairs` which pairs to fit on
    (``train``; ``fit`` = train minus the validation pairs, for tuning; ``all``)."""

    per_pair: int = 24
    image_size: int = 64
    supersample: int = 1
    seed: int = 0
    input_size: int = 128
    blocks: tuple[str, ...] = ("gconv1", "gconv2", "gconv3", "gconv4", "gconv5", "ggrid4",
                               "ggrid5", "hist", "rgb", "tone")  # fmt: skip
    weights: tuple[tuple[str, float], ...] = (("hist", 10.0), ("rgb", 10.0), ("tone", 10.0))
    ridge: float = 1.0
    templates: tuple[str, ...] = ("a {colour} {shape}",)
    synonyms: bool = False
    colour_boost: float = 1.0
    colour_template: str = "a {colour} object"
    pairs: str = "train"

    def key(self) -> dict:
        """The settings as a JSON-able dict (part of the cache key)."""
        return asdict(self)

    def passes(self) -> tuple[str, ...]:
        """The AlexNet passes `blocks` needs (``rgb``, ``grey``)."""
        grey = any(b.startswith("g") for b in self.blocks)
        rgb = any(b[:-1] in ("conv", "max", "grid") for b in self.blocks)
        return (("rgb",) if rgb else ()) + (("grey",) if grey else ())


#: The settings `OfflineEncoder()` and ``load_encoder("offline")`` use.
DEFAULT_SETTINGS = OfflineSettings()


def _square(a: np.ndarray) -> np.ndarray:
    """Image [H, W, 3] padded to a square with its median border colour (a crop keeps its
    aspect instead of being stretched)."""
    h, w = a.shape[:2]
    if h == w:
        return a
    border = np.concatenate([a[0], a[-1], a[:, 0], a[:, -1]])
    side = max(h, w)
    out = np.empty((side, side, 3), np.float32)
    out[:] = np.median(border, axis=0)
    y, x = (side - h) // 2, (side - w) // 2
    out[y : y + h, x : x + w] = a
    return out


def _pool(images: list[np.ndarray], size: int) -> torch.Tensor:
    """Images (each [H, W, 3] in [0, 1]) padded to squares (`_square`) and resized to
    [n, 3, size, size] (antialiased)."""
    out = []
    for im in images:
        a = np.asarray(im, dtype=np.float32)
        if a.ndim != 3 or a.shape[2] != 3 or min(a.shape[:2]) < 1:
            raise ValueError(f"an image must be [H, W, 3], got {list(a.shape)}")
        t = torch.from_numpy(np.ascontiguousarray(_square(a))).permute(2, 0, 1)[None]
        if t.shape[-2:] != (size, size):
            t = F.interpolate(t, size=(size, size), mode="bilinear", antialias=True,
                              align_corners=False)  # fmt: skip
        out.append(t.clamp(0.0, 1.0))
    return torch.cat(out) if out else torch.zeros(0, 3, size, size)


def _colour_blocks(x: torch.Tensor) -> dict[str, np.ndarray]:
    """Colour statistics of images [n, 3, 32, 32]: `hist` a soft 4x4x4 RGB histogram [n, 64] and
    `rgb` the mean colour [n, 3], both weighted by a centre Gaussian times the distance from the
    median border colour."""
    n, _, h, w = x.shape
    px = x.permute(0, 2, 3, 1).reshape(n, h * w, 3).double()
    yy, xx = torch.meshgrid(torch.linspace(-1, 1, h), torch.linspace(-1, 1, w), indexing="ij")
    centre = torch.exp(-(xx**2 + yy**2) / (2 * 0.5**2)).reshape(1, -1).double()
    ring = torch.ones(h, w, dtype=torch.bool)
    ring[2:-2, 2:-2] = False
    border = px[:, ring.reshape(-1)].median(dim=1).values  # [n, 3]
    fg = 1.0 - torch.exp(-((px - border[:, None]) ** 2).sum(-1) / (2 * 0.12**2))
    wgt = centre * (0.05 + fg)
    wgt = wgt / wgt.sum(1, keepdim=True)
    rgb = (px * wgt[..., None]).sum(1)
    b = _HIST_BINS
    pos = px.clamp(0, 1) * (b - 1)
    lo = pos.floor().clamp(max=b - 2)
    frac = pos - lo
    lo = lo.long()
    hist = torch.zeros(n, b**3, dtype=torch.float64)
    for corner in range(8):
        bits = [(corner >> k) & 1 for k in range(3)]
        idx = torch.zeros_like(lo[..., 0])
        share = wgt.clone()
        for ch, bit in enumerate(bits):
            idx = idx * b + lo[..., ch] + bit
            share = share * (frac[..., ch] if bit else 1 - frac[..., ch])
        hist.scatter_add_(1, idx, share)
    mask = F.adaptive_avg_pool2d(fg.reshape(n, 1, h, w).float(), 8).reshape(n, -1).double()
    # Tone: weighted quantiles of brightness (max channel) and saturation, which tell white
    # from grey from black under shading better than the mean does.
    val = px.amax(-1)
    sat = (val - px.amin(-1)) / val.clamp_min(1e-3)
    tone = torch.cat([_weighted_quantiles(val, wgt, (0.25, 0.5, 0.75, 0.9)),
                      _weighted_quantiles(sat, wgt, (0.5, 0.9)),
                      border.amax(-1, keepdim=True), (rgb.amax(-1) - border.amax(-1))[:, None]],
                     dim=1)  # fmt: skip
    return {"hist": hist.sqrt().numpy(), "rgb": rgb.numpy(), "mask": mask.numpy(),
            "tone": tone.numpy()}  # fmt: skip


def _weighted_quantiles(v: torch.Tensor, w: torch.Tensor, qs: tuple[float, ...]) -> torch.Tensor:
    """Quantiles `qs` of each row of values `v` [n, m] under weights `w` [n, m] (rows sum to 1),
    as [n, len(qs)]."""
    order = v.argsort(1)
    vs, cw = v.gather(1, order), w.gather(1, order).cumsum(1)
    idx = torch.stack([(cw < q).sum(1) for q in qs], 1).clamp(max=v.shape[1] - 1)
    return vs.gather(1, idx)


def _grey(x: torch.Tensor) -> torch.Tensor:
    """Luminance of images [n, 3, H, W], contrast-normalised per image (mean 0.5, std 0.2),
    repeated on three channels: a view of the shape that no longer shows its colour."""
    lum = (x * torch.tensor([0.299, 0.587, 0.114]).view(1, 3, 1, 1)).sum(1, keepdim=True)
    mu = lum.mean((2, 3), keepdim=True)
    sd = lum.std((2, 3), keepdim=True).clamp_min(1e-3)
    return ((lum - mu) / sd * 0.2 + 0.5).clamp(0.0, 1.0).expand(-1, 3, -1, -1)


def _alexnet() -> torch.nn.Module:
    """The LPIPS AlexNet (cached by `load_lpips`); `EncoderError` naming the install command
    when its weights are missing."""
    from sync4d.metrics.lpips import LPIPSWeightsMissing, load_lpips

    try:
        return load_lpips()
    except LPIPSWeightsMissing as e:
        raise EncoderError(f"the offline encoder needs the AlexNet weights: {e}") from None


@torch.no_grad()
def feature_blocks(images: list[np.ndarray] | np.ndarray, input_size: int = 128,
                   passes: tuple[str, ...] = ("rgb",), batch: int = 64
                   ) -> dict[str, np.ndarray]:  # fmt: skip
    """Every feature block of `images` (each [H, W, 3] in [0, 1]), as float64 [n, d_block].
    For each AlexNet pass in `passes` (``"rgb"``: the image; ``"grey"``: its contrast-normalised
    luminance, names prefixed ``g``): ``conv1``..``conv5`` (square roots of the spatial means
    of the ReLU maps; 64, 192, 384, 256, 256 channels), ``max1``..``max5`` (square roots of the
    spatial maxima) and ``grid1``..``grid5`` (square roots of 2x2 spatial means); then the
    colour blocks ``hist`` (64), ``rgb`` (3), ``tone`` (8) and ``mask`` (64) of
    `_colour_blocks`."""
    alex = _alexnet()
    images = list(images)
    parts: dict[str, list[np.ndarray]] = {}

    def add(name: str, t: torch.Tensor) -> None:
        parts.setdefault(name, []).append(t.double().clamp_min(0).sqrt().numpy())

    for s in range(0, len(images), batch):
        chunk = images[s : s + batch]
        x = _pool(chunk, input_size)
        for kind in passes:
            pre = {"rgb": "", "grey": "g"}[kind]
            for i, f in enumerate(alex.features(x if kind == "rgb" else _grey(x))):
                add(f"{pre}conv{i + 1}", f.mean((2, 3)))
                add(f"{pre}max{i + 1}", f.amax((2, 3)))
                add(f"{pre}grid{i + 1}", F.adaptive_avg_pool2d(f, 2).flatten(1))
        for k, v in _colour_blocks(_pool(chunk, _COLOUR_SIZE)).items():
            parts.setdefault(k, []).append(v)
    if not parts:
        return {}
    return {k: np.concatenate(v) for k, v in parts.items()}


def select_features(blocks: dict[str, np.ndarray], names: tuple[str, ...]) -> np.ndarray:
    """The named blocks side by side [n, sum of widths] (float64)."""
    return np.concatenate([blocks[k] for k in names], axis=1)


def _block_scale(blocks: dict[str, np.ndarray], settings: OfflineSettings) -> np.ndarray:
    """Per-feature weight after standardising: each block's weight (default 1)."""
    w = dict(settings.weights)
    return np.concatenate([np.full(blocks[k].shape[1], float(w.get(k, 1.0)))
                           for k in settings.blocks])  # fmt: skip


def fit_ridge(x: np.ndarray, y: np.ndarray, ridge: float, scale: np.ndarray | None = None
              ) -> dict[str, np.ndarray]:  # fmt: skip
    """Closed-form ridge regression of targets `y` [n, D] on features `x` [n, d]: the features
    are standardised (then multiplied by `scale` [d]), the penalty is ``ridge * n``; returns
    ``mean``, ``scale`` (1 / std times `scale`), ``weight`` [d, D] and ``bias`` [D] (float64),
    so that the prediction is ``((x - mean) * scale) @ weight + bias``."""
    x = np.asarray(x, np.float64)
    y = np.asarray(y, np.float64)
    n, d = x.shape
    mean = x.mean(0)
    sd = x.std(0)
    s = np.where(sd > 1e-8, 1.0 / np.maximum(sd, 1e-8), 0.0)
    if scale is not None:
        s = s * scale
    z = (x - mean) * s
    bias = y.mean(0)
    yc = y - bias
    lam = ridge * n
    if n < d:  # dual form: W = Z^T (Z Z^T + lam I)^-1 Y
        weight = z.T @ np.linalg.solve(z @ z.T + lam * np.eye(n), yc)
    else:
        weight = np.linalg.solve(z.T @ z + lam * np.eye(d), z.T @ yc)
    return {"mean": mean, "scale": s, "weight": weight, "bias": bias}


def _apply(m: dict[str, np.ndarray], x: np.ndarray) -> np.ndarray:
    return normalise_rows(((x - m["mean"]) * m["scale"]) @ m["weight"] + m["bias"])


def caption_targets(text: MiniLM, settings: OfflineSettings) -> np.ndarray:
    """The target embedding of every vocabulary pair, [len(COLOURS), len(SHAPES), dim]: the
    normalised mean of the MiniLM embeddings of its captions (templates x synonyms), plus
    `settings.colour_boost` times its colour's offset (`colour_offsets`), renormalised."""
    out = np.zeros((len(shapes.COLOURS), len(shapes.SHAPES), text.dim), np.float64)
    for ci, c in enumerate(shapes.COLOURS):
        for si, s in enumerate(shapes.SHAPES):
            names = shapes.SHAPE_SYNONYMS[s] if settings.synonyms else (s,)
            caps = [t.format(colour=c, shape=nm) for t in settings.templates for nm in names]
            out[ci, si] = normalise_rows(text.encode(caps).mean(0, keepdims=True))[0]
    if settings.colour_boost:
        out = out + settings.colour_boost * colour_offsets(text, settings.colour_template)[:, None]
    return normalise_rows(out.reshape(-1, text.dim)).reshape(out.shape)


def colour_offsets(text: MiniLM, template: str = "a {colour} object") -> np.ndarray:
    """Each colour's direction in MiniLM's space, [len(COLOURS), dim]: the embedding of
    `template` with that colour minus the mean over all colours (no shape named, so no
    colour-shape pair is favoured)."""
    e = text.encode([template.format(colour=c) for c in shapes.COLOURS]).astype(np.float64)
    return e - e.mean(0)


def _pairs(which: str) -> list[tuple[str, str]]:
    if which == "train":
        return shapes.train_pairs()
    if which == "fit":  # the training pairs without the validation pairs (for tuning)
        val = set(shapes.validation_pairs())
        return [p for p in shapes.train_pairs() if p not in val]
    if which == "all":
        return shapes.all_pairs()
    raise ValueError(f"pairs must be train, fit or all, not {which!r}")


def _digest(arrays: dict[str, np.ndarray]) -> str:
    h = hashlib.sha256()
    for k in sorted(arrays):
        a = np.ascontiguousarray(arrays[k])
        h.update(k.encode() + str(a.dtype).encode() + str(a.shape).encode() + a.tobytes())
    return h.hexdigest()


class OfflineEncoder(Encoder):
    """The closed-vocabulary offline encoder (see the module note): texts are MiniLM
    embeddings, images AlexNet + colour features mapped into that space by a ridge map fitted
    on generated shapes (cached). `fit_seconds` holds the timings of the fit when one ran
    (``generate``, ``features``, ``fit``: wall seconds; ``*_cpu``: process CPU seconds;
    ``images``: how many; empty when the map came from the cache)."""

    kind = "offline"
    closed_vocabulary = True

    def __init__(self, settings: OfflineSettings | None = None, use_cache: bool = True) -> None:
        from sync4d.metrics.lpips import ALEXNET_SHA256

        self.settings = settings or DEFAULT_SETTINGS
        self.text = load_minilm()
        _alexnet()  # both weight files present and intact, or EncoderError now
        self._digests = {"alexnet": ALEXNET_SHA256, "minilm": self.text.weights_sha256,
                         "tokenizer": self.text.tokenizer_sha256}  # fmt: skip
        key = {"generator": shapes.GENERATOR_VERSION, "features": FEATURE_VERSION,
               "digests": self._digests, "settings": self.settings.key()}  # fmt: skip
        self.cache_key = hashlib.sha256(json.dumps(key, sort_keys=True).encode()).hexdigest()
        self.cache_path = cache_dir() / "offline-encoder" / f"map-{self.cache_key[:24]}.npz"
        self.fit_seconds: dict[str, float] = {}
        self.from_cache = False
        m = self._load_cached() if use_cache else None
        if m is None:
            m = self._fit()
            if use_cache:
                self._save(m)
        else:
            self.from_cache = True
        if m["weight"].shape[1] != self.text.dim:
            raise EncoderError(f"{self.cache_path}: map has the wrong width; delete the file")
        self._map = m
        self._map_digest = _digest(m)

    def _load_cached(self) -> dict[str, np.ndarray] | None:
        try:
            with np.load(self.cache_path) as z:
                m = {k: z[k] for k in ("mean", "scale", "weight", "bias")}
                stored = str(z["digest"])
        except (OSError, KeyError, ValueError):
            return None
        return m if stored == _digest(m) else None  # a damaged file is refitted

    def _save(self, m: dict[str, np.ndarray]) -> None:
        def write(tmp: Path) -> None:
            with open(tmp, "wb") as f:
                np.savez(f, digest=np.array(_digest(m)), **m)

        try:
            self.cache_path.parent.mkdir(parents=True, exist_ok=True)
            write_atomic(self.cache_path, write)
        except OSError as e:  # WriteFailed too: an unwritable cache only costs a refit
            logging.getLogger("sync4d").warning("could not cache the offline encoder map (%s)", e)

    def _fit(self) -> dict[str, np.ndarray]:
        st = self.settings
        clock = [(time.perf_counter(), time.process_time())]
        data = shapes.generate(_pairs(st.pairs), st.per_pair, st.seed, st.image_size,
                               st.supersample)  # fmt: skip
        clock.append((time.perf_counter(), time.process_time()))
        blocks = feature_blocks(data.images, st.input_size, st.passes())
        clock.append((time.perf_counter(), time.process_time()))
        targets = caption_targets(self.text, st)[data.colours, data.shapes]
        m = fit_ridge(select_features(blocks, st.blocks), targets, st.ridge,
                      _block_scale(blocks, st))  # fmt: skip
        m = {k: v.astype(np.float32) for k, v in m.items()}
        clock.append((time.perf_counter(), time.process_time()))
        self.fit_seconds = {"images": float(len(data.images))}
        for i, name in enumerate(("generate", "features", "fit")):
            self.fit_seconds[name] = clock[i + 1][0] - clock[i][0]
            self.fit_seconds[f"{name}_cpu"] = clock[i + 1][1] - clock[i][1]
        return m

    @property
    def dim(self) -> int:
        """Embedding dimension: MiniLM's hidden size (384)."""
        return self.text.dim

    @property
    def fingerprint(self) -> str:
        """SHA-256 over the AlexNet, MiniLM and tokenizer digests and the fitted map."""
        parts = [self._digests[k] for k in sorted(self._digests)] + [self._map_digest]
        return hashlib.sha256("\n".join(parts).encode()).hexdigest()

    def image_features(self, images: list[np.ndarray]) -> np.ndarray:
        """The raw (unstandardised) features [n, d] the map reads, float64."""
        st = self.settings
        return select_features(feature_blocks(images, st.input_size, st.passes()), st.blocks)

    def encode_images(self, images: list[np.ndarray]) -> np.ndarray:
        """Embeddings [n, dim] (float32, unit rows) of images, each [H, W, 3] in [0, 1]."""
        if len(images) == 0:
            return np.zeros((0, self.dim), np.float32)
        return _apply(self._map, self.image_features(images))

    def encode_texts(self, texts: list[str]) -> np.ndarray:
        """MiniLM embeddings [n, dim] (float32, unit rows) of `texts`."""
        return self.text.encode(list(texts))

    def describe(self) -> dict:
        """The base record plus the vocabulary the encoder knows."""
        d = super().describe()
        d["vocabulary"] = {"colours": list(shapes.COLOURS), "shapes": list(shapes.SHAPES)}
        return d


def _accuracy(emb: np.ndarray, colours: np.ndarray, kinds: np.ndarray,
              text: np.ndarray) -> dict[str, float]:  # fmt: skip
    """Top-1 accuracies of image embeddings [n, D] against caption embeddings [C, S, D]."""
    nc, ns, _ = text.shape
    best = (emb @ text.reshape(nc * ns, -1).T).argmax(1)
    pc, ps = best // ns, best % ns
    return {
        "pair": float(np.mean((pc == colours) & (ps == kinds))),
        "colour": float(np.mean(pc == colours)),
        "shape": float(np.mean(ps == kinds)),
    }


def zero_shot_report(encoder: OfflineEncoder | None = None, per_pair: int = 20, seed: int = 1,
                     template: str = "a {colour} {shape}",
                     pairs: list[tuple[str, str]] | None = None, seen: bool = True
                     ) -> dict:  # fmt: skip
    """Top-1 accuracy of the offline encoder on fresh images (generator seed `seed`,
    `per_pair` each) of the held-out colour-shape pairs (or `pairs`), each classified by
    cosine similarity among the captions of ALL vocabulary pairs (`template`): ``pair`` (both
    right), ``colour`` and ``shape`` (that part of the top caption right), ``by_pair`` the pair
    accuracy of each held-out caption; ``seen`` (if `seen`) gives the same on as many fresh
    images of the training pairs. Times in seconds."""
    enc = encoder or OfflineEncoder()
    held = pairs if pairs is not None else shapes.heldout_pairs()
    t0 = time.perf_counter()
    caps = [template.format(colour=c, shape=s) for c in shapes.COLOURS for s in shapes.SHAPES]
    text = enc.encode_texts(caps).reshape(len(shapes.COLOURS), len(shapes.SHAPES), -1)
    out: dict = {"template": template, "seed": seed, "per_pair": per_pair,
                 "captions": len(caps), "heldout_pairs": len(held)}  # fmt: skip
    fitted = _pairs(enc.settings.pairs)
    out["heldout_in_fit"] = bool(set(held) & set(fitted))
    for name, ps in (("heldout", held), ("seen", fitted if seen else [])):
        if not ps:
            continue
        data = shapes.generate(ps, per_pair, seed, enc.settings.image_size)
        emb = enc.encode_images(list(data.images))
        out[name] = _accuracy(emb, data.colours, data.shapes, text)
        if name == "heldout":
            best = (emb @ text.reshape(len(caps), -1).T).argmax(1)
            right = best == data.colours * len(shapes.SHAPES) + data.shapes
            per = right.reshape(len(ps), per_pair).mean(1)  # generate() is pair-major
            out[name]["by_pair"] = {shapes.caption(c, s, template): float(a)
                                    for (c, s), a in zip(ps, per, strict=True)}  # fmt: skip
    out["seconds"] = time.perf_counter() - t0
    out["fit_seconds"] = dict(enc.fit_seconds)
    out["settings"] = enc.settings.key()
    return out


if __name__ == "__main__":  # python -m sync4d.phase3.encoders.offline: fit (or load) and report
    torch.set_num_threads(1)
    t = time.perf_counter()
    e = OfflineEncoder()
    report = {"load_seconds": time.perf_counter() - t, "from_cache": e.from_cache,
              **zero_shot_report(e)}  # fmt: skip
    sys.stdout.write(json.dumps(report, indent=1) + "\n")  # a script's output, not a print
