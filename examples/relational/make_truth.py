"""Ground truth of the relational question sets in this folder, from the true states only.

    python examples/relational/make_truth.py [--data /path/to/dnerf/bouncingballs]

writes ``embedded.json`` (the embedded synthetic scene: its true object poses,
`sync4d.data.synthetic.object_poses`, and its named states) and, when the D-NeRF scene is there,
``bouncingballs.json`` (each ball's centre triangulated from its instance masks in the 150
training views: the ray through the mask's centroid in each view, with a second-difference
smoothness prior over time; no reconstruction of ours is read).

Each question below is written with its meaning by hand (the form, the subject, the state or
event, the relation), independently of how `sync4d.phase3.relational` reads the wording; the
answer is then computed by operators of this folder's own (`truth_ops.py`, the documented
semantics, no code of the method) on the *true* states, and stored as the object, its time
ranges (normalised time, half a truth frame of slack each side) and, for counts, the number.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np
import truth_ops

from sync4d.data import synthetic as syn

HERE = Path(__file__).resolve().parent


def Q(question, form, subject=None, atoms=(), n=None, quantity=None, direction=None,
      relation=None, negated=False, target=0):  # fmt: skip
    """A question and its meaning: `subject` an object name (None: every object), `atoms`
    state / event names, `relation` (word, other object name or None for "it", its atoms,
    negated)."""
    return dict(question=question, form=form, subject=subject, atoms=list(atoms), n=n,
                quantity=quantity, direction=direction, relation=relation, negated=negated,
                target=target)  # fmt: skip


def truth_answer(spec, names, times, centres, states):
    """The stored answer of question `spec` (`truth_ops.answer` on the true states): the
    object, its time ranges (half a frame of slack each side) and, for counts, the number."""
    height = centres[..., 2]
    speed = np.linalg.norm(np.gradient(centres, times, axis=1), axis=-1)
    k, spans, count = truth_ops.answer(spec, names, states, height, speed)
    dt = float(np.median(np.diff(times)))
    ranges = [[max(0.0, float(times[s]) - dt / 2), min(1.0, float(times[e]) + dt / 2)]
              for s, e in spans]  # fmt: skip
    out = {"question": spec["question"], "form": spec["form"], "object": names[k],
           "times": ranges}  # fmt: skip
    if spec["form"] in ("count", "count-select"):
        out["count"] = count
    return out


# --- the embedded scene ----------------------------------------------------------------------

EMBEDDED = [
    # ordinals over objects
    Q("which object starts moving first", "ordinal-objects", atoms=["moving"], n=1),
    Q("which thing comes to a stop first", "ordinal-objects", atoms=["at rest"], n=1),
    Q("the first object to leave the ground", "ordinal-objects", atoms=["rising"], n=1),
    Q("which object is the last to begin moving", "ordinal-objects", atoms=["moving"], n=-1),
    # ordinals within one object's episodes
    Q("the second time the red ball touches the floor", "ordinal-episodes", "red ball",
      ["contact"], n=2),
    Q("the first episode of the blue box standing still", "ordinal-episodes", "blue box",
      ["at rest"], n=1),
    Q("the last time the blue box is motionless", "ordinal-episodes", "blue box", ["at rest"],
      n=-1),
    Q("the red ball's first contact with the ground", "ordinal-episodes", "red ball",
      ["contact"], n=1),
    # counts
    Q("how many times does the blue box stop", "count", "blue box", ["at rest"]),
    Q("how often is the red ball on the ground", "count", "red ball", ["contact"]),
    Q("how many times does the red ball go up", "count", "red ball", ["rising"]),
    Q("the object that rises only once", "count-select", atoms=["rising"], n=1),
    Q("which object is at rest twice", "count-select", atoms=["at rest"], n=2),
    # relations
    Q("the red ball while the blue box is sliding", "relation", "red ball",
      relation=("while", "blue box", ["moving"], False)),
    Q("the blue box while the red ball is not on the ground", "relation", "blue box",
      relation=("while", "red ball", ["contact"], True)),
    Q("the red ball before it jumps", "relation", "red ball",
      relation=("before", None, ["rising"], False)),
    Q("the blue box after it stops moving", "relation", "blue box",
      relation=("after", None, ["moving"], True)),
    Q("the red ball rolling after it lands", "relation", "red ball", ["moving"],
      relation=("after", None, ["contact"], False)),
    Q("the blue box during the red ball's descent", "relation", "blue box",
      relation=("during", "red ball", ["falling"], False)),
    Q("the green pillar until the blue box starts to move", "relation", "green pillar",
      relation=("until", "blue box", ["moving"], False)),
    Q("which object turns first", "ordinal-objects", atoms=["turning"], n=1),
    Q("how many times does the blue box slide", "count", "blue box", ["moving"]),
    Q("the blue box before the red ball jumps", "relation", "blue box",
      relation=("before", "red ball", ["rising"], False)),
    Q("the red ball while the blue box is at rest", "relation", "red ball",
      relation=("while", "blue box", ["at rest"], False)),
    # extremes
    Q("the highest object", "extreme", quantity="height", direction="max"),
    Q("the lowest object", "extreme", quantity="height", direction="min"),
    Q("which object moves the fastest", "extreme", atoms=["moving"], quantity="speed",
      direction="max"),
    Q("the object that stays still the longest", "extreme", atoms=["at rest"],
      quantity="duration", direction="max"),
    Q("the shortest rise", "extreme", atoms=["rising"], quantity="duration", direction="min"),
    # negation
    Q("the object that never moves", "negation", atoms=["moving"]),
    Q("which object never turns", "negation", atoms=["turning"]),
    Q("the red ball when it is not touching the ground", "relation", "red ball",
      relation=("while", None, ["contact"], True)),
    Q("the object that is never at rest", "negation", atoms=["at rest"]),
]


def embedded_truth() -> dict:
    times = np.linspace(0.0, 1.0, 201)
    names = [o.name for o in syn.OBJECTS]
    centres = np.array([[syn.object_poses(float(t))[o.label][1] for t in times]
                        for o in syn.OBJECTS])  # fmt: skip
    radius = np.array([min(o.size) for o in syn.OBJECTS])
    k, t = len(names), len(times)
    contact = np.ones((k, t), bool)  # the box and the pillar stand on the plate throughout
    contact[0] = ~((times > syn.HOP[0]) & (times < syn.HOP[2]))  # the ball's hop
    turning = np.zeros((k, t))
    turning[0] = 1.0  # the ball rolls throughout
    s = (times - syn.SLIDE[0]) / (syn.SLIDE[1] - syn.SLIDE[0])
    turning[1] = ((s > 0) & (s < 1)).astype(float)
    states = truth_ops.true_states(times, centres, radius, contact, turning)
    return {"version": 1, "kind": "relational", "scene": "embedded synthetic scene",
            "truth": "sync4d.data.synthetic.object_poses (true poses) and STATES, on 201 "
                     "times; examples/relational/make_truth.py",
            "questions": [truth_answer(q, names, times, centres, states)
                          for q in EMBEDDED]}  # fmt: skip


# --- bouncingballs ---------------------------------------------------------------------------

BB_NAMES = ["red ball", "green ball", "blue ball"]


def _solve(rays: np.ndarray, keep: np.ndarray, smooth: float) -> np.ndarray:
    """Points [T, 3] nearest the rays [T, 2, 3] (origin, unit direction) kept by `keep` [T],
    with a second-difference smoothness prior of weight `smooth`."""
    t = len(rays)
    d2 = np.zeros((t - 2, t))
    for i in range(t - 2):
        d2[i, i:i + 3] = [1.0, -2.0, 1.0]
    a, b = np.kron(d2.T @ d2, np.eye(3)) * smooth, np.zeros(3 * t)
    for i in range(t):
        if not keep[i]:
            continue
        o, d = rays[i]
        q = np.eye(3) - np.outer(d, d)
        a[3 * i:3 * i + 3, 3 * i:3 * i + 3] += q
        b[3 * i:3 * i + 3] += q @ o
    return np.linalg.solve(a, b).reshape(t, 3)


def triangulate(root: Path, smooth: float = 20.0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(times [T], centres [3, T, 3], radii [3]) of the three balls from their instance masks
    (a ball's radius: the median over the views of its largest inscribed disc at its
    distance): in each
    view the ray through the centre of the largest disc inside the ball's mask (a shadow or
    highlight that the colour threshold attached to the ball moves the mask's mean, not
    this), solved with a smoothness prior; then again without the views where that disc is
    under 85 % of the ball's median size at its distance (another ball hides part of it)."""
    from PIL import Image
    from scipy.ndimage import distance_transform_edt

    meta = json.loads((root / "transforms_train.json").read_text())
    frames = sorted(meta["frames"], key=lambda f: f["time"])
    t = len(frames)
    rays = np.full((3, t, 2, 3), np.nan)
    size = np.full((3, t), np.nan)  # inscribed radius / focal
    for i, f in enumerate(frames):
        m = np.asarray(Image.open(root / "masks" / (f["file_path"][2:] + ".png")))
        w = m.shape[1]
        focal = 0.5 * w / np.tan(0.5 * meta["camera_angle_x"])
        c2w = np.asarray(f["transform_matrix"], np.float64)
        for k in (1, 2, 3):
            sel = m == k
            if sel.sum() < 5:
                continue
            dist = distance_transform_edt(sel)
            ys, xs = np.nonzero(dist >= dist.max() - 0.5)
            d = np.array([(xs.mean() + 0.5 - w / 2) / focal, -(ys.mean() + 0.5 - w / 2) / focal,
                          -1.0])  # fmt: skip
            rays[k - 1, i] = [c2w[:3, 3], c2w[:3, :3] @ (d / np.linalg.norm(d))]
            size[k - 1, i] = dist.max() / focal
    out, radii = np.zeros((3, t, 3)), np.zeros(3)
    for k in range(3):
        seen = ~np.isnan(rays[k]).any(axis=(1, 2))
        first = _solve(rays[k], seen, smooth)
        radius = size[k] * np.linalg.norm(first - rays[k, :, 0], axis=1)
        keep = seen & (radius >= 0.85 * np.nanmedian(radius))
        out[k] = _solve(rays[k], keep, smooth)
        radii[k] = float(np.nanmedian(radius[keep]))
    return np.array([f["time"] for f in frames], np.float64), out, radii


#: A ball touches the plate while its centre is within this fraction of its radius of its
#: height at the bounce (the lowest point of a local dip of its true height): the contact's
#: definition, written here from the true heights alone (`Phase3Config.contact_band` states
#: the same meaning for the reconstruction).
TOUCH_BAND = 0.05


def true_contacts(height: np.ndarray, radii: np.ndarray) -> np.ndarray:
    """Contact with the plate [K, T] from the true centre heights [K, T]: around each bounce
    (a local minimum of a ball's height within half its radius of its lowest height over the
    clip, where the plate is; a wobble in mid-air is higher), the frames within `TOUCH_BAND`
    radii of that minimum."""
    k, t = height.shape
    out = np.zeros((k, t), bool)
    for j in range(k):
        h = height[j]
        for f in range(1, t - 1):
            at_plate = h[f] - h.min() <= 0.5 * radii[j]
            if at_plate and h[f] <= h[f - 1] and h[f] < h[f + 1]:
                top = h[f] + TOUCH_BAND * radii[j]
                s = f
                while s > 0 and h[s - 1] <= top:
                    s -= 1
                e = f
                while e < t - 1 and h[e + 1] <= top:
                    e += 1
                out[j, s:e + 1] = True
    return out


BB = [
    # ordinals over objects
    Q("which ball lands first", "ordinal-objects", atoms=["contact"], n=1),
    Q("which ball is the last to touch the ground", "ordinal-objects", atoms=["contact"], n=-1),
    Q("the first ball to hit the floor", "ordinal-objects", atoms=["contact"], n=1),
    Q("the third ball to land", "ordinal-objects", atoms=["contact"], n=3),
    Q("the second ball to bounce", "ordinal-objects", atoms=["contact"], n=2),
    # ordinals within one ball's episodes
    Q("the second bounce of the red ball", "ordinal-episodes", "red ball", ["contact"], n=2),
    Q("the blue ball's first bounce", "ordinal-episodes", "blue ball", ["contact"], n=1),
    Q("the last time the red ball touches down", "ordinal-episodes", "red ball", ["contact"],
      n=-1),
    Q("the first time the green ball goes up", "ordinal-episodes", "green ball", ["rising"],
      n=1),
    Q("the second descent of the blue ball", "ordinal-episodes", "blue ball", ["falling"], n=2),
    # counts
    Q("how many times does the red ball bounce", "count", "red ball", ["contact"]),
    Q("how many times does the green ball hit the ground", "count", "green ball",
      ["contact"]),
    Q("how often does the blue ball strike the plate", "count", "blue ball", ["contact"]),
    Q("the ball that bounces only once", "count-select", atoms=["contact"], n=1),
    Q("which ball bounces exactly one time", "count-select", atoms=["contact"], n=1),
    Q("which ball bounces the fewest times", "count-select", atoms=["contact"],
      quantity="count", direction="min"),
    # relations
    Q("the blue ball while the red ball is falling", "relation", "blue ball",
      relation=("while", "red ball", ["falling"], False)),
    Q("the red ball after it first lands", "relation", "red ball",
      relation=("after", None, ["contact"], False)),
    Q("the green ball before it hits the ground", "relation", "green ball",
      relation=("before", None, ["contact"], False)),
    Q("the green ball until the blue ball touches the plate", "relation", "green ball",
      relation=("until", "blue ball", ["contact"], False)),
    Q("the red ball rising after the green ball lands", "relation", "red ball", ["rising"],
      relation=("after", "green ball", ["contact"], False)),
    Q("the blue ball during the green ball's descent", "relation", "blue ball",
      relation=("during", "green ball", ["falling"], False)),
    Q("the green ball going up while the blue ball comes down", "relation", "green ball",
      ["rising"], relation=("while", "blue ball", ["falling"], False)),
    # extremes
    Q("the highest ball", "extreme", quantity="height", direction="max"),
    Q("which ball drops the fastest", "extreme", atoms=["falling"], quantity="speed",
      direction="max"),
    Q("the fastest ball", "extreme", quantity="speed", direction="max"),
    Q("the longest fall", "extreme", atoms=["falling"], quantity="duration", direction="max"),
    Q("which ball rises highest", "extreme", atoms=["rising"], quantity="height",
      direction="max"),
    # negation
    Q("the red ball while it is not falling", "relation", "red ball",
      relation=("while", None, ["falling"], True)),
    Q("which ball never bounces after the red ball's second bounce", "negation",
      atoms=["contact"], relation=("after", "red ball", ["contact"], False, 2)),
    Q("which ball never touches the ground before the blue ball does", "negation",
      atoms=["contact"], relation=("before", "blue ball", ["contact"], False)),
]


#: The same meanings in other words (none of them tuned on): a separate file, so the table
#: can tell the set the method was developed on from wordings it never saw.
BB_PARAPHRASES = [
    Q("Which ball reaches the plate first?", "ordinal-objects", atoms=["contact"], n=1),
    Q("which ball touches down last", "ordinal-objects", atoms=["contact"], n=-1),
    Q("When does the red ball hit the floor for the second time?", "ordinal-episodes",
      "red ball", ["contact"], n=2),
    Q("the blue ball's final impact with the ground", "ordinal-episodes", "blue ball",
      ["contact"], n=-1),
    Q("How many times does the blue ball come down onto the plate?", "count", "blue ball",
      ["contact"]),
    Q("count the bounces of the green ball", "count", "green ball", ["contact"]),
    Q("Which ball hits the ground a single time?", "count-select", atoms=["contact"], n=1),
    Q("What is the red ball doing while the blue ball descends?", "relation", "red ball",
      relation=("while", "blue ball", ["falling"], False)),
    Q("the blue ball after the red ball touches the floor", "relation", "blue ball",
      relation=("after", "red ball", ["contact"], False)),
    Q("the red ball before it strikes the plate", "relation", "red ball",
      relation=("before", None, ["contact"], False)),
    Q("Which ball is the quickest?", "extreme", quantity="speed", direction="max"),
    Q("which ball is higher than the others", "extreme", quantity="height", direction="max"),
    Q("the ball that drops for the longest time", "extreme", atoms=["falling"],
      quantity="duration", direction="max"),
    Q("which ball never hits the plate after the red ball's second landing", "negation",
      atoms=["contact"], relation=("after", "red ball", ["contact"], False, 2)),
]


def bb_truth(root: Path, questions: list[dict] | None = None) -> dict:
    times, centres, radii = triangulate(root)
    contact = true_contacts(centres[..., 2], radii)
    states = truth_ops.true_states(times, centres, radii, contact)
    return {"version": 1, "kind": "relational", "scene": "D-NeRF bouncingballs",
            "truth": "ball centres triangulated from the instance masks of the 150 training "
                     "views (masks/train, labels.json) with a smoothness prior; contact: "
                     "within 5 % of the ball's radius of its height at each bounce "
                     "(true_contacts); "
                     "examples/relational/make_truth.py",
            "questions": [truth_answer(q, BB_NAMES, times, centres, states)
                           for q in questions or BB]}  # fmt: skip


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", default=str(HERE.parents[2] / "shared" / "data" / "dnerf" /
                                          "bouncingballs"))  # fmt: skip
    ap.add_argument("--out", default=str(HERE))
    args = ap.parse_args()
    out = Path(args.out)
    (out / "embedded.json").write_text(json.dumps(embedded_truth(), indent=1) + "\n")
    data = Path(args.data)
    if (data / "masks" / "train").is_dir():
        (out / "bouncingballs.json").write_text(json.dumps(bb_truth(data), indent=1) + "\n")
        (out / "bouncingballs-paraphrases.json").write_text(
            json.dumps(bb_truth(data, BB_PARAPHRASES), indent=1) + "\n")
    print(f"wrote {out}")


if __name__ == "__main__":
    main()
