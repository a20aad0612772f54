"""The embedded default scene: a small dynamic scene generated in code with its own renderer
(exact analytic ray casting in numpy, independent of the splatting rasterizer), written as a
D-NeRF/Blender dataset so the ordinary loader reads it.

Content (world z up, metres):

* ground plane z = 0, a plain light plate within |x|, |y| <= 1.25 (label 0, static background);
* label 1, "red ball" (radius 0.3): rolls along +x, hops 0.3 m into the air (rising, falling)
  and rolls on; it travels 0.5 m in all, turning about the y axis as it rolls, so its striped
  texture shows the rotation;
* label 2, "blue box" (0.7 x 0.5 x 0.4): at rest, slides 0.4 m across the ground while turning 45
  degrees about z with an eased (decelerating) profile, then rests again;
* label 3, "green pillar" (0.3 x 0.3 x 0.9): never moves (identity trajectory).

Every object's rigid trajectory (rotation R(t), translation t(t) with x_world = R x_local + t)
and its named state intervals ("rising", "falling", "sliding", ...) are written to
`ground_truth.json` for the later phases to test against. Cameras: a ring of training cameras
seeing every time step, and held-out test cameras at other azimuths on every k-th time step.

Each object is lit by a light fixed to the object (the direction `_LIGHT` in its own frame), so
its shading turns with it: a Gaussian's colour does not change over time in the model, and under
a world-fixed light a turning Lambertian surface changes colour, which biases any photometric
estimate of the turn toward less rotation (measured: the ball's recovered roll fell 16 % short).
The ground plate is lit in the world frame.

Two variants give SIFT something to match, for `write_orbit_video` (one camera moving on an
arc over the scene's time steps, encoded to a video file with the true cameras: what the
`sync4d process` test reconstructs): `SyntheticConfig.ground_texture = "blobs"` paints the plate
with seeded random coloured shapes, and `backdrop_radius` stands a wall painted alike around the
scene (static structure off the ground plane). The defaults keep the plain scene, and its cache
fingerprint unchanged.
"""

from __future__ import annotations

import functools
import hashlib
import json
import math
import time as _time
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from sync4d.data.scene import DatasetError, as_number, as_number_array, cache_dir, check_pose
from sync4d.events import GeneratingScene, emit

__all__ = [
    "SyntheticConfig",
    "SyntheticGroundTruth",
    "default_scene_dir",
    "ensure_default_scene",
    "load_ground_truth",
    "object_poses",
    "OrbitVideo",
    "write_orbit_video",
    "write_synthetic_scene",
]

GROUND_TRUTH = "ground_truth.json"
_VERSION = 3
_GROUND_HALF = 1.25
#: Albedo of the plain ground plate. A textured ground makes a poor default: within a
#: few-minute CPU budget its many static Gaussians paint time-averaged smears of the moving
#: objects and D_theta never learns their motion (measured: a 0.82/0.55 checkerboard left the
#: objects' per-Gaussian motion error at the static level after 3000 iterations, while this
#: plate and a white background both let it halve by iteration 750).
GROUND_ALBEDO = 1.0
_LIGHT = np.array([0.4, 0.3, 1.0]) / np.linalg.norm([0.4, 0.3, 1.0])
_AMBIENT, _DIFFUSE = 0.35, 0.65


@dataclass(frozen=True)
class SyntheticConfig:
    """Size of the generated scene: `size`x`size` images, `frames` time steps, `train_cameras`
    on a ring seeing every step, `test_cameras` between them on every `test_every`-th step."""

    size: int = 128
    frames: int = 40
    train_cameras: int = 8
    test_cameras: int = 2
    test_every: int = 4
    radius: float = 4.0
    elevation_deg: float = 30.0
    fov_deg: float = 40.0
    supersample: int = 2
    #: "plain" (the default plate) or "blobs" (seeded random coloured shapes: SIFT texture).
    ground_texture: str = "plain"
    #: Radius (metres) of a textured backdrop wall around the scene (a cylinder about the z
    #: axis, 4 m tall, seen from inside: the cameras must stand within it); 0: none, the sky
    #: is transparent.
    backdrop_radius: float = 0.0
    #: Every object holds its pose of time 0 at every time: a scene with no motion (tests of
    #: what sync4d skips when nothing moves; ground_truth.json's named states do not apply).
    still: bool = False
    #: The box's colour while it slides ("" keeps it blue throughout): a state that changes the
    #: object's appearance with its motion, which the paper's appearance-only scorer can find
    #: and its static-only ablation cannot (tests/phase3/test_phase3_claims.py). One of
    #: `SLIDING_COLOURS`.
    sliding_colour: str = ""

    def __post_init__(self) -> None:
        if self.sliding_colour and self.sliding_colour not in SLIDING_COLOURS:
            raise ValueError(f"sliding_colour must be '' or one of {sorted(SLIDING_COLOURS)}, "
                             f"not {self.sliding_colour!r}")  # fmt: skip
        if self.ground_texture not in ("plain", "blobs"):
            raise ValueError(
                f"ground_texture must be 'plain' or 'blobs', not {self.ground_texture!r}"
            )
        if not self.backdrop_radius >= 0.0:
            raise ValueError(f"backdrop_radius must be >= 0 (0: none), not {self.backdrop_radius}")


@dataclass(frozen=True)
class _Object:
    label: int
    name: str
    colour: str
    kind: str  # "sphere" or "box"
    size: tuple[float, float, float]  # sphere: (r, r, r); box: half extents
    static: bool


OBJECTS = (
    _Object(1, "red ball", "red", "sphere", (0.3, 0.3, 0.3), False),
    _Object(2, "blue box", "blue", "box", (0.35, 0.25, 0.2), False),
    _Object(3, "green pillar", "green", "box", (0.15, 0.15, 0.45), True),
)

#: Colours the box can take while it slides (`SyntheticConfig.sliding_colour`).
SLIDING_COLOURS = {"yellow": (0.95, 0.85, 0.1), "red": (0.9, 0.15, 0.1)}
#: The box's slide: start and end times.
SLIDE = (0.2, 0.8)
#: The ball's hop: take-off, apex and landing times.
HOP = (0.35, 0.55, 0.75)
#: Apex height of the hop above resting on the ground (metres).
HOP_HEIGHT = 0.3

#: Named states per object label as (state, t0, t1), times in [0, 1].
STATES: tuple[tuple[int, str, float, float], ...] = (
    (1, "rolling on the ground", 0.0, HOP[0]),
    (1, "rising", HOP[0], HOP[1]),
    (1, "falling", HOP[1], HOP[2]),
    (1, "rolling on the ground", HOP[2], 1.0),
    (2, "at rest", 0.0, SLIDE[0]),
    (2, "sliding", SLIDE[0], SLIDE[1]),
    (2, "at rest", SLIDE[1], 1.0),
    (3, "standing still", 0.0, 1.0),
)


def _rot_y(a: float) -> np.ndarray:
    c, s = math.cos(a), math.sin(a)
    return np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])


def _rot_z(a: float) -> np.ndarray:
    c, s = math.cos(a), math.sin(a)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def _smoothstep(x: float) -> float:
    x = min(1.0, max(0.0, x))
    return x * x * (3.0 - 2.0 * x)


def object_poses(t: float) -> dict[int, tuple[np.ndarray, np.ndarray]]:
    """Rigid pose (R [3, 3], translation [3]) of every object at time `t` in [0, 1]."""
    r = OBJECTS[0].size[0]
    # Ball: rolls, hops (a parabola from HOP[0] to HOP[2]), rolls on; x advances uniformly.
    z = r
    if HOP[0] < t < HOP[2]:
        z += HOP_HEIGHT * (1.0 - ((t - HOP[1]) / (HOP[1] - HOP[0])) ** 2)
    x = -0.25 + 0.5 * t
    ball = (_rot_y((x + 0.25) / r), np.array([x, 0.5, z]))
    # Box: rests, slides with an eased profile while turning 45 degrees, rests.
    s = _smoothstep((t - SLIDE[0]) / (SLIDE[1] - SLIDE[0]))
    start, end = np.array([0.45, -0.45]), np.array([0.05, -0.45])
    xy = start + s * (end - start)
    box = (_rot_z(math.pi / 4 * s), np.array([xy[0], xy[1], OBJECTS[1].size[2]]))
    pillar = (np.eye(3), np.array([-0.85, -0.8, OBJECTS[2].size[2]]))
    return {1: ball, 2: box, 3: pillar}


def _look_at_gl(eye: np.ndarray, target: np.ndarray) -> np.ndarray:
    """OpenGL camera-to-world (x right, y up, looking down -z) from `eye` towards `target`."""
    back = eye - target
    back = back / np.linalg.norm(back)
    right = np.cross([0.0, 0.0, 1.0], back)
    right /= np.linalg.norm(right)
    up = np.cross(back, right)
    m = np.eye(4)
    m[:3, 0], m[:3, 1], m[:3, 2], m[:3, 3] = right, up, back, eye
    return m


def _camera(cfg: SyntheticConfig, azimuth: float) -> np.ndarray:
    el = math.radians(cfg.elevation_deg)
    eye = cfg.radius * np.array(
        [math.cos(el) * math.cos(azimuth), math.cos(el) * math.sin(azimuth), math.sin(el)]
    )
    return _look_at_gl(eye, np.array([0.0, 0.0, 0.4]))


def _rays(cfg: SyntheticConfig, c2w_gl: np.ndarray, ss: int) -> tuple[np.ndarray, np.ndarray]:
    """Ray origin [3] and unit directions [size*ss, size*ss, 3] through sub-pixel centres, with
    the loader's intrinsics (fx = size / (2 tan(fov / 2)), principal point at the centre)."""
    n = cfg.size
    f = 0.5 * n / math.tan(0.5 * math.radians(cfg.fov_deg))
    sub = (np.arange(n * ss) + 0.5) / ss  # sub-pixel centres in pixel units
    u, v = np.meshgrid(sub, sub)
    d_cv = np.stack([(u - 0.5 * n) / f, (v - 0.5 * n) / f, np.ones_like(u)], -1)
    rot_cv = c2w_gl[:3, :3] @ np.diag([1.0, -1.0, -1.0])
    d = d_cv @ rot_cv.T
    return c2w_gl[:3, 3].copy(), d / np.linalg.norm(d, axis=-1, keepdims=True)


def _hit_sphere(o, d, centre, radius):
    oc = o - centre
    b = d @ oc
    c = oc @ oc - radius * radius
    disc = b * b - c
    t = -b - np.sqrt(np.maximum(disc, 0.0))
    return np.where((disc > 0) & (t > 1e-6), t, np.inf)


def _hit_box(o, d, rot, centre, half):
    """Distances to an oriented box and the hit normals in the box frame."""
    ol = rot.T @ (o - centre)
    dl = d @ rot  # = (R^T d) per ray
    with np.errstate(divide="ignore", invalid="ignore"):
        inv = 1.0 / dl
        t1 = (-np.asarray(half) - ol) * inv
        t2 = (np.asarray(half) - ol) * inv
    tmin = np.nanmax(np.minimum(t1, t2), axis=-1)
    tmax = np.nanmin(np.maximum(t1, t2), axis=-1)
    hit = (tmax >= tmin) & (tmin > 1e-6)
    return np.where(hit, tmin, np.inf), ol, dl


#: Texels per metre of the "blobs" ground texture and of the backdrop wall's texture.
_GROUND_TEXELS, _WALL_TEXELS = 256, 48
#: Height of the backdrop wall (metres).
_WALL_HEIGHT = 4.0


@functools.cache
def _blob_texture(width: int, height: int, count: int, size: tuple[float, float], seed: int):
    """float64 [height, width, 3] albedo in [0, 1], read-only: a grey base under `count`
    seeded random ellipses, rectangles and triangles of random colours, `size` texels
    (min, max radius) across, so that every patch looks different (texture SIFT can match)."""
    from PIL import Image, ImageDraw

    rng = np.random.default_rng(seed)
    im = Image.new("RGB", (width, height), (150, 150, 150))
    draw = ImageDraw.Draw(im)
    for _ in range(count):
        x, y = rng.uniform(0, width), rng.uniform(0, height)
        r = rng.uniform(*size)
        colour = tuple(int(c) for c in rng.integers(20, 246, 3))
        kind = rng.integers(3)
        if kind == 0:
            e = rng.uniform(0.4, 1.0)
            draw.ellipse([x - r, y - r * e, x + r, y + r * e], fill=colour)
        elif kind == 1:
            draw.rectangle([x - r, y - 0.6 * r, x + r, y + 0.6 * r], fill=colour)
        else:
            a = rng.uniform(0, 2 * math.pi) + np.array([0.0, 2.1, 4.2])
            draw.polygon(list(zip(x + r * np.cos(a), y + r * np.sin(a), strict=True)), fill=colour)
    tex = np.asarray(im, dtype=np.float64) / 255.0
    tex.flags.writeable = False  # cached: shared by every render
    return tex


def _sample(tex: np.ndarray, u: np.ndarray, v: np.ndarray, wrap: bool) -> np.ndarray:
    """Bilinear lookup [N, 3] of `tex` [H, W, 3] at texel coordinates `u` (column), `v` (row)
    [N], texel centres at +0.5; columns wrap around when `wrap`, else clamp."""
    h, w = tex.shape[:2]
    u, v = u - 0.5, np.clip(v - 0.5, 0.0, h - 1.001)
    u = np.mod(u, w) if wrap else np.clip(u, 0.0, w - 1.001)
    i, j = v.astype(int), u.astype(int)
    j1 = (j + 1) % w if wrap else j + 1
    fv, fu = (v - i)[:, None], (u - j)[:, None]
    top = tex[i, j] * (1 - fu) + tex[i, j1] * fu
    bottom = tex[i + 1, j] * (1 - fu) + tex[i + 1, j1] * fu
    return top * (1 - fv) + bottom * fv


def _ground_albedo(cfg: SyntheticConfig, p: np.ndarray) -> np.ndarray:
    """Albedo [N, 3] of the plate at ground points `p` [N, 3]."""
    if cfg.ground_texture == "plain":
        return np.full((len(p), 3), GROUND_ALBEDO)
    n = int(2 * _GROUND_HALF * _GROUND_TEXELS)
    tex = _blob_texture(n, n, 900, (0.02 * _GROUND_TEXELS, 0.15 * _GROUND_TEXELS), 7)
    u = (p[:, 0] + _GROUND_HALF) * _GROUND_TEXELS
    v = (p[:, 1] + _GROUND_HALF) * _GROUND_TEXELS
    return _sample(tex, u, v, wrap=False)


def _hit_wall(o: np.ndarray, d: np.ndarray, radius: float) -> tuple[np.ndarray, np.ndarray]:
    """Distances [...] to the inside of the backdrop wall (the cylinder x^2 + y^2 = radius^2,
    0 <= z <= _WALL_HEIGHT, seen from inside) and the hit points [..., 3]."""
    a = d[..., 0] ** 2 + d[..., 1] ** 2
    b = o[0] * d[..., 0] + o[1] * d[..., 1]
    c = o[0] ** 2 + o[1] ** 2 - radius**2
    with np.errstate(divide="ignore", invalid="ignore"):
        t = (-b + np.sqrt(np.maximum(b * b - a * c, 0.0))) / a
    t = np.where((a > 1e-12) & (c < 0), t, np.inf)
    p = o + np.where(np.isfinite(t), t, 0.0)[..., None] * d
    t = np.where((p[..., 2] >= 0.0) & (p[..., 2] <= _WALL_HEIGHT), t, np.inf)
    return t, p


def _wall_albedo(radius: float, p: np.ndarray) -> np.ndarray:
    """Albedo [N, 3] of the backdrop wall at points `p` [N, 3]: texture wrapped around it."""
    width = int(round(2 * math.pi * radius * _WALL_TEXELS))
    height = int(_WALL_HEIGHT * _WALL_TEXELS)
    count = int(60 * 2 * math.pi * radius * _WALL_HEIGHT)
    tex = _blob_texture(width, height, count, (0.08 * _WALL_TEXELS, 0.4 * _WALL_TEXELS), 11)
    u = np.arctan2(p[:, 1], p[:, 0]) * radius * _WALL_TEXELS
    v = (_WALL_HEIGHT - p[:, 2]) * _WALL_TEXELS
    return _sample(tex, u, v, wrap=True)


def _shade(base: np.ndarray, normal: np.ndarray) -> np.ndarray:
    lam = np.clip(normal @ _LIGHT, 0.0, 1.0)
    return base * (_AMBIENT + _DIFFUSE * lam)[..., None]


def _render(cfg: SyntheticConfig, c2w: np.ndarray, t: float) -> tuple[np.ndarray, np.ndarray]:
    """RGBA uint8 [H, W, 4] (sky transparent) and label mask uint8 [H, W] at time `t`."""
    ss = cfg.supersample
    o, d = _rays(cfg, c2w, ss)
    shape = d.shape[:2]
    depth = np.full(shape, np.inf)
    label = np.full(shape, -1, np.int16)  # -1 sky, 0 ground, k objects
    rgb = np.zeros(shape + (3,))
    # Ground plane.
    with np.errstate(divide="ignore", invalid="ignore"):
        tg = np.where(d[..., 2] < -1e-9, -o[2] / d[..., 2], np.inf)
    p = o + np.where(np.isfinite(tg), tg, 0.0)[..., None] * d
    on = np.isfinite(tg) & (np.abs(p[..., 0]) <= _GROUND_HALF) & (np.abs(p[..., 1]) <= _GROUND_HALF)
    depth[on], label[on] = tg[on], 0
    ground = _ground_albedo(cfg, p[on])
    rgb[on] = _shade(ground, np.broadcast_to([0.0, 0.0, 1.0], ground.shape))
    if cfg.backdrop_radius > 0.0:
        tw, pw = _hit_wall(o, d, cfg.backdrop_radius)
        wall = tw < depth
        depth[wall], label[wall] = tw[wall], 0
        rgb[wall] = 0.9 * _wall_albedo(cfg.backdrop_radius, pw[wall])
    poses = object_poses(0.0 if cfg.still else t)
    for obj in OBJECTS:
        rot, centre = poses[obj.label]
        if obj.kind == "sphere":
            th = _hit_sphere(o, d, centre, obj.size[0])
            near = th < depth
            if not near.any():
                continue
            ph = o + th[near][:, None] * d[near]
            n_world = (ph - centre) / obj.size[0]
            local = n_world @ rot  # R^T n
            lon = np.arctan2(local[:, 1], local[:, 0])
            lat = np.arcsin(np.clip(local[:, 2], -1, 1))
            stripe = (np.floor(lon / (math.pi / 4)) + np.floor(lat / (math.pi / 4))) % 2
            base = np.where(stripe[:, None] > 0, [0.9, 0.12, 0.1], [0.95, 0.85, 0.8])
            rgb[near] = _shade(base, local)
        else:
            th, ol, dl = _hit_box(o, d, rot, centre, obj.size)
            near = th < depth
            if not near.any():
                continue
            pl = ol + th[near][:, None] * dl[near]
            rel = pl / np.asarray(obj.size)
            axis = np.argmax(np.abs(rel), axis=-1)
            n_local = np.zeros_like(pl)
            n_local[np.arange(len(pl)), axis] = np.sign(rel[np.arange(len(pl)), axis])
            tiles = (np.floor(pl / 0.2).sum(-1)) % 2
            colour = {"blue": [0.15, 0.3, 0.9], "green": [0.2, 0.75, 0.25]}[obj.colour]
            if obj.label == 2 and cfg.sliding_colour and SLIDE[0] < t < SLIDE[1]:
                colour = list(SLIDING_COLOURS[cfg.sliding_colour])
            dark = np.asarray(colour) * 0.6
            base = np.where(tiles[:, None] > 0, colour, dark)
            rgb[near] = _shade(base, n_local)
        depth[near], label[near] = th[near], obj.label
    n = cfg.size
    cover = (label >= 0).reshape(n, ss, n, ss).mean(axis=(1, 3))
    colour = (
        rgb.reshape(n, ss, n, ss, 3).sum(axis=(1, 3)) / np.maximum(cover * ss * ss, 1)[..., None]
    )
    rgba = np.concatenate([colour, cover[..., None]], -1)
    rgba = (np.clip(rgba, 0, 1) * 255 + 0.5).astype(np.uint8)
    centre_sample = label[ss // 2 :: ss, ss // 2 :: ss]
    return rgba, np.maximum(centre_sample, 0).astype(np.uint8)


def _config_dict(cfg: SyntheticConfig) -> dict:
    """`cfg` as stored and fingerprinted; the default plain ground and no backdrop are left
    out, so scenes cached before those fields existed keep their fingerprint."""
    d = asdict(cfg)
    if d["ground_texture"] == "plain":
        del d["ground_texture"]
    if d["backdrop_radius"] == 0.0:
        del d["backdrop_radius"]
    if not d["still"]:
        del d["still"]
    if not d["sliding_colour"]:
        del d["sliding_colour"]
    return d


def _fingerprint(cfg: SyntheticConfig) -> str:
    blob = json.dumps({"version": _VERSION, "config": _config_dict(cfg)}, sort_keys=True)
    return hashlib.sha256(blob.encode()).hexdigest()[:16]


def _is_complete(root: Path, cfg: SyntheticConfig) -> bool:
    try:
        gt = json.loads((root / GROUND_TRUTH).read_text())
    except (OSError, ValueError):
        return False
    return gt.get("fingerprint") == _fingerprint(cfg)


def write_synthetic_scene(out_dir: str | Path, config: SyntheticConfig | None = None) -> Path:
    """Render the scene into `out_dir` as a D-NeRF dataset (transforms_{train,val,test}.json,
    RGBA PNGs, masks/{split}/*.png, masks/labels.json) plus ground_truth.json. Does nothing
    when `out_dir` already holds the scene for the same config; ground_truth.json is written
    last, so an interrupted generation is redone."""
    from PIL import Image

    cfg = config or SyntheticConfig()
    root = Path(out_dir)
    if _is_complete(root, cfg):
        return root
    (root / GROUND_TRUTH).unlink(missing_ok=True)
    times = np.linspace(0.0, 1.0, cfg.frames)
    fov = math.radians(cfg.fov_deg)
    train_az = [2 * math.pi * k / cfg.train_cameras for k in range(cfg.train_cameras)]
    test_az = [
        2 * math.pi * (k + 0.5) / cfg.test_cameras + math.pi / cfg.train_cameras
        for k in range(cfg.test_cameras)
    ]
    splits: dict[str, list[tuple[str, float, np.ndarray]]] = {"train": [], "test": []}
    for i, t in enumerate(times):
        for c, az in enumerate(train_az):
            splits["train"].append((f"t{i:03d}_c{c}", float(t), _camera(cfg, az)))
        if i % cfg.test_every == 0:
            for c, az in enumerate(test_az):
                splits["test"].append((f"t{i:03d}_c{c}", float(t), _camera(cfg, az)))
    for split, frames in splits.items():
        (root / split).mkdir(parents=True, exist_ok=True)
        (root / "masks" / split).mkdir(parents=True, exist_ok=True)
        records = []
        for name, t, c2w in frames:
            rgba, mask = _render(cfg, c2w, t)
            Image.fromarray(rgba, "RGBA").save(root / split / f"{name}.png")
            Image.fromarray(mask, "L").save(root / "masks" / split / f"{name}.png")
            records.append(
                {"file_path": f"./{split}/{name}", "time": t, "transform_matrix": c2w.tolist()}
            )
        doc = json.dumps({"camera_angle_x": fov, "frames": records}, indent=1)
        (root / f"transforms_{split}.json").write_text(doc)
        if split == "test":
            (root / "transforms_val.json").write_text(doc)
    labels = {"0": "background"} | {str(o.label): o.name for o in OBJECTS}
    (root / "masks" / "labels.json").write_text(json.dumps(labels, indent=1))
    objects = []
    for obj in OBJECTS:
        poses = [object_poses(0.0 if cfg.still else float(t))[obj.label] for t in times]
        objects.append(
            {
                "id": obj.label, "name": obj.name, "colour": obj.colour, "kind": obj.kind,
                "size": list(obj.size), "static": obj.static,
                "rotations": [r.tolist() for r, _ in poses],
                "translations": [tr.tolist() for _, tr in poses],
            }
        )  # fmt: skip
    gt = {
        "version": _VERSION,
        "fingerprint": _fingerprint(cfg),
        "config": _config_dict(cfg),
        "times": times.tolist(),
        "objects": objects,
        "states": [{"object": k, "state": s, "t0": a, "t1": b} for k, s, a, b in STATES],
        "scene_bounds": [[-_GROUND_HALF, -_GROUND_HALF, 0.0], [_GROUND_HALF, _GROUND_HALF, 1.0]],
    }
    tmp = root / (GROUND_TRUTH + ".tmp")
    tmp.write_text(json.dumps(gt))
    tmp.replace(root / GROUND_TRUTH)
    return root


@dataclass
class OrbitVideo:
    """A video of the scene seen by one moving camera: frame k shows time `times[k]` from
    `c2w[k]` ([N, 4, 4] OpenGL camera-to-world, world z up, metres); square `size`-pixel
    frames with focal length `focal` (pixels) and the principal point at the centre; `extent`
    is the diagonal of the scene's bounding box (metres)."""

    path: Path
    times: np.ndarray
    c2w: np.ndarray
    focal: float
    size: int
    fps: float
    extent: float


def write_orbit_video(
    path: str | Path,
    config: SyntheticConfig | None = None,
    frames: int = 48,
    arc_deg: float = 100.0,
    start_deg: float = -70.0,
    swing_deg: float = 15.0,
    fps: float = 24.0,
    codec: str = "libx264",
) -> OrbitVideo:
    """Render `frames` views of the scene, one per time step evenly spaced over [0, 1], from a
    camera moving on an arc of `arc_deg` degrees of azimuth (from `start_deg`) at `config`'s
    radius and field of view, looking at the scene's centre, its elevation swinging by
    +-`swing_deg` over one sine period (an orbit about one fixed axis is a critical motion
    for self-calibration: it leaves the focal length undetermined), and encode them with PyAV
    (`codec`, near-lossless) at `fps` frames per second, the sky composited on white. The
    default config is a 256-pixel variant with the "blobs" ground and a backdrop wall (6 m):
    the plain default scene is too bare for SIFT. Returns the true cameras."""
    import av

    cfg = config or SyntheticConfig(
        size=256, radius=3.6, ground_texture="blobs", backdrop_radius=6.0
    )
    if cfg.size % 2:
        raise ValueError(f"video frames need an even size (yuv420p), got {cfg.size}")
    path = Path(path)
    times = np.linspace(0.0, 1.0, frames)
    azimuths = np.radians(start_deg + arc_deg * times)
    elevations = np.radians(cfg.elevation_deg + swing_deg * np.sin(2.0 * math.pi * times))
    eyes = cfg.radius * np.stack(
        [np.cos(elevations) * np.cos(azimuths), np.cos(elevations) * np.sin(azimuths),
         np.sin(elevations)], -1,
    )  # fmt: skip
    c2w = np.stack([_look_at_gl(eye, np.array([0.0, 0.0, 0.4])) for eye in eyes])
    with av.open(str(path), "w") as container:
        stream = container.add_stream(codec, rate=round(fps))
        stream.width = stream.height = cfg.size
        stream.pix_fmt = "yuv420p"
        if codec == "libx264":
            stream.options = {"crf": "8", "preset": "medium"}
        else:
            stream.bit_rate = 20_000_000
        for t, cam in zip(times, c2w, strict=True):
            rgba, _ = _render(cfg, cam, float(t))
            a = rgba[..., 3:4].astype(np.float64) / 255.0
            rgb = rgba[..., :3] * a + 255.0 * (1.0 - a)
            image = av.VideoFrame.from_ndarray((rgb + 0.5).astype(np.uint8), format="rgb24")
            for packet in stream.encode(image):
                container.mux(packet)
        for packet in stream.encode():
            container.mux(packet)
    focal = 0.5 * cfg.size / math.tan(0.5 * math.radians(cfg.fov_deg))
    bounds = np.array([[-_GROUND_HALF, -_GROUND_HALF, 0.0], [_GROUND_HALF, _GROUND_HALF, 1.0]])
    extent = float(np.linalg.norm(bounds[1] - bounds[0]))
    return OrbitVideo(path, times, c2w, focal, cfg.size, fps, extent)


@dataclass
class SyntheticGroundTruth:
    """Known motion of the synthetic scene: `rotations` [K, T, 3, 3] and `translations`
    [K, T, 3] (object-to-world at `times` [T]), per-object `ids`, `names`, `static` flags, and
    `states` as (object id, state, t0, t1)."""

    times: np.ndarray
    ids: list[int]
    names: list[str]
    static: list[bool]
    rotations: np.ndarray
    translations: np.ndarray
    states: list[tuple[int, str, float, float]]
    bounds: np.ndarray

    @property
    def extent(self) -> float:
        """Diagonal length of the scene's bounding box (metres)."""
        return float(np.linalg.norm(self.bounds[1] - self.bounds[0]))

    def motion_errors(
        self, rotations: np.ndarray, translations: np.ndarray, times: np.ndarray, label: int
    ) -> tuple[np.ndarray, np.ndarray]:
        """Per-frame error of a recovered motion of object `label` relative to its first frame:
        rotation error (degrees) [T] and object-centre error (metres) [T]. `rotations` [T, 3, 3]
        and `translations` [T, 3] map canonical to world at `times` [T] (e.g. one object's rows
        of Phase 2's motion export); each time must be one of the ground truth's frame times."""
        if label not in self.ids:
            raise ValueError(f"motion_errors: no object {label} (ids {self.ids})")
        a, b = np.asarray(rotations, np.float64), np.asarray(translations, np.float64)
        if a.shape != (len(times), 3, 3) or b.shape != (len(times), 3):
            raise ValueError(
                f"motion_errors: expected rotations [{len(times)}, 3, 3] and translations "
                f"[{len(times)}, 3], got {list(a.shape)} and {list(b.shape)}"
            )
        gi = self.ids.index(label)
        rg, tg = self.rotations[gi], self.translations[gi]
        rows = [int(np.argmin(np.abs(self.times - t))) for t in np.asarray(times, np.float64)]
        if not np.allclose(self.times[rows], times, atol=1e-6):
            raise ValueError("motion_errors: times must be frame times of the ground truth")
        # Motion relative to the first frame: recovered a_t a_0^-1 and b_t - (a_t a_0^-1) b_0.
        a_rel = a @ np.linalg.inv(a[0])
        b_rel = b - a_rel @ b[0]
        rg_rel = rg[rows] @ rg[rows[0]].T
        cos = (np.trace(a_rel @ rg_rel.transpose(0, 2, 1), axis1=1, axis2=2) - 1.0) / 2.0
        rot = np.degrees(np.arccos(np.clip(cos, -1.0, 1.0)))
        centre = np.linalg.norm(a_rel @ tg[rows[0]] + b_rel - tg[rows], axis=1)
        return rot, centre

    def export_errors(self, export: dict[str, np.ndarray]) -> dict[str, tuple[float, float]]:
        """Mean rotation error (degrees) and mean centre error (% of `extent`) of every object,
        by name, for a Phase 2 motion export (`rotations` [K, T, 3, 3], `translations`
        [K, T, 3], `times` [T]; the checkpoint's `export.*` tensors)."""
        out = {}
        for name, label in zip(self.names, self.ids, strict=True):
            rot, centre = self.motion_errors(
                export["rotations"][label], export["translations"][label], export["times"], label
            )
            out[name] = (float(rot.mean()), float(100.0 * centre.mean() / self.extent))
        return out


def load_ground_truth(root: str | Path) -> SyntheticGroundTruth:
    """Read `root/ground_truth.json`; `DatasetError` naming the file when it is malformed."""
    path = Path(root) / GROUND_TRUTH
    try:
        gt = json.loads(path.read_text())
    except FileNotFoundError:
        raise DatasetError(path, "ground truth file is missing") from None
    except ValueError as e:
        raise DatasetError(path, f"invalid JSON ({e})") from None
    try:
        times = as_number_array(gt["times"], path, "'times'")
        objs = gt["objects"]
        rot = as_number_array([o["rotations"] for o in objs], path, "objects' 'rotations'")
        tr = as_number_array([o["translations"] for o in objs], path, "objects' 'translations'")
        states = [(int(s["object"]), str(s["state"]),
                   as_number(s["t0"], path, f"state {j} 't0'"),
                   as_number(s["t1"], path, f"state {j} 't1'"))
                  for j, s in enumerate(gt["states"])]  # fmt: skip
        bounds = as_number_array(gt["scene_bounds"], path, "'scene_bounds'")
        ids = [int(o["id"]) for o in objs]
        names = [str(o["name"]) for o in objs]
        static = [bool(o["static"]) for o in objs]
    except DatasetError:
        raise
    except (KeyError, TypeError, ValueError) as e:
        raise DatasetError(path, f"malformed ground truth ({type(e).__name__}: {e})") from None
    k, t = len(objs), len(times)
    if rot.shape != (k, t, 3, 3) or tr.shape != (k, t, 3) or bounds.shape != (2, 3):
        raise DatasetError(
            path,
            f"expected rotations [{k}, {t}, 3, 3], translations [{k}, {t}, 3] and bounds "
            f"[2, 3], got {list(rot.shape)}, {list(tr.shape)}, {list(bounds.shape)}",
        )
    if not (np.isfinite(rot).all() and np.isfinite(tr).all() and np.isfinite(times).all()):
        raise DatasetError(path, "ground truth contains NaN or inf")
    for i, obj in zip(ids, rot, strict=True):
        for j, r in enumerate(obj):
            check_pose(r, path, f"object {i} rotation at time index {j}")
    return SyntheticGroundTruth(times, ids, names, static, rot, tr, states, bounds)


def default_scene_dir() -> Path:
    """Where the default scene is cached: `synthetic-vN` under :func:`cache_dir`."""
    return cache_dir() / f"synthetic-v{_VERSION}"


def ensure_default_scene(config: SyntheticConfig | None = None) -> Path:
    """The default scene's folder, generated first if missing (a few seconds)."""
    root = default_scene_dir()
    cfg = config or SyntheticConfig()
    if not _is_complete(root, cfg):
        t0 = _time.perf_counter()
        emit(GeneratingScene(str(root)))
        write_synthetic_scene(root, cfg)
        emit(GeneratingScene(str(root), _time.perf_counter() - t0))
    return root
