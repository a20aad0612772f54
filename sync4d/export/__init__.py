"""Results out: the scene description (scene.py, schema.py, prompt.py, describe.py: objects,
their motion and names as structured data) and splat files (splats.py: the Gaussians of a run,
canonical or at a time, as 3DGS PLY, SPZ and 4D delta-frame PLY or zip files). Reads runs
through `sync4d.runs.load_run`; beside the pipeline, below the commands. Names are imported on
first use (gsply, behind SPZ, is imported only when an SPZ is written or read).
"""

from sync4d.lazy import lazy_exports

#: Public names and the module that defines each.
_EXPORTS = {
    "ExportError": "errors",
    **dict.fromkeys(
        ("Splats", "default_times", "ply_properties", "read_ply", "read_sequence", "read_spz",
         "splats_at", "write_ply", "write_sequence", "write_spz"), "splats"),
}  # fmt: skip

__all__, __getattr__ = lazy_exports(__name__, _EXPORTS)
