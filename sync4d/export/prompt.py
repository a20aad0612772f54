"""A plain-text summary of a scene description for an LLM (`export RUN --prompt FILE`): the
objects, what each does over time, and their interactions, generated from the description's
JSON alone (`prompt_text(load(path).doc)`), so the text says nothing the file does not.

`count_tokens` counts the text's tokens with the tokenizer at hand: the offline encoder's
WordPiece tokenizer (all-MiniLM-L6-v2's, installed with sync4d); an LLM's BPE tokenizer gives a
somewhat different count.
"""

from __future__ import annotations

import numpy as np

__all__ = ["count_tokens", "prompt_text"]


def _t(x: float) -> str:
    return f"{x:.2f}"


def _v(v) -> str:
    return "(" + ", ".join(f"{x:.2f}" for x in v) + ")"


def _spans(items: list[dict]) -> str:
    return ", ".join(f"{_t(s['t0'])}-{_t(s['t1'])}" for s in items)


def _object_lines(obj: dict, track: dict, up: np.ndarray) -> list[str]:
    size = obj["extent"]["size_max"]
    rigid = obj["rigid_share"]
    still = all(s["state"] == "at rest" for s in obj["segments"]) and any(
        s["start"] == 0 and s["end"] == len(track["visible"]) - 1 for s in obj["segments"])
    # Phase 2's rigid share is 0 where an object never moved: say "static" there.
    kind = ("static" if still else "moves rigidly" if rigid >= 0.9 else "moves mostly rigidly"
            if rigid >= 0.6 else "deforms as it moves") + f" (rigid share {rigid:.2f})"
    head = (f"- {obj['name']} (id {obj['id']}): {obj['gaussians']:,} Gaussians, about "
            f"{size[0]:.2f} x {size[1]:.2f} x {size[2]:.2f}, {kind}")
    if obj["vocabulary"]:
        head += "; looks like " + ", ".join(f"\"{v['text']}\" ({v['similarity']:.2f})"
                                            for v in obj["vocabulary"])  # fmt: skip
    lines = [head + "."]
    c = np.asarray(track["centroid"], float)
    speed = np.asarray(track["kinematics"]["speed"], float)
    height = c @ up
    lines.append(f"  Path: from {_v(c[0])} to {_v(c[-1])}; highest at frame "
                 f"{int(np.argmax(height))}, fastest at frame {int(np.argmax(speed))} "
                 f"(speed {speed.max():.2f}).")  # fmt: skip
    by_state: dict[str, list[dict]] = {}
    for s in obj["segments"]:
        by_state.setdefault(s["state"], []).append(s)
    if by_state:
        lines.append("  Motion: " + "; ".join(f"{state} {_spans(segs)}"
                                              for state, segs in by_state.items()) + ".")
    else:
        lines.append("  Motion: no motion state holds for long enough to report.")
    for slot in obj["slots"]:
        when = _spans(slot["intervals"]) or "never active"
        margin = f", margin {slot['margin']:.2f}" if "margin" in slot else ""
        lines.append(f"  Matches \"{slot['text']}\" ({slot['source']}, score "
                     f"{slot['score']:.2f}{margin}): {when}.")  # fmt: skip
    return lines


_VERBS = {"approach": "approaches", "contact": "touches", "separation": "moves away from"}


def prompt_text(doc: dict) -> str:
    """The summary of the scene description `doc` (the JSON as loaded)."""
    meta = doc["metadata"]
    names = {0: "the background"} | {o["id"]: o["name"] for o in doc["objects"]}
    tracks = {t["id"]: t for t in doc["tracks"]}
    up = np.asarray(meta["axes"]["up"], float)
    frames = meta["frames"]
    ckpt = (meta["checkpoint"]["sha256"] or "none")[:12]
    dataset = meta["run"]["dataset"] or meta["run"]["name"]
    out = [
        f"A dynamic 3D scene ({dataset}) reconstructed by sync4d {meta['sync4d']} "
        f"(checkpoint {ckpt}).",
        f"Time runs from 0 to 1 over {frames['count']} frames; lengths are in the scene's "
        f"world units (the objects span about {meta['scale']['extent']:.2f}); up is "
        f"{_v(up)}. Intervals below are start-end times.",
        "",
        f"Objects ({len(doc['objects'])}):",
    ]
    for obj in doc["objects"]:
        out += _object_lines(obj, tracks[obj["id"]], up)
    attached = {slot["text"] for obj in doc["objects"] for slot in obj["slots"]}
    loose = [t for t in doc.get("texts", []) if t not in attached]
    if loose:
        margin = meta.get("thresholds", {}).get("slot_margin")
        why = f" by {margin:.2f} or more" if margin is not None else ""
        out.append("No object matches " + ", ".join(f"\"{t}\"" for t in loose) + " (no "
                   f"object's appearance is nearer to it than the others'{why}).")  # fmt: skip
    out += ["", "Interactions:"]
    if not doc["events"]:
        out.append("- none detected.")
    pairs: dict[tuple[str, int, int], list[dict]] = {}
    for e in doc["events"]:
        pairs.setdefault((e["kind"], *e["objects"]), []).append(e)
    for (kind, a, b), evs in sorted(pairs.items(), key=lambda kv: kv[1][0]["start"]):
        n = len(evs)
        times = _spans(evs)
        count = f" {n} times" if n > 1 else ""
        out.append(f"- {names[a]} {_VERBS[kind]} {names[b]}{count}: {times}.")
    return "\n".join(out) + "\n"


def count_tokens(text: str) -> tuple[int, str]:
    """The number of tokens of `text` and the tokenizer that counted them (the offline
    encoder's all-MiniLM-L6-v2 WordPiece, special tokens excluded)."""
    from tokenizers import Tokenizer

    from sync4d.phase3.encoders.minilm import find_minilm_dir

    tok = Tokenizer.from_file(str(find_minilm_dir() / "tokenizer.json"))
    tok.no_truncation()
    return len(tok.encode(text, add_special_tokens=False).ids), "all-MiniLM-L6-v2 WordPiece"
