"""The 4D viewer (`sync4d view RUN`): a run in the browser through viser.

`state` holds what is shown without any web server (the run, reloaded as it trains; its splats
at a time split by object, from `sync4d.export.splats`; tracks; the field's answers; renders
through sync4d's rasterizer), `app` puts it on a viser page (time slider, play, objects,
query box, timeline, render button). Above the export room, below the commands.
"""

from sync4d.lazy import lazy_exports

#: Public names and the module that defines each, imported on first use (viser only with app).
_EXPORTS = {"Viewer": "app", "ViewerState": "state", "SplatArrays": "state",
            "ObjectInfo": "state"}  # fmt: skip

__all__, __getattr__ = lazy_exports(__name__, _EXPORTS)
