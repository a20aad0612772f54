"""Results out (issue 42): a run as files other tools read.

* the **scene description** (`model` types it, torch-free: `Scene`; `describe` builds it,
  `scene` writes and loads it, `schema` holds its JSON Schema, generated from the model,
  `prompt` turns it into text for an LLM): objects, tracks, motion segments, pairwise events
  and language slots of a Phase 2 run with a language field;
* **splat files** (`splats`): the Gaussians, canonical or deformed to a time, as 3DGS PLY
  (gsplat's property order plus ``object_id``), SPZ, and 4D sequences (brush's delta-frame PLY
  or a zip of PLYs).

Above the phases and the run folder (it reads `load_run` and `load_field`), beside the
pipeline; the command line's `export` and the viewer use it. Names are imported on first use
(gsply, behind SPZ, only when an SPZ is written or read). docs/export.md has the formats.
"""

from sync4d.lazy import lazy_exports

#: Public names and the module that defines each, imported on first use.
_EXPORTS = {
    "ExportError": "errors",
    "SceneSettings": "describe", "describe": "describe",
    "Scene": "model",
    **dict.fromkeys(("SceneDescription", "SceneError", "SceneObject", "Track", "load",
                     "with_embeddings", "write_scene"), "scene"),
    "prompt_text": "prompt", "count_tokens": "prompt",
    **dict.fromkeys(
        ("Splats", "default_times", "is_sequence_folder", "ply_properties", "read_ply",
         "read_sequence", "read_spz", "sequence_frame_name", "sequence_sidecar", "splats_at",
         "write_ply", "write_sequence", "write_sequence_folder", "write_spz"), "splats"),
}  # fmt: skip

__all__, __getattr__ = lazy_exports(__name__, _EXPORTS)
