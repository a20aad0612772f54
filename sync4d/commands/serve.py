"""``sync4d serve RUN``: the run for AI agents, on the Model Context Protocol (`sync4d.serve`,
docs/mcp.md). Over stdio by default (a desktop MCP client starts it as a subprocess and talks
on its stdin and stdout; nothing else is written to stdout), or with ``--http [HOST:]PORT``
over streamable HTTP at ``http://HOST:PORT/mcp`` (``--sse``: the older SSE transport at
``/sse``).

The run folder is checked before serving (a missing folder or checkpoint is refused with the
command to run); the field, the run and torch load on the first call that needs them, so the
server answers its client's handshake at once. A run without Phase 3 is served: its renders
work, and the tools that need the language field say which command builds it.
"""

from __future__ import annotations

import argparse
import signal
import sys

from sync4d.commands.view import port_problem
from sync4d.errors import Sync4dError
from sync4d.options import add_encoder, add_threads

__all__ = ["add_arguments", "main", "parse_address"]


def add_arguments(p: argparse.ArgumentParser) -> None:
    """The description and arguments of ``sync4d serve`` (`sync4d.cli`)."""
    p.description = (
        "Serve a run to an MCP client (an LLM desktop app, an agent): tools describe (the "
        "scene description), query (which object matches a text, and when), track (an "
        "object's pose, velocity and box over an interval), events (contacts, approaches, "
        "motion segments) and render (a PNG at a time and camera), and the scene JSON and LLM "
        "prompt as resources. Over stdio (the client starts it), or --http. docs/mcp.md has a "
        "client's configuration."
    )
    p.add_argument("run", metavar="RUN", help="run folder written by 'fit' (the language field "
                   "of --phases 3 answers query, describe, track and events)")
    p.add_argument("--http", default=None, metavar="[HOST:]PORT",
                   help="serve over HTTP (streamable HTTP at http://HOST:PORT/mcp) instead of "
                   "stdio; HOST defaults to 127.0.0.1 (this machine only)")
    p.add_argument("--sse", action="store_true",
                   help="with --http: the older SSE transport (at /sse) for clients without "
                   "streamable HTTP")
    p.add_argument("--4dgs", dest="fourdgs", default=None, metavar="FILE.4dgs",
                   help="a .4dgs file exported from this run (sync4d export RUN --4dgs FILE): "
                   "describe names it (refused when it is of another checkpoint)")
    add_encoder(p)
    add_threads(p, "torch and the rasterizer")

#: Address of ``--http PORT`` without a host: this machine only.
DEFAULT_HOST = "127.0.0.1"


def parse_address(text: str) -> tuple[str, int]:
    """``PORT``, ``HOST:PORT`` or ``[IPv6]:PORT`` as (host, port); ValueError saying why not."""
    host, sep, port = text.rpartition(":")
    if not sep:
        host, port = DEFAULT_HOST, text
    host = host.strip("[]") or DEFAULT_HOST
    if not port.isdigit() or not 0 < int(port) < 65536:
        raise ValueError(f"--http {text}: give PORT or HOST:PORT with a port in 1-65535")
    return host, int(port)


def _interrupt(signum: int, frame: object) -> None:
    """SIGTERM ends the server as Ctrl-C does."""
    raise KeyboardInterrupt


def main(args: argparse.Namespace) -> int:
    """Run `serve` with parsed `args`; the exit status."""
    from sync4d.serve.tools import RunTools

    tools = RunTools(args.run, encoder=args.encoder, threads=args.threads, fourdgs=args.fourdgs)
    try:
        tools.check()
        http = parse_address(args.http) if args.http else None
        if args.sse and http is None:
            raise ValueError("--sse is a transport over HTTP: add --http [HOST:]PORT")
        if http is not None:
            problem = port_problem(*http)
            if problem:
                raise ValueError(problem.replace("--port", "--http"))
        try:
            from sync4d.serve.server import serve
        except ImportError as e:
            raise ValueError(f"serve needs the MCP SDK ({e}): pip install 'mcp>=2,<3'") from None
    except (Sync4dError, ValueError) as e:  # ValueError: --http, --sse, no MCP SDK
        print(f"serve: {e}", file=sys.stderr)
        return 2
    if http is None:
        print(f"serve: {tools.run_dir} over stdio (the MCP client ends it)", file=sys.stderr)
    else:
        path = "/sse" if args.sse else "/mcp"
        host = f"[{http[0]}]" if ":" in http[0] else http[0]
        print(f"serve: {tools.run_dir} at http://{host}:{http[1]}{path} (Ctrl-C stops it)",
              flush=True)  # fmt: skip
    previous = signal.signal(signal.SIGTERM, _interrupt)
    try:
        serve(tools, http, sse=args.sse)
    except KeyboardInterrupt:
        print("serve: stopped", file=sys.stderr)
    finally:
        signal.signal(signal.SIGTERM, previous)
    return 0
