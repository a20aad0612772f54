"""``sync4d view RUN``: the run in the browser (`sync4d.viewer`): its Gaussians at any time, the
objects and their tracks, queries that light up the answer, renders of the current view.

The server listens on loopback unless ``--host`` says otherwise; it stops on Ctrl-C (or
SIGTERM), and when the last browser tab has been closed for a few seconds (``--keep-open``
keeps it). A run still being trained is shown as its latest checkpoint and reloaded as it saves.
"""

from __future__ import annotations

import argparse
import errno
import signal
import socket
import sys
import threading
import time
from pathlib import Path

from sync4d.errors import Sync4dError
from sync4d.files import writer_of
from sync4d.options import add_encoder, add_threads, port_number
from sync4d.runs.names import CHECKPOINT_NAME

__all__ = ["add_arguments", "main", "port_problem"]


def add_arguments(p: argparse.ArgumentParser) -> None:
    """The description and arguments of ``sync4d view`` (`sync4d.cli`)."""
    p.description = (
        "Serve a run's Gaussians on a local web page (viser): a time slider with play and "
        "speed, the dataset's cameras, the objects (show, isolate, highlight) and their "
        "tracks, a query box that ranks the objects and lights up the answer while it is "
        "active, and a button that renders the current view through sync4d's rasterizer into "
        "RUN/renders. Ctrl-C, or closing the last tab, stops it."
    )
    p.add_argument("run", metavar="RUN", help="run folder (one still training is reloaded as "
                   "it saves)")
    p.add_argument("--port", type=port_number, default=8080, metavar="P",
                   help="the port to serve on (default 8080)")
    p.add_argument("--host", default="127.0.0.1", metavar="ADDR",
                   help="the address to listen on (default 127.0.0.1: this machine only; "
                   "0.0.0.0 shares it on the network)")
    p.add_argument("--keep-open", action="store_true",
                   help="keep serving after the last browser tab closes (default: stop)")
    add_encoder(p)
    add_threads(p, "torch and the rasterizer")

#: Seconds without any browser before the server stops (a page reload reconnects sooner).
LINGER_SECONDS = 5.0


class _Refused(Sync4dError, RuntimeError):
    """A view that cannot start; the message says why and what to do."""


def port_problem(host: str, port: int) -> str | None:
    """Why `host`:`port` cannot be served (in use, not an address of this machine), or None."""
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        try:
            s.bind((host, port))
        except (UnicodeError, TypeError, ValueError, OverflowError):  # not a host name at all
            return (f"cannot listen on {host[:80]!r}:{port}: not an address or host name; "
                    "check --host (e.g. 127.0.0.1) and --port (1-65535)")  # fmt: skip
        except OSError as e:
            if e.errno == errno.EADDRINUSE:
                return (f"port {port} on {host} is in use (another viewer or server); pick "
                        f"another with --port")  # fmt: skip
            return f"cannot listen on {host}:{port} ({e.strerror or e}); check --host and --port"
    return None


def _check_run(run_dir: Path) -> str | None:
    """A note for a run being written, or `_Refused` for one that cannot be shown."""
    if not run_dir.is_dir():
        raise _Refused(f"{run_dir}: no such run folder; train one with "
                       f"`sync4d fit DATA --out {run_dir}`")  # fmt: skip
    writer = writer_of(run_dir)
    if not (run_dir / CHECKPOINT_NAME).is_file():
        if writer:
            raise _Refused(f"{run_dir} has no checkpoint yet: it is being written by {writer}; "
                           "open the viewer after its first save")  # fmt: skip
        raise _Refused(f"{run_dir}: no {CHECKPOINT_NAME} (not a run folder, or its training "
                       f"never saved); train it with `sync4d fit DATA --out {run_dir}`")
    if writer:
        return (f"{run_dir} is being written by {writer}: showing its latest checkpoint, "
                "reloaded as it saves")  # fmt: skip
    return None


def _serve(viewer, server, keep_open: bool, stop: threading.Event) -> None:
    """Wait for `stop` (Ctrl-C, SIGTERM) or (unless `keep_open`) the last browser to leave."""
    seen, empty_since = False, None
    while True:
        if stop.wait(0.25):
            print("view: stopped", file=sys.stderr)
            return
        if keep_open:
            continue
        clients = len(server.get_clients())
        seen = seen or clients > 0
        if clients:
            empty_since = None
        elif seen:
            empty_since = empty_since or time.monotonic()
            if time.monotonic() - empty_since > LINGER_SECONDS:
                print("view: the last browser tab closed; stopping", file=sys.stderr)
                return


def main(args: argparse.Namespace) -> int:
    """Run `view` with parsed `args`; the exit status."""
    run_dir = Path(args.run)
    try:
        note = _check_run(run_dir)
        problem = port_problem(args.host, args.port)
        if problem:
            raise _Refused(problem)
        try:
            import viser
        except ImportError:
            raise _Refused("the viewer needs viser: pip install viser") from None
        if args.threads:
            import torch

            torch.set_num_threads(args.threads)
        from sync4d.viewer.app import Viewer
        from sync4d.viewer.state import ViewerState

        state = ViewerState(run_dir, args.encoder)
    except Sync4dError as e:
        print(f"view: {e}", file=sys.stderr)
        return e.exit_code
    if note:
        print(f"view: {note}", file=sys.stderr)
    if state.field is None:
        print(f"view: queries are off: {state.field_message}", file=sys.stderr)
    server = viser.ViserServer(host=args.host, port=args.port, verbose=False)
    # Ctrl-C and SIGTERM set a flag the serving loop reads, rather than raising wherever the
    # main thread is: raised inside viser's client bookkeeping, the stop that followed could
    # hang past a test's 30 s on a loaded machine.
    stop = threading.Event()
    previous = {sig: signal.signal(sig, lambda *_: stop.set())
                for sig in (signal.SIGINT, signal.SIGTERM)}  # fmt: skip
    viewer = None
    try:
        viewer = Viewer(server, state, threads=args.threads)
        shown = "localhost" if args.host in ("127.0.0.1", "localhost") else args.host
        print(f"view: {state.run_dir} at http://{shown}:{server.get_port()} "
              f"(Ctrl-C stops it{'' if args.keep_open else '; so does closing the last tab'})",
              flush=True)  # fmt: skip
        _serve(viewer, server, args.keep_open, stop)
    except KeyboardInterrupt:  # a signal before the handlers were in place
        print("view: stopped", file=sys.stderr)
    finally:
        if viewer is not None:
            viewer.stop()
        server.stop()
        for sig, handler in previous.items():
            signal.signal(sig, handler)
    return 0
