#!/usr/bin/env sh
# Serve a run to AI agents over the Model Context Protocol (docs/mcp.md). With PORT set: serve it
# over HTTP at http://127.0.0.1:$PORT/mcp until Ctrl-C. Without: what an agent does over stdio,
# through the MCP SDK's own client: start `sync4d serve RUN`, list its tools, ask a query, track
# the top object, list the events and save a render (serve-render.png), then stop the server.
# With FOURDGS set to a .4dgs file exported from the run (sync4d export RUN --4dgs FILE), the
# server is started with --4dgs FILE and `describe` names it.
set -eu
RUN="${1:-runs/synthetic}"
PY="${PYTHON:-python3}"
if [ -n "${PORT:-}" ]; then
    exec "$PY" -m sync4d serve "$RUN" --http "$PORT"
fi
"$PY" - "$RUN" "${2:-the red ball while it is falling}" <<'PYEOF'
import asyncio
import base64
import json
import os
import sys

from mcp import Client
from mcp.client.stdio import StdioServerParameters

run, text = sys.argv[1], sys.argv[2]


async def main() -> None:
    extra = ["--4dgs", os.environ["FOURDGS"]] if os.environ.get("FOURDGS") else []
    server = StdioServerParameters(command=sys.executable,
                                   args=["-m", "sync4d", "serve", run, *extra])
    async with Client(server) as client:
        tools = (await client.list_tools()).tools
        print("tools:", ", ".join(t.name for t in tools))
        for f in (await client.call_tool("describe", {})).structured_content["files"]:
            print(f"file: {f['path']} ({f['format']}, {f['bytes']:,} bytes, {f['tracks']} tracks)")
        result = await client.call_tool("query", {"text": text})
        if result.is_error:
            sys.exit(result.content[0].text)
        top = result.structured_content["answer"]
        spans = ", ".join(f"{i['t0']:.2f}-{i['t1']:.2f}" for i in top["intervals"]) or "never"
        print(f"query {text!r}: {top['name']} (score {top['score']:.3f}), active {spans}")
        track = (await client.call_tool("track", {"object": top["name"]})).structured_content
        for f in track["frames"][:: max(1, len(track["frames"]) // 5)]:
            print(f"  t={f['t']:.2f} position={json.dumps(f['position'])} speed={f['speed']:.2f}")
        events = (await client.call_tool("events", {"object": top["name"]})).structured_content
        for e in events["events"]:
            print(f"  {e['kind']} {' / '.join(e['names'])}: {e['t0']:.2f}-{e['t1']:.2f}")
        t = top["intervals"][0]["t0"] if top["intervals"] else 0.5
        image, info = (await client.call_tool("render", {"t": t})).content
        with open("serve-render.png", "wb") as f:
            f.write(base64.b64decode(image.data))
        print(f"render: serve-render.png ({info.text})")


asyncio.run(main())
PYEOF
