"""Generated renders of single coloured shapes with captions: the training data of the offline
encoder's image-to-text map (`sync4d.phase3.encoders.offline`).

Design note (closed-vocabulary): the vocabulary is `COLOURS` x `SHAPES` ("a red ball"); nothing
outside it is drawn or named. Each image shows ONE named shape, framed as Phase 3 frames its object
crops (the silhouette's bounding box plus a 12 % margin, so the shape fills most of the image),
with random size, placement, aspect, partial crops at the borders, mild blur and noise.

Each shape is ray cast exactly in numpy (sphere, box, cylinder, cone, pyramid and disc as convex
intersections of quadrics and slabs, the torus by sphere tracing) under a perspective camera at
a random elevation, with Lambertian shading, an ambient term and an optional Blinn-Phong
highlight (half the images lit in linear light and encoded to sRGB, as a renderer does, half
shaded in sRGB, as the embedded synthetic scene is), so it looks like a render of a 3D object;
it is plain or carries stripes / checks of a second colour (a darker tint, or near-white as on
the synthetic scene's striped ball). Half the images stand the shape on a lit ground plate with
its shadow; the rest of the background is light, dark, grey, a gradient or smooth noise. A third
also show part of another shape of another colour at a border, in front or behind (crops of
neighbouring objects overlap). Pixels are supersampled when `supersample` > 1 (anti-aliased).

Everything is deterministic: image ``k`` of pair (colour, shape) under seed ``s`` depends only on
``(s, colour, shape, k)``. A fixed fifth of the colour-shape pairs is held out (`heldout_pairs`)
for zero-shot tests, chosen so every colour and every shape keeps partners in training; another
fifth of the training pairs is the validation split (`validation_pairs`) used for tuning.
"""

from __future__ import annotations

import colorsys
import math
from dataclasses import dataclass

import numpy as np

__all__ = [
    "COLOURS",
    "GENERATOR_VERSION",
    "SHAPES",
    "SHAPE_SYNONYMS",
    "ShapeSet",
    "all_pairs",
    "caption",
    "generate",
    "heldout_pairs",
    "render_shape",
    "train_pairs",
    "validation_pairs",
]

#: Bumped whenever the images change: cached maps fitted on older images are stale.
GENERATOR_VERSION = 1

#: Colour names and their base sRGB albedo in [0, 1] (jittered per image).
_PALETTE: dict[str, tuple[float, float, float]] = {
    "red": (0.85, 0.10, 0.08),
    "green": (0.15, 0.65, 0.20),
    "blue": (0.12, 0.28, 0.90),
    "yellow": (0.95, 0.85, 0.10),
    "orange": (0.98, 0.50, 0.05),
    "purple": (0.50, 0.15, 0.72),
    "pink": (0.98, 0.55, 0.72),
    "white": (0.94, 0.94, 0.94),
    "black": (0.06, 0.06, 0.06),
    "grey": (0.50, 0.50, 0.50),
    "brown": (0.45, 0.27, 0.10),
    "cyan": (0.10, 0.80, 0.85),
}
#: The colour vocabulary.
COLOURS: tuple[str, ...] = tuple(_PALETTE)
#: The shape vocabulary (the first name of each `SHAPE_SYNONYMS` entry).
SHAPES: tuple[str, ...] = ("ball", "box", "pillar", "cone", "ring", "disc", "pyramid")
#: Other names of each shape (used only as alternative caption targets).
SHAPE_SYNONYMS: dict[str, tuple[str, ...]] = {
    "ball": ("ball", "sphere"),
    "box": ("box", "cube", "block"),
    "pillar": ("pillar", "column", "cylinder"),
    "cone": ("cone",),
    "ring": ("ring", "torus"),
    "disc": ("disc", "plate", "disk"),
    "pyramid": ("pyramid",),
}
_ACHROMATIC = {"white", "black", "grey"}
#: Pairs the downstream scenes name (D-NeRF bouncingballs, the embedded synthetic scene); kept
#: in training whatever the hold-out rule says.
_ANCHORS = {("red", "ball"), ("green", "ball"), ("blue", "ball"), ("blue", "box"),
            ("green", "pillar")}  # fmt: skip


def caption(colour: str, shape: str, template: str = "a {colour} {shape}") -> str:
    """The caption of a colour-shape pair, e.g. ``"a red ball"``."""
    return template.format(colour=colour, shape=shape)


def all_pairs() -> list[tuple[str, str]]:
    """Every (colour, shape) pair of the vocabulary, colour-major."""
    return [(c, s) for c in COLOURS for s in SHAPES]


def _fold(colour: str, shape: str) -> int:
    """Which of five folds a pair is in: a Latin-square rule, so each colour has its shapes and
    each shape its colours spread over all folds."""
    return (COLOURS.index(colour) + 3 * SHAPES.index(shape) + 2) % 5


def heldout_pairs() -> list[tuple[str, str]]:
    """The pairs never used to fit the map (fold 0, about a fifth), for zero-shot tests."""
    return [p for p in all_pairs() if _fold(*p) == 0 and p not in _ANCHORS]


def train_pairs() -> list[tuple[str, str]]:
    """The pairs the map is fitted on (all but `heldout_pairs`)."""
    held = set(heldout_pairs())
    return [p for p in all_pairs() if p not in held]


def validation_pairs() -> list[tuple[str, str]]:
    """Training pairs set aside (fold 1) when tuning settings on the training pairs alone."""
    return [p for p in train_pairs() if _fold(*p) == 1 and p not in _ANCHORS]


# ---------------------------------------------------------------------------------------------
# Ray casting. Rays are (o, d) [N, 3] in the shape's own frame (z up, about unit size); every
# routine returns (t_in, t_out, n_in): the entry/exit distances [N] (a miss has t_in >= t_out)
# and the outward normal at entry [N, 3].

_INF = 1e30


def _slab(o: np.ndarray, d: np.ndarray, axis: np.ndarray, lo: float, hi: float):
    """Interval of the ray inside ``lo <= p . axis <= hi``."""
    od, dd = o @ axis, d @ axis
    small = np.abs(dd) < 1e-12
    dd = np.where(small, 1e-12, dd)
    t1, t2 = (lo - od) / dd, (hi - od) / dd
    t_in, t_out = np.minimum(t1, t2), np.maximum(t1, t2)
    inside = (od >= lo) & (od <= hi)
    t_in = np.where(small, np.where(inside, -_INF, _INF), t_in)
    t_out = np.where(small, np.where(inside, _INF, -_INF), t_out)
    n = np.where((t1 < t2)[:, None], -axis[None], axis[None])
    return t_in, t_out, n


def _quadric_interval(a: np.ndarray, b: np.ndarray, c: np.ndarray):
    """Interval where ``a t^2 + 2 b t + c <= 0`` for ``a > 0`` (rays with no root: empty)."""
    disc = b * b - a * c
    ok = disc >= 0
    s = np.sqrt(np.where(ok, disc, 0.0))
    a = np.maximum(a, 1e-12)
    t_in = np.where(ok, (-b - s) / a, _INF)
    t_out = np.where(ok, (-b + s) / a, -_INF)
    return t_in, t_out


def _sphere(o: np.ndarray, d: np.ndarray, r: float):
    a = (d * d).sum(1)
    b = (o * d).sum(1)
    c = (o * o).sum(1) - r * r
    t_in, t_out = _quadric_interval(a, b, c)
    p = o + np.clip(t_in, -10, 10)[:, None] * d
    return t_in, t_out, p / r


def _cylinder_z(o: np.ndarray, d: np.ndarray, r: float):
    """Infinite cylinder ``x^2 + y^2 <= r^2``."""
    a = d[:, 0] ** 2 + d[:, 1] ** 2
    b = o[:, 0] * d[:, 0] + o[:, 1] * d[:, 1]
    c = o[:, 0] ** 2 + o[:, 1] ** 2 - r * r
    para = a < 1e-12
    t_in, t_out = _quadric_interval(a, b, c)
    inside = c <= 0
    t_in = np.where(para, np.where(inside, -_INF, _INF), t_in)
    t_out = np.where(para, np.where(inside, _INF, -_INF), t_out)
    p = o + np.clip(t_in, -10, 10)[:, None] * d
    n = np.stack([p[:, 0], p[:, 1], np.zeros_like(p[:, 0])], 1) / r
    return t_in, t_out, n


def _cone_z(o: np.ndarray, d: np.ndarray, radius: float, height: float):
    """Solid cone: base disc of `radius` at z = 0, apex at z = `height`."""
    k2 = (radius / height) ** 2
    q0 = height - o[:, 2]
    a = d[:, 0] ** 2 + d[:, 1] ** 2 - k2 * d[:, 2] ** 2
    b = o[:, 0] * d[:, 0] + o[:, 1] * d[:, 1] + k2 * q0 * d[:, 2]
    c = o[:, 0] ** 2 + o[:, 1] ** 2 - k2 * q0**2
    s_in, s_out, s_n = _slab(o, d, np.array([0.0, 0.0, 1.0]), 0.0, height)
    a = np.where(np.abs(a) < 1e-12, 1e-12, a)
    disc = b * b - a * c
    ok = disc >= 0
    s = np.sqrt(np.where(ok, disc, 0.0))
    r1, r2 = (-b - s) / a, (-b + s) / a
    t1, t2 = np.minimum(r1, r2), np.maximum(r1, r2)
    pos = a > 0
    # a > 0: inside the double cone on [t1, t2]; a < 0: outside (t1, t2), and within the slab
    # only one of the two outer pieces (the lower nappe) can remain.
    in_a = np.where(pos, np.maximum(s_in, t1), s_in)
    out_a = np.where(pos, np.minimum(s_out, t2), np.minimum(s_out, t1))
    in_b, out_b = np.maximum(s_in, t2), s_out
    use_b = (~pos) & (out_a <= in_a)
    t_in = np.where(use_b, in_b, in_a)
    t_out = np.where(use_b, out_b, out_a)
    no_root = ~ok
    t_in = np.where(no_root & pos, _INF, np.where(no_root & ~pos, s_in, t_in))
    t_out = np.where(no_root & pos, -_INF, np.where(no_root & ~pos, s_out, t_out))
    p = o + np.clip(t_in, -10, 10)[:, None] * d
    n_side = np.stack([p[:, 0], p[:, 1], k2 * (height - p[:, 2])], 1)
    n_side /= np.linalg.norm(n_side, axis=1, keepdims=True) + 1e-12
    on_slab = np.abs(t_in - s_in) < 1e-9
    n = np.where(on_slab[:, None], s_n, n_side)
    return t_in, t_out, n


def _intersect(parts: list[tuple[np.ndarray, np.ndarray, np.ndarray]]):
    """Intersection of convex pieces: latest entry (with its normal), earliest exit."""
    t_in = np.stack([p[0] for p in parts])
    t_out = np.min(np.stack([p[1] for p in parts]), 0)
    which = np.argmax(t_in, 0)
    normals = np.stack([p[2] for p in parts])
    n = normals[which, np.arange(t_in.shape[1])]
    return t_in[which, np.arange(t_in.shape[1])], t_out, n


_EX, _EY, _EZ = np.eye(3)


@dataclass(frozen=True)
class _Shape:
    """One drawn shape: its kind, size parameters and the rotation into the world frame."""

    kind: str
    params: tuple[float, ...]
    rot: np.ndarray  # [3, 3] local -> world

    def local_hit(self, o: np.ndarray, d: np.ndarray):
        """(t_in, t_out, n_in) of local rays against the solid."""
        k, p = self.kind, self.params
        if k == "ball":
            return _sphere(o, d, p[0])
        if k in ("box", "pillar_box"):
            axes = zip((_EX, _EY, _EZ), p, strict=True)
            return _intersect([_slab(o, d, ax, -h, h) for ax, h in axes])
        if k in ("pillar", "disc"):
            r, h = p
            return _intersect([_cylinder_z(o, d, r), _slab(o, d, _EZ, -h, h)])
        if k == "cone":
            return _cone_z(o, d, p[0], p[1])
        if k == "pyramid":
            half, height = p
            parts = [_slab(o, d, _EZ, 0.0, height)]
            for ax in (_EX, -_EX, _EY, -_EY):
                n = ax * height + _EZ * half  # faces through the apex and a base edge
                n = n / np.linalg.norm(n)
                parts.append(_slab(o, d, n, -_INF, (_EZ * height) @ n))
            return _intersect(parts)
        if k == "ring":
            return _torus(o, d, p[0], p[1])
        raise ValueError(k)

    def zmin(self) -> float:
        """Lowest world z of the shape (where the ground plate goes)."""
        k, p = self.kind, self.params
        if k == "ball":
            return -p[0]
        if k in ("box", "pillar_box"):
            corners = np.array([[sx * p[0], sy * p[1], sz * p[2]] for sx in (-1, 1)
                                for sy in (-1, 1) for sz in (-1, 1)])  # fmt: skip
            return float((corners @ self.rot.T)[:, 2].min())
        if k in ("pillar", "disc"):
            r, h = p
            axis = self.rot[:, 2]
            return float(-(h * abs(axis[2]) + r * math.sqrt(max(0.0, 1 - axis[2] ** 2))))
        if k in ("cone", "pyramid"):
            return 0.0
        if k == "ring":
            big, small = p
            axis = self.rot[:, 2]
            return float(-(big * math.sqrt(max(0.0, 1 - axis[2] ** 2)) + small))
        raise ValueError(k)


def _torus(o: np.ndarray, d: np.ndarray, big: float, small: float):
    """Torus about z (radii `big`, `small`) by sphere tracing from the bounding sphere."""
    b_in, b_out, _ = _sphere(o, d, big + small)
    n_rays = len(o)
    t_in = np.full(n_rays, _INF)
    idx = np.nonzero(b_in < b_out)[0]
    t = np.maximum(b_in[idx], 0.0)
    oo, dd, end = o[idx], d[idx], b_out[idx]
    live = np.arange(len(idx))  # rays still marching
    for _ in range(64):
        p = oo[live] + t[live, None] * dd[live]
        dist = np.hypot(np.hypot(p[:, 0], p[:, 1]) - big, p[:, 2]) - small
        done = dist < 1e-4
        t_in[idx[live[done]]] = t[live[done]]
        t[live] += np.maximum(dist, 1e-4)
        live = live[~done & (t[live] < end[live])]
        if not len(live):
            break
    p = o + np.clip(t_in, -10, 10)[:, None] * d
    rho = np.hypot(p[:, 0], p[:, 1]) + 1e-12
    centre = np.stack([p[:, 0] / rho * big, p[:, 1] / rho * big, np.zeros(n_rays)], 1)
    n = p - centre
    n /= np.linalg.norm(n, axis=1, keepdims=True) + 1e-12
    return t_in, np.where(t_in < _INF, t_in + 1.0, -_INF), n


def _rot_z(a: float) -> np.ndarray:
    c, s = math.cos(a), math.sin(a)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def _rot_x(a: float) -> np.ndarray:
    c, s = math.cos(a), math.sin(a)
    return np.array([[1.0, 0.0, 0.0], [0.0, c, -s], [0.0, s, c]])


def _draw_shape(kind: str, rng: np.random.Generator) -> _Shape:
    """Random size, aspect and pose of a shape of `kind` (about unit size, centred)."""
    yaw = rng.uniform(0, 2 * math.pi)
    tilt = 0.0
    if kind == "ball":
        params: tuple[float, ...] = (1.0,)
    elif kind == "box":
        cube = rng.random() < 0.35
        hx = rng.uniform(0.6, 1.0)
        if cube:
            params = (hx, hx * rng.uniform(0.9, 1.1), hx * rng.uniform(0.9, 1.1))
        else:
            params = (hx, hx * rng.uniform(0.5, 1.0), hx * rng.uniform(0.4, 1.1))
    elif kind == "pillar":
        r = rng.uniform(0.25, 0.45)
        h = r * rng.uniform(2.2, 4.0)
        if rng.random() < 0.4:
            kind, params = "pillar_box", (r, r * rng.uniform(0.8, 1.2), h)
        else:
            params = (r, h)
        tilt = rng.uniform(-0.12, 0.12)
    elif kind == "cone":
        params = (rng.uniform(0.5, 0.9), rng.uniform(1.2, 2.0))
    elif kind == "pyramid":
        params = (rng.uniform(0.6, 1.0), rng.uniform(0.8, 1.6))
    elif kind == "disc":
        params = (1.0, rng.uniform(0.04, 0.14))
        tilt = rng.uniform(0.0, 0.5) if rng.random() < 0.3 else 0.0
    elif kind == "ring":
        params = (1.0, rng.uniform(0.18, 0.38))
        tilt = rng.uniform(0.0, 1.2)
    else:
        raise ValueError(f"unknown shape {kind!r}")
    rot = _rot_z(yaw) @ _rot_x(tilt)
    return _Shape(kind, params, rot)


def _jitter_colour(colour: str, rng: np.random.Generator) -> np.ndarray:
    """The base albedo of `colour` with a small random hue, saturation and value change."""
    r, g, b = _PALETTE[colour]
    h, s, v = colorsys.rgb_to_hsv(r, g, b)
    if colour in _ACHROMATIC:
        s = min(1.0, s + rng.uniform(0.0, 0.08))
        h = rng.random()
        v = float(np.clip(v + rng.uniform(-0.08, 0.05), 0.0, 1.0))
    else:
        h = (h + rng.uniform(-0.025, 0.025)) % 1.0
        s = float(np.clip(s * rng.uniform(0.7, 1.08), 0.0, 1.0))
        v = float(np.clip(v * rng.uniform(0.8, 1.1), 0.0, 1.0))
    rgb = np.array(colorsys.hsv_to_rgb(h, s, v))
    if colour not in _ACHROMATIC and rng.random() < 0.25:  # a lighter tint (light green)
        rgb = rgb + (1.0 - rgb) * rng.uniform(0.05, 0.12 if colour in ("red", "pink") else 0.3)
    return rgb


def _to_linear(c: np.ndarray) -> np.ndarray:
    """sRGB in [0, 1] to linear light."""
    return np.where(c <= 0.04045, c / 12.92, ((c + 0.055) / 1.055) ** 2.4)


def _to_srgb(c: np.ndarray) -> np.ndarray:
    """Linear light to sRGB in [0, 1]."""
    c = np.clip(c, 0.0, 1.0)
    return np.where(c <= 0.0031308, c * 12.92, 1.055 * c ** (1 / 2.4) - 0.055)


def _background(u: np.ndarray, v: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """Background colours [N, 3] at image coordinates `u`, `v` [N] in [0, 1]."""
    kind = rng.choice(["light", "dark", "grey", "gradient", "noise"], p=[0.3, 0.15, 0.2, 0.2, 0.15])

    def tone(lo: float, hi: float) -> np.ndarray:
        base = rng.uniform(lo, hi)
        tint = rng.normal(0.0, 0.03, 3)
        return np.clip(base + tint, 0.0, 1.0)

    if kind == "light":
        return np.broadcast_to(tone(0.82, 1.0), (len(u), 3)).copy()
    if kind == "dark":
        return np.broadcast_to(tone(0.0, 0.22), (len(u), 3)).copy()
    if kind == "grey":
        return np.broadcast_to(tone(0.3, 0.7), (len(u), 3)).copy()
    if kind == "gradient":
        a, b = tone(0.0, 1.0), tone(0.0, 1.0)
        ang = rng.uniform(0, 2 * math.pi)
        s = np.clip(0.5 + (u - 0.5) * math.cos(ang) + (v - 0.5) * math.sin(ang), 0.0, 1.0)
        return a[None] * (1 - s[:, None]) + b[None] * s[:, None]
    grid = rng.uniform(0.0, 1.0, (5, 5, 1)) * 0.6 + rng.uniform(0.0, 0.4)
    grid = grid + rng.normal(0.0, 0.03, (5, 5, 3))
    gx, gy = u * 4, v * 4
    x0, y0 = np.clip(np.floor(gx).astype(int), 0, 3), np.clip(np.floor(gy).astype(int), 0, 3)
    fx, fy = (gx - x0)[:, None], (gy - y0)[:, None]
    out = (grid[y0, x0] * (1 - fx) * (1 - fy) + grid[y0, x0 + 1] * fx * (1 - fy)
           + grid[y0 + 1, x0] * (1 - fx) * fy + grid[y0 + 1, x0 + 1] * fx * fy)  # fmt: skip
    return np.clip(out, 0.0, 1.0)


def _texture(colour: str, base: np.ndarray, rng: np.random.Generator):
    """A function of local points [N, 3] giving albedo [N, 3]: plain, stripes or checks."""
    mode = rng.choice(["plain", "stripes", "checks"], p=[0.6, 0.2, 0.2])
    if mode == "plain":
        return lambda p: np.broadcast_to(base, p.shape)
    light_first = colour in ("yellow", "orange", "pink")  # their dark tints read as other colours
    if colour not in _ACHROMATIC and (light_first or rng.random() < 0.5):
        other = np.clip(np.array([0.95, 0.88, 0.82]) + rng.normal(0, 0.03, 3), 0, 1)
    elif colour == "black":
        other = base + 0.12
    else:
        other = base * rng.uniform(0.6, 0.8)
    freq = rng.uniform(1.5, 3.0)
    axis = rng.normal(size=3)
    axis /= np.linalg.norm(axis)
    if mode == "stripes":
        def tex(p: np.ndarray) -> np.ndarray:
            m = (np.floor(freq * (p @ axis) * 2) % 2)[:, None]
            return base * (1 - m) + other * m
    else:
        def tex(p: np.ndarray) -> np.ndarray:
            m = (np.floor(freq * p).sum(1) % 2)[:, None]
            return base * (1 - m) + other * m
    return tex


def render_shape(colour: str, shape: str, rng: np.random.Generator, size: int = 64,
                 supersample: int = 2) -> np.ndarray:  # fmt: skip
    """One image [size, size, 3] (float32 in [0, 1]) of a `colour` `shape`, drawn with `rng`;
    a third of them also show part of another shape of another colour at a border, as crops
    of neighbouring objects do."""
    if colour not in _PALETTE or shape not in SHAPES:
        raise ValueError(f"not in the vocabulary: {colour!r} {shape!r}")
    n_px = size * supersample
    img, hit = _render(colour, shape, rng, n_px)
    if rng.random() < 0.35:
        other = COLOURS[rng.choice([i for i, c in enumerate(COLOURS) if c != colour])]
        side = int(n_px * rng.uniform(0.5, 1.0))
        patch, cover = _render(other, SHAPES[rng.integers(len(SHAPES))], rng, max(8, side // 2))
        rows = (np.arange(side) * patch.shape[0]) // side  # nearest-neighbour upscaling
        patch, cover = patch[rows][:, rows], cover[rows][:, rows]
        inside = int(side * rng.uniform(0.2, 0.6))  # how far it reaches into the image
        along = int(rng.integers(-side // 2, n_px - side // 2))
        edge = rng.integers(4)
        top = [inside - side, n_px - inside, along, along][edge]
        left = [along, along, inside - side, n_px - inside][edge]
        front = rng.random() < 0.5  # in front of the shape, else behind it
        for r in range(max(0, top), min(n_px, top + side)):
            cols = np.arange(max(0, left), min(n_px, left + side))
            if not len(cols):
                break
            m = cover[r - top, cols - left]
            if not front:
                m = m & ~hit[r, cols]
            img[r, cols[m]] = patch[r - top, cols[m] - left]
    img = img.reshape(size, supersample, size, supersample, 3).mean((1, 3))
    if rng.random() < 0.5:
        img = _blur(img, rng.uniform(0.3, 1.0))
    img = img + rng.normal(0.0, rng.uniform(0.0, 0.02), img.shape)
    return np.clip(img, 0.0, 1.0).astype(np.float32)


def _render(colour: str, shape: str, rng: np.random.Generator,
            n_px: int) -> tuple[np.ndarray, np.ndarray]:  # fmt: skip
    """Ray cast one framed shape: colours [n_px, n_px, 3] in [0, 1] (not yet averaged down)
    and the rays that hit the shape [n_px, n_px] (bool)."""
    obj = _draw_shape(shape, rng)
    base = _jitter_colour(colour, rng)
    texture = _texture(colour, base, rng)
    # Camera: perspective, at a random elevation and distance, looking at the shape.
    centre = np.zeros(3)
    if obj.kind in ("cone", "pyramid"):  # they stand on z = 0, apex up
        centre = np.array([0.0, 0.0, obj.params[1] * 0.4])
    low = 20 if obj.kind == "disc" else 5  # a flat disc seen edge-on is a line
    elev = rng.uniform(math.radians(low), math.radians(55))
    azim = rng.uniform(0, 2 * math.pi)
    dist = rng.uniform(4.0, 7.0)
    fwd = -np.array([math.cos(elev) * math.cos(azim), math.cos(elev) * math.sin(azim),
                     math.sin(elev)])  # fmt: skip
    eye = centre - dist * fwd
    right = np.cross(fwd, _EZ)
    right /= np.linalg.norm(right)
    down = np.cross(fwd, right)
    light = rng.normal(size=3)
    light[2] = abs(light[2]) + 0.8
    light = light / np.linalg.norm(light)
    if light @ fwd > 0.3:  # mostly lit from the camera's side
        light = light - 2 * (light @ fwd) * fwd * np.array([1.0, 1.0, 0.0])
        light /= np.linalg.norm(light)
    ambient = rng.uniform(0.25, 0.45)
    spec = rng.uniform(0.0, 0.35) if rng.random() < 0.6 else 0.0
    shininess = rng.uniform(10, 60)
    plate = rng.random() < 0.5
    plate_z = obj.zmin()
    plate_albedo = np.clip(rng.uniform(0.55, 1.0) + rng.normal(0, 0.02, 3), 0, 1)
    plate_radius = rng.uniform(2.0, 4.0)
    # Half the images light in linear space and encode to sRGB, as a renderer does (brighter
    # shadows); the rest shade the sRGB albedo directly, as the synthetic scene does.
    gamma = rng.random() < 0.5
    lin_in, lin_out = (_to_linear, _to_srgb) if gamma else (np.asarray, np.asarray)
    rot = obj.rot

    def cast(x: np.ndarray, y: np.ndarray, near: np.ndarray | None = None):
        """World rays through normalised image coordinates; their hit on the shape (only rays
        in `near` are tested, the others miss)."""
        d = x[:, None] * right + y[:, None] * down + fwd
        d /= np.linalg.norm(d, axis=1, keepdims=True)
        t_in = np.full(len(d), _INF)
        n = np.zeros_like(d)
        hit = np.zeros(len(d), bool)
        idx = np.arange(len(d)) if near is None else np.nonzero(near)[0]
        if len(idx):
            dl = d[idx] @ rot
            ti, to, nl = obj.local_hit(np.broadcast_to(eye @ rot, dl.shape), dl)
            hit[idx] = (ti < to) & (ti > 0) & (ti < 1e3)
            t_in[idx], n[idx] = ti, nl @ rot.T
        return d, t_in, n, hit

    # Framing: the silhouette's bounding box from a coarse pass, plus a 12 % margin.
    span = 1.6 * 2.2 / dist
    g = np.linspace(-span, span, 40)
    gx, gy = np.meshgrid(g, g)
    *_, hit = cast(gx.ravel(), gy.ravel())
    if hit.any():
        xs, ys = gx.ravel()[hit], gy.ravel()[hit]
        step = g[1] - g[0]
        x0, x1 = xs.min() - step / 2, xs.max() + step / 2
        y0, y1 = ys.min() - step / 2, ys.max() + step / 2
    else:
        x0 = y0 = -span / 2
        x1 = y1 = span / 2
    side = max(x1 - x0, y1 - y0) * 1.24 * math.exp(rng.uniform(-0.15, 0.25))
    stretch = math.exp(rng.uniform(-0.12, 0.12))
    wx, wy = side * stretch, side / stretch
    cx = (x0 + x1) / 2 + rng.normal(0, 0.04) * side
    cy = (y0 + y1) / 2 + rng.normal(0, 0.04) * side
    if rng.random() < 0.2:  # cut by the image border, as crops at the frame's edge are
        ang = rng.uniform(0, 2 * math.pi)
        shift = rng.uniform(0.12, 0.3)
        cx += math.cos(ang) * shift * wx
        cy += math.sin(ang) * shift * wy
    lin = (np.arange(n_px) + 0.5) / n_px
    uu, vv = np.meshgrid(lin, lin)
    u, v = uu.ravel(), vv.ravel()
    px, py = cx + (u - 0.5) * wx, cy + (v - 0.5) * wy
    pad = 2.5 * (g[1] - g[0])  # rays beyond the coarse silhouette's box cannot hit
    near = (px > x0 - pad) & (px < x1 + pad) & (py > y0 - pad) & (py < y1 + pad)
    d, t_in, n, hit = cast(px, py, near)
    img = _background(u, v, rng)
    if plate:
        dz = d[:, 2]
        tp = np.where(dz < -1e-6, (plate_z - eye[2]) / np.where(dz < -1e-6, dz, -1.0), -1.0)
        on = (tp > 0) & ~hit
        p = eye + tp[:, None] * d
        on &= np.hypot(p[:, 0], p[:, 1]) < plate_radius
        if on.any():
            ps = p[on] + light * 1e-4
            dl = np.broadcast_to(light, ps.shape)
            s_in, s_out, _ = obj.local_hit(ps @ rot, dl @ rot)
            shadow = (s_in < s_out) & (s_out > 0)
            shade = ambient + (1 - ambient) * max(light[2], 0.0) * (~shadow)
            img[on] = lin_out(lin_in(plate_albedo)[None] * shade[:, None])
    if hit.any():
        nn = n[hit]
        nn /= np.linalg.norm(nn, axis=1, keepdims=True) + 1e-12
        view = -d[hit]
        flip = (nn * view).sum(1) < 0  # the inside of a slab seen at a grazing angle
        nn[flip] *= -1
        lam = np.clip(nn @ light, 0.0, 1.0)
        half = light[None] + view
        half /= np.linalg.norm(half, axis=1, keepdims=True)
        hl = spec * np.clip((nn * half).sum(1), 0.0, 1.0) ** shininess * (lam > 0)
        p_local = (eye + t_in[hit, None] * d[hit]) @ rot
        alb = texture(p_local)
        amb = ambient * (0.5 if gamma else 1.0)
        img[hit] = lin_out(lin_in(alb) * (amb + (1 - amb) * lam)[:, None] + hl[:, None])
    return np.clip(img, 0.0, 1.0).reshape(n_px, n_px, 3), hit.reshape(n_px, n_px)


def _blur(img: np.ndarray, sigma: float) -> np.ndarray:
    """Separable Gaussian blur of [H, W, 3] with edge replication."""
    r = max(1, int(math.ceil(2.5 * sigma)))
    k = np.exp(-0.5 * (np.arange(-r, r + 1) / sigma) ** 2)
    k /= k.sum()
    pad = np.pad(img, ((r, r), (r, r), (0, 0)), mode="edge")
    h = sum(k[i] * pad[:, i : i + img.shape[1]] for i in range(2 * r + 1))
    return sum(k[i] * h[i : i + img.shape[0]] for i in range(2 * r + 1))


@dataclass(frozen=True)
class ShapeSet:
    """Generated images with their labels: `images` [n, S, S, 3] float32 in [0, 1]; `colours`
    and `shapes` [n] int indices into `COLOURS` and `SHAPES`."""

    images: np.ndarray
    colours: np.ndarray
    shapes: np.ndarray

    def captions(self, template: str = "a {colour} {shape}") -> list[str]:
        """The caption of each image."""
        pairs = zip(self.colours, self.shapes, strict=True)
        return [caption(COLOURS[c], SHAPES[s], template) for c, s in pairs]


def generate(pairs: list[tuple[str, str]], per_pair: int, seed: int = 0, size: int = 64,
             supersample: int = 2) -> ShapeSet:  # fmt: skip
    """`per_pair` images of each (colour, shape) in `pairs`, pair-major; image k of a pair
    depends only on (seed, pair, k)."""
    n = len(pairs) * per_pair
    images = np.zeros((n, size, size, 3), np.float32)
    colours = np.zeros(n, np.int64)
    shapes = np.zeros(n, np.int64)
    i = 0
    for colour, shape in pairs:
        ci, si = COLOURS.index(colour), SHAPES.index(shape)
        for k in range(per_pair):
            rng = np.random.default_rng([GENERATOR_VERSION, seed, ci, si, k])
            images[i] = render_shape(colour, shape, rng, size, supersample)
            colours[i], shapes[i] = ci, si
            i += 1
    return ShapeSet(images, colours, shapes)
