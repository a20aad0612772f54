"""For agents: a run on the Model Context Protocol (`sync4d serve RUN`, docs/mcp.md).

`tools` answers without any protocol (`RunTools`: the scene description, queries, tracks,
events and renders of one run, loaded lazily or prepared in the background from the start,
torch only for what renders or describes; bounded caches, nothing written to the run);
`cache` keeps the scene description between starts, outside the run folder; `server` puts it
on MCP through the official `mcp` SDK (typed tools, the scene JSON and the LLM prompt as
resources; stdio or HTTP). It stands on the viewer's floor, above the export
room (the description) and Phase 3 (queries), below the commands; it imports neither the
viewer nor the commands. Names are imported on first use (the SDK only with `server`).
"""

from sync4d.lazy import lazy_exports

#: Public names and the module that defines each, imported on first use.
_EXPORTS = {"RunTools": "tools", "ToolProblem": "tools", "build_server": "server",
            "serve": "server"}  # fmt: skip

__all__, __getattr__ = lazy_exports(__name__, _EXPORTS)
