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
"""

from __future__ import annotations

import hashlib
import json
import math
import time as _time
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from sync4d.data.scene import DatasetError, as_number, as_number_array, cache_dir, check_pose

__all__ = [
    "SyntheticConfig",
    "SyntheticGroundTruth",
    "default_scene_dir",
    "ensure_default_scene",
    "load_ground_truth",
    "object_poses",
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
    (2, "at rest", 0.0, 0.2),
    (2, "sliding", 0.2, 0.8),
    (2, "at rest", 0.8, 1.0),
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
    s = _smoothstep((t - 0.2) / 0.6)
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
    ground = np.full((int(on.sum()), 3), GROUND_ALBEDO)
    rgb[on] = _shade(ground, np.broadcast_to([0.0, 0.0, 1.0], ground.shape))
    poses = object_poses(t)
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


def _fingerprint(cfg: SyntheticConfig) -> str:
    blob = json.dumps({"version": _VERSION, "config": asdict(cfg)}, sort_keys=True)
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
        poses = [object_poses(float(t))[obj.label] for t in times]
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
        "config": asdict(cfg),
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
        import sys

        t0 = _time.perf_counter()
        print(f"generating the synthetic scene in {root} ...", file=sys.stderr)
        write_synthetic_scene(root, cfg)
        print(f"  done in {_time.perf_counter() - t0:.1f}s", file=sys.stderr)
    return root
