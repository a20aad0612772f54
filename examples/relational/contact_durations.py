"""Contact durations of a bouncingballs run against the truth from the instance masks.

    python examples/relational/contact_durations.py RUN [--data DIR] [--out FILE]

For each ball, each bounce: the contact the run's state model finds
(`sync4d.phase3.states.ground_contacts`, on RUN's language field) beside the true contact
(`make_truth.true_contacts`: the triangulated centre within 5 % of the ball's radius of its
height at the bounce), matched by overlap, with onset, offset and duration in frames and the
differences. Prints a table and writes the rows to FILE (JSON; default
docs/bench/contact-durations-bouncingballs.json).
"""

from __future__ import annotations

import argparse
import datetime
import json
import sys
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))

from make_truth import BB_NAMES, triangulate, true_contacts  # noqa: E402

from sync4d.phase3 import states  # noqa: E402
from sync4d.phase3.activation import intervals  # noqa: E402
from sync4d.phase3.query import field_settings  # noqa: E402
from sync4d.phase3.store import FieldError, load_field  # noqa: E402
from sync4d.report import align_table  # noqa: E402


def rows(run: Path, data: Path) -> list[dict]:
    """One row per true bounce (and per found contact that matches none)."""
    field = load_field(run)
    if not set(BB_NAMES) <= set(field.names):
        raise FieldError(f"{run}: its objects are {', '.join(field.names)}; this compares "
                         f"bouncingballs' {', '.join(BB_NAMES)}")  # fmt: skip
    cfg = field_settings(field)
    times, centres, radii = triangulate(data)
    truth = true_contacts(centres[..., 2], radii)
    ft = np.asarray(field.times, np.float64)
    # the truth's frames on the field's frames (the same training times, nearest)
    idx = np.abs(ft[:, None] - times[None, :]).argmin(1)
    found = states.ground_contacts(field, cfg)
    out = []
    for k, name in enumerate(BB_NAMES):
        label = field.labels[field.names.index(name)]
        mine = [(c.start, c.end) for c in found if c.label == label]
        used = set()
        for s, e in intervals(truth[k][idx]):
            match = next((m for m in mine if m[0] <= e and s <= m[1] and m not in used), None)
            row = {"ball": name, "true": [s, e], "true_frames": e - s + 1}
            if match is not None:
                used.add(match)
                row.update(found=list(match), found_frames=match[1] - match[0] + 1,
                           onset_diff=match[0] - s, offset_diff=match[1] - e,
                           duration_diff=(match[1] - match[0]) - (e - s))  # fmt: skip
            out.append(row)
        for m in mine:
            if m not in used:
                out.append({"ball": name, "true": None, "found": list(m),
                            "found_frames": m[1] - m[0] + 1})  # fmt: skip
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("run")
    ap.add_argument("--data", default=str(HERE.parents[2] / "shared" / "data" / "dnerf" /
                                          "bouncingballs"))  # fmt: skip
    ap.add_argument("--out", default=str(HERE.parents[1] / "docs" / "bench" /
                                         "contact-durations-bouncingballs.json"))  # fmt: skip
    args = ap.parse_args()
    masks = Path(args.data) / "masks" / "train"
    if not masks.is_dir():
        sys.exit(f"contact_durations: {masks} is missing; give the bouncingballs folder with "
                 "its instance masks as --data")  # fmt: skip
    try:
        rs = rows(Path(args.run), Path(args.data))
    except FieldError as e:
        sys.exit(f"contact_durations: {e}")

    def cell(r: dict, k: str) -> str:
        v = r.get(k)
        return "-" if v is None else (f"{v[0]}-{v[1]}" if isinstance(v, list) else str(v))

    print(align_table(["ball", "true frames", "found frames", "true n", "found n", "onset",
                       "offset", "duration"],
                      [[r["ball"], cell(r, "true"), cell(r, "found"), cell(r, "true_frames"),
                        cell(r, "found_frames"), cell(r, "onset_diff"), cell(r, "offset_diff"),
                        cell(r, "duration_diff")] for r in rs]))  # fmt: skip
    doc = {"benchmark": "contact-durations", "scene": "D-NeRF bouncingballs",
           "date": datetime.datetime.now(datetime.UTC).isoformat(timespec="seconds"),
           "command": " ".join(["python", *sys.argv]), "run": args.run,
           "truth": "make_truth.true_contacts: the triangulated centre within 5 % of the "
                    "ball's radius of its height at each bounce", "rows": rs}  # fmt: skip
    Path(args.out).write_text(json.dumps(doc, indent=1) + "\n")
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
