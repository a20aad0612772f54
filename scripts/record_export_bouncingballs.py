"""Write docs/bench/export-bouncingballs.json: docs/export.md's "Bouncingballs, measured" figures,
re-measured by exporting a bouncingballs run with Phase 3 (`sync4d export RUN --vocab
examples/bouncingballs-vocab.txt --query "a ball touching the floor" --scene ... --prompt ...`
into a temporary folder) and reading the files back, with the date, the command and the machine
(docs/bench/README.md):

- the run: its final test PSNR, training seconds and per-object Gaussian counts;
- `scene.json` and its side file's sizes, frames, objects, events by kind;
- the prompt's token count (`sync4d.export.prompt.count_tokens`) and whether it is the committed
  examples/bouncingballs-prompt.txt byte for byte;
- each vocabulary entry's static margin (cosine of the best object minus the second best,
  from the side file's embeddings) and whether it got a slot;
- every contact with the background: its times, evidence and the smallest gap to the surface
  under the ball inside it, in the ball's radii (the Phase 3 field's `gaps`).

    OMP_NUM_THREADS=1 python scripts/record_export_bouncingballs.py RUN
"""

from __future__ import annotations

import contextlib
import datetime
import hashlib
import io
import json
import sys
import tempfile
from pathlib import Path

import numpy as np

from sync4d.bench.measure import machine_info
from sync4d.cli import main as cli
from sync4d.export import load
from sync4d.export.prompt import count_tokens
from sync4d.phase3.store import load_field

ROOT = Path(__file__).resolve().parents[1]
OUT = ROOT / "docs" / "bench" / "export-bouncingballs.json"
VOCAB = ROOT / "examples" / "bouncingballs-vocab.txt"
EXAMPLE = ROOT / "examples" / "bouncingballs-prompt.txt"
QUERY = "a ball touching the floor"


def run_facts(run: Path) -> dict:
    rows = [json.loads(ln) for ln in (run / "metrics.jsonl").read_text().splitlines()]
    last = [r for r in rows if "final" in r][-1]
    return {
        "run": str(run),
        "source": "the run's metrics.jsonl (its final evaluation), read, not re-run",
        "phases": json.loads((run / "run.json").read_text()).get("config", {}).get("phases"),
        "final_test_psnr": last["final"]["psnr"],
        "final_iteration": last["iteration"],
        "train_seconds": last["train_seconds"],
        "train_minutes": last["train_seconds"] / 60,
    }


def main() -> int:
    if len(sys.argv) != 2:
        print(__doc__, file=sys.stderr)
        return 2
    run = Path(sys.argv[1])
    with tempfile.TemporaryDirectory() as tmp:
        scene_path, prompt_path = Path(tmp) / "bb-scene.json", Path(tmp) / "bb-prompt.txt"
        argv = ["export", str(run), "--vocab", str(VOCAB), "--query", QUERY,
                "--scene", str(scene_path), "--prompt", str(prompt_path)]  # fmt: skip
        with contextlib.redirect_stdout(io.StringIO()) as printed:
            assert cli(argv) == 0
        side = next(p for p in Path(tmp).iterdir() if p.name.startswith("bb-scene.embeddings"))
        scene = load(scene_path)
        raw = json.loads(scene_path.read_text())
        prompt = prompt_path.read_text()
        sizes = {"scene_json_bytes": scene_path.stat().st_size,
                 "side_file_bytes": side.stat().st_size}  # fmt: skip
    tokens, tokenizer = count_tokens(prompt)
    objects = raw["objects"]
    names = {o["id"]: o["name"] for o in objects}
    # Static margins of the vocabulary entries (texts: the --vocab entries, then the queries).
    static = np.asarray(scene.embeddings["static"], np.float64)
    texts = np.asarray(scene.embeddings["texts"], np.float64)
    vocab = [ln.strip() for ln in VOCAB.read_text().splitlines() if ln.strip()]
    slotted = {s["text"] for o in objects for s in o.get("slots", []) if s["source"] == "vocab"}
    margins = {}
    for i, text in enumerate(vocab):
        cos = static @ texts[i] / (np.linalg.norm(static, axis=1) * np.linalg.norm(texts[i]))
        order = np.argsort(-cos)
        margins[text] = {"object": names[objects[order[0]]["id"]],
                         "static_margin": float(cos[order[0]] - cos[order[1]]),
                         "slot": text in slotted}  # fmt: skip
    # Contacts with the background and the smallest gap inside each, in the ball's radii.
    field = load_field(run)
    labels = [int(v) for v in field.labels]
    bg = list(field.gap_labels).index(0)
    contacts = []
    for e in raw["events"]:
        if e["kind"] != "contact" or e["objects"][1] != 0:
            continue
        k = labels.index(e["objects"][0])
        gaps = np.asarray(field.gaps[k, bg], np.float64)[e["start"] : e["end"] + 1]
        smallest = float(np.nanmin(gaps) / field.radius[k])
        contacts.append({"object": names[e["objects"][0]], "t0": e["t0"], "t1": e["t1"],
                         "evidence": e["evidence"], "smallest_gap_radii": smallest})  # fmt: skip
    kinds: dict[str, int] = {}
    for e in raw["events"]:
        kinds[e["kind"]] = kinds.get(e["kind"], 0) + 1
    record = {
        "date": datetime.datetime.now(datetime.UTC).isoformat(timespec="seconds"),
        "command": "OMP_NUM_THREADS=1 python scripts/record_export_bouncingballs.py RUN "
        f"(RUN: {run}; export: sync4d {' '.join(argv[:1])} RUN --vocab "
        f'examples/bouncingballs-vocab.txt --query "{QUERY}" --scene ... --prompt ...)',
        "machine": machine_info(),
        "run": run_facts(run),
        "objects": [
            {
                "name": o["name"],
                "gaussians": o["gaussians"],
                "radius": o["radius"],
                "observed_frames": o["observed_frames"],
            }
            for o in objects
        ],  # fmt: skip
        "frames": len(raw["metadata"]["frames"]["times"]),
        "events": len(raw["events"]),
        "events_by_kind": kinds,
        **sizes,
        "scene_json_kb": sizes["scene_json_bytes"] / 1e3,
        "side_file_kb": sizes["side_file_bytes"] / 1e3,
        "prompt": {
            "tokens": tokens,
            "tokenizer": tokenizer,
            "sha256": hashlib.sha256(prompt.encode()).hexdigest(),
            "same_as_example": prompt == EXAMPLE.read_text(),
        },  # fmt: skip
        "slot_margin": raw["metadata"]["thresholds"]["slot_margin"],
        "vocabulary_margins": margins,
        "contacts_with_background": contacts,
        "printed": printed.getvalue().strip().splitlines()[-3:],
    }
    OUT.write_text(json.dumps(record, indent=1) + "\n")
    print(json.dumps(record, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
