"""``cfsr serve``: the live service and browser viewer (needs the ``live`` extra).

With no arguments it plays the built-in demo recording (simulated on first use and cached)
on http://127.0.0.1:8000/. FastAPI, uvicorn and pyusb are imported inside :func:`run` only, after
the check that the ``live`` extra is installed. Every start-up problem (missing extra or viewer
files, bad flag, taken port, unusable data folder, a source that cannot open) is one line on
stderr and exit status 2, with nothing left behind in ``/dev/shm``.
"""

from __future__ import annotations

import argparse
import hashlib
import os
import sys
import tempfile
from pathlib import Path

from cfsr.cli import _common  # available_memory read at call time (tests stand one in)
from cfsr.cli._common import add_pool_arguments, count_type
from cfsr.cli._extras import require_extra
from cfsr_live.replay.device import MAX_SPEED, MIN_SPEED
from cfsr_live.service import sources
from cfsr_live.service.config import QUALITIES
from cfsr_live.service.frameslot import FRAME_PREFIX
from cfsr_live.service.safefs import FolderLock
from cfsr_live.service.security import install_log_redaction
from cfsr_live.service.settings import (
    DEFAULT_MAX_CONNECTIONS,
    MAX_FPS_RANGE,
    RING_MAX_MB_RANGE,
    RING_SECONDS_RANGE,
    Settings,
    SourceSpec,
    default_data_dir,
)
from cfsr_live.service.signals import (
    Stopped,
    ignore_ending_signals,
    raise_on_ending_signals,
    start_resource_tracker,
    trap_ending_signals,
)
from cfsr_live.shm.files import remove_stale_files, shared_dirs
from cfsr_live.shm.ring import RING_PREFIX

HELP = "start the live service and browser viewer (needs cfsr[live])"
#: the source kind opened when the command line names none
DEFAULT_SOURCE = "demo"


def _port(text: str) -> int:
    try:
        port = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not a port number") from None
    if not 1 <= port <= 65535:
        raise argparse.ArgumentTypeError(f"{port} is not a port (1..65535)")
    return port


def _bounded(lo: float, hi: float, what: str):
    """An argparse type for a finite float in [lo, hi] (NaN and inf refused)."""

    def parse(text: str) -> float:
        try:
            v = float(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"{text!r} is not a number") from None
        if not lo <= v <= hi:  # false for NaN too
            raise argparse.ArgumentTypeError(f"{text} is outside {lo:g}..{hi:g} {what}")
        return v

    return parse


def add_arguments(p: argparse.ArgumentParser) -> None:
    fps_lo, fps_hi = MAX_FPS_RANGE
    ring_lo, ring_hi = RING_SECONDS_RANGE
    cap_lo, cap_hi = RING_MAX_MB_RANGE

    # each kind of source adds its own flags (cfsr_live.service.sources); none: the demo
    src = p.add_mutually_exclusive_group()
    for kind in sources.kinds():
        kind.add_select_argument(src, "serve")
    for kind in sources.kinds():
        kind.add_arguments(p, "serve")
    p.add_argument("--host", default="127.0.0.1",
                   help="bind address (default 127.0.0.1; anything else needs --token)")
    p.add_argument("--port", type=_port, default=8000, help="port, 1..65535 (default 8000)")
    p.add_argument("--token", default=os.environ.get("CFSR_TOKEN"),
                   help="access token the API requires (default $CFSR_TOKEN; prefer the "
                   "variable: a flag is visible to other users in the process list)")
    p.add_argument("--allow-host", action="append", default=[], metavar="NAME",
                   help="also answer to this Host name (repeatable; default: loopback names "
                   "and the bound address only, which defeats DNS rebinding)")
    p.add_argument("--allow-origin", action="append", default=[], metavar="URL",
                   help="also accept WebSocket and state-changing requests from this browser "
                   "origin, e.g. http://myhost:3000 (repeatable; default: the service's own)")
    p.add_argument("--data-dir", type=Path, default=None,
                   help="folder of recordings offered in the viewer; recordings are written to "
                   "DATA_DIR/recordings (default $CFSR_DATA_DIR or ~/.local/share/cfsr)")
    p.add_argument("--method", default="tfp", help="initial reconstruction method (default tfp)")
    p.add_argument("--speed", type=_bounded(MIN_SPEED, MAX_SPEED, "x real time"),
                   default=1.0, help=f"replay speed, {MIN_SPEED:g}..{MAX_SPEED:g} (1 = real time)")
    p.add_argument("--no-loop", action="store_true", help="stop at the end of a replay")
    p.add_argument("--quality", choices=QUALITIES, default="auto",
                   help="CFSR's tier: auto (full when --max-fps allows it, fast frames between; "
                   "default), full or fast; other methods have none")
    p.add_argument("--max-fps", type=_bounded(*MAX_FPS_RANGE, "frames/s"), default=30.0,
                   help=f"most frames/s published, {fps_lo:g}..{fps_hi:g} (default 30)")
    add_pool_arguments(
        p,
        "reconstruction processes: frames computed at once, each on its own step (default: "
        "one per usable core; each holds its own copy of the library, see "
        "'cfsr bench --throughput')",
    )
    p.add_argument("--ring-seconds", type=_bounded(*RING_SECONDS_RANGE, "s"), default=0.25,
                   help=f"seconds of sensor data the shared ring holds, {ring_lo:g}..{ring_hi:g} "
                   "(default 0.25; 1 s of a 400 x 250 camera is 500 MB of shared memory), "
                   "or less where that is over --ring-max-mb")
    p.add_argument("--ring-max-mb", type=count_type(cap_lo, cap_hi, "MiB"), default=1024,
                   help=f"the shared ring's size cap, {cap_lo}..{cap_hi} MiB (default 1024, "
                   "and at most a quarter of the memory available at start): "
                   "a source whose rate and geometry ask for more (a recording's sidecar "
                   "sets both) gets a shorter ring; one whose 8 blocks do not fit is refused")
    p.add_argument("--max-connections", type=count_type(16, 100_000, "connections"),
                   default=DEFAULT_MAX_CONNECTIONS,
                   help=f"open HTTP and WebSocket connections at most, 16..100000 (default "
                   f"{DEFAULT_MAX_CONNECTIONS}; lowered to stay under the open-file limit); one "
                   "more is closed at once")
    p.add_argument("--trusted-proxy", action="append", default=[], metavar="ADDR",
                   help="believe X-Forwarded-For/-Proto from this reverse proxy's address "
                   "(repeatable; default none: the peer address is the client's, whatever "
                   "headers say)")
    p.add_argument("--replay-mode", choices=("paced", "unpaced", "fast"), default="paced",
                   metavar="{paced,unpaced}",
                   help="paced: real-time schedule (default); unpaced: deterministic, as fast as "
                   "the worker consumes (tests; 'fast', its former name, still works)")
    p.add_argument("--log-level", default="warning", help="uvicorn log level")
    p.add_argument("--no-warmup", action="store_true",
                   help="do not compile the methods' kernels in the background on a first start "
                        "(otherwise a low-priority 'cfsr warmup' runs once, so switching to CSR "
                        "or CFSR later does not wait on the compiler; also CFSR_WARMUP=0)")
    p.add_argument("--test-hooks", action="store_true", help=argparse.SUPPRESS)


def _replay_mode(name: str) -> str:
    """The replay mode ``name``; the former ``fast`` (it read like CFSR's fast tier) is
    ``unpaced``, said once on stderr."""
    if name != "fast":
        return name
    print("cfsr serve: --replay-mode fast is now named --replay-mode unpaced", file=sys.stderr)
    return "unpaced"


def build_settings(args: argparse.Namespace):
    # every kind checks its own flags (the group lets at most one pick a source)
    picked = [s for k in sources.kinds() if (s := k.spec_from_args(args)) is not None]
    spec = picked[0] if picked else SourceSpec(kind=DEFAULT_SOURCE)
    return Settings(
        host=args.host,
        port=args.port,
        token=args.token or None,
        data_dir=args.data_dir or default_data_dir(),
        source=spec,
        speed=args.speed,
        loop=not args.no_loop,
        replay_mode=_replay_mode(args.replay_mode),
        method=args.method,
        quality=args.quality,
        max_fps=args.max_fps,
        ring_seconds=args.ring_seconds,
        ring_max_bytes=args.ring_max_mb << 20,
        max_connections=args.max_connections,
        trusted_proxies=list(args.trusted_proxy),
        **({} if args.workers is None else {"workers": args.workers}),
        threads=args.threads,
        test_hooks=args.test_hooks,
        warmup=not args.no_warmup,
        allowed_hosts=list(args.allow_host),
        allowed_origins=list(args.allow_origin),
    )


def _check_port(host: str, port: int) -> None:
    """Fail early, with one clear line, when the address is taken (before the demo is made and
    the worker started)."""
    import socket

    family = socket.AF_INET6 if ":" in host else socket.AF_INET
    with socket.socket(family, socket.SOCK_STREAM) as s:
        s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        try:
            s.bind((host, port))
        except OSError as exc:
            raise OSError(
                f"cannot listen on {host}:{port} ({exc.strerror}); another server may be "
                f"running there: stop it or pass --port"
            ) from None


def _check_data_dir(path: Path) -> None:
    """The data folder must be a folder we can list and write recordings into."""
    if path.exists() and not path.is_dir():
        raise OSError(f"data folder {path} is not a folder")
    try:
        path.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise OSError(f"data folder {path} cannot be created ({exc.strerror or exc})") from None
    if not os.access(path, os.R_OK | os.W_OK | os.X_OK):
        raise OSError(f"data folder {path} is not readable and writable by this user")
    try:
        next(os.scandir(path), None)
        with tempfile.TemporaryFile(dir=path):
            pass
    except OSError as exc:
        raise OSError(f"data folder {path} is not usable ({exc.strerror or exc})") from None


def _check_viewer(settings) -> None:
    # deferred: FastAPI and uvicorn load after the live extra's check, never in `cfsr --help`
    from cfsr_live.service.app import viewer_dir

    page = viewer_dir(settings) / "index.html"
    if not page.is_file():
        raise OSError(
            f"the viewer's files are missing from this install ({page} not found); "
            "reinstall with: pip install --force-reinstall 'cfsr[live]'"
        )


def _remove_stale_segments() -> int:
    """Shared-memory files of a server that crashed (its pid is gone): removed, and counted.

    Creating a ring or slot removes them too (:func:`cfsr_live.shm.files.create_shared_file`); this
    pass only exists so that the start can say how many there were."""
    dirs = {d for d in shared_dirs() if d.is_dir()}
    return sum(remove_stale_files(d, pre) for d in dirs for pre in (RING_PREFIX, FRAME_PREFIX))


def _token_note(token: str | None) -> str:
    # Never print the token itself (logs and terminals are shared): a fingerprint lets the
    # user check which token the server took.
    if not token:
        return ""
    fp = hashlib.sha256(token.encode()).hexdigest()[:8]
    return (f"; access token required (sha256 {fp}..., from --token or $CFSR_TOKEN): "
            "the viewer asks for it once")


def run(args: argparse.Namespace) -> int:
    require_extra("live")
    settings = build_settings(args)  # refuses a non-loopback bind without a token
    _check_viewer(settings)
    _check_port(settings.host, settings.port)
    _check_data_dir(settings.data_dir)
    say = lambda m: print(f"cfsr serve: {m}", flush=True)  # noqa: E731
    # deferred: FastAPI and uvicorn load after the live extra's check, never in `cfsr --help`
    from cfsr_live.service.httpproto import install_log_rate_limit

    # no log record of this process, at any level, carries the token or a session cookie
    install_log_redaction([settings.token] if settings.token else [])
    install_log_rate_limit()  # a client cannot make the server log the same line 2,000 times/s
    start_resource_tracker()  # before any queue: it must outlive a closed terminal
    raise_on_ending_signals()  # a signal during the start unwinds it cleanly
    lock = FolderLock(settings.data_dir)
    if lock.holder is not None:
        say(f"another cfsr serve (pid {lock.holder or 'unknown'}) uses the data folder "
            f"{settings.data_dir}: recordings are created exclusively, so a name the other "
            "server has taken is refused here (409)")
    try:
        return _serve(settings, args, say)
    except Stopped as exc:
        ignore_ending_signals()
        return 128 + exc.signum
    finally:
        lock.close()


def _fit_ring_to_memory(settings, say) -> None:
    """Lower the ring's cap to a quarter of the memory available now (not below the smallest
    cap): the ring lives in shared memory, and a fast source fills all of it."""
    share = max(RING_MAX_MB_RANGE[0] << 20, _common.available_memory() // 4)
    if share < settings.ring_max_bytes:
        say(f"the ring holds at most {share >> 20} MiB (a quarter of the memory available), "
            f"less than --ring-max-mb {settings.ring_max_bytes >> 20}")
        settings.ring_max_bytes = share


def _serve(settings, args: argparse.Namespace, say) -> int:
    """Start the runtime, serve until stopped, stop; the exit status."""
    stale = _remove_stale_segments()
    if stale:
        say(f"removed {stale} shared-memory file(s) left by a server that did not stop cleanly")
    _fit_ring_to_memory(settings, say)

    # slow first-use work (the demo's simulation) is said here, before the service starts
    sources.get(settings.source.kind).prepare(
        settings.source, sources.OpenOptions.from_settings(settings, say=say))

    # deferred: FastAPI and uvicorn load after the live extra's check, never in `cfsr --help`
    from cfsr_live.service.app import create_app
    from cfsr_live.service.httpproto import HeadTimeoutH11Protocol
    from cfsr_live.service.runtime import Runtime

    rt = Runtime(settings)
    try:
        rt.start()  # opens the source, creates the ring and the frame slot, starts the worker
    except Exception as exc:  # noqa: BLE001 - any failure to start is one line, not a trace
        rt.stop()
        print(f"cfsr serve: error: could not start: {exc}", file=sys.stderr)
        return 2
    except BaseException:  # an ending signal: Runtime.start has cleaned up after itself
        rt.stop()
        raise
    try:
        server = _make_server(settings, args, say, rt, create_app, HeadTimeoutH11Protocol)
        try:
            server.run()
        except SystemExit:
            pass  # uvicorn exits when it cannot bind; reported below
    finally:
        ignore_ending_signals()  # the stop below runs to its end
        rt.stop()  # idempotent: normally the lifespan has stopped it already
    if not server.started:
        print(f"cfsr serve: error: could not start on {settings.host}:{settings.port}",
              file=sys.stderr)
        return 2
    caught = server._captured_signals  # what ended it, if a signal did
    return 128 + int(caught[-1]) if caught else 0


def _make_server(settings, args: argparse.Namespace, say, rt, create_app, http):
    """The uvicorn server of ``rt``'s app (every ending signal trapped, request heads timed)."""
    # deferred: FastAPI and uvicorn load after the live extra's check, never in `cfsr --help`
    import uvicorn

    from cfsr_live.service.httpproto import (
        ACCEPT_BATCH,
        connection_cap,
        raise_open_file_limit,
        widen_listen_queue,
    )
    from cfsr_live.service.hub import MAX_CLIENT_MESSAGE_BYTES, MAX_CLIENT_MESSAGES_QUEUED

    if rt.kernels.status().state == "compiling":
        say("first start here: compiling the methods' kernels in the background at low "
            "priority (a few minutes; progress in the viewer, 'kernels' in /api/status)")
    cap = connection_cap(settings.max_connections, raise_open_file_limit())
    if cap < settings.max_connections:
        say(f"at most {cap} open connections (the open-file limit, 'ulimit -n', is lower "
            f"than --max-connections {settings.max_connections} needs)")
        settings.max_connections = cap  # the app sizes its body slots from it
    app = create_app(settings, runtime=rt)
    host = settings.host
    shown = f"[{host}]" if ":" in host else host
    url = f"http://{shown}:{settings.port}/"

    class _Server(uvicorn.Server):
        def capture_signals(self):
            # SIGHUP and SIGQUIT too, and nothing re-raised afterwards (cfsr_live.service.signals)
            return trap_ending_signals(self.handle_exit)

        async def startup(self, sockets=None):
            await super().startup(sockets)
            for srv in getattr(self, "servers", ()):
                widen_listen_queue(srv.sockets)
            if self.started:
                say(f"viewer at {url}  (source: {settings.source.id}"
                    f"{_token_note(settings.token)}; Ctrl+C to stop)")

    http = type("CappedH11Protocol", (http,), {"max_connections": cap,
                                                "header_timeout": settings.header_timeout_s})
    trusted = settings.trusted_proxies
    config = uvicorn.Config(
        app,
        host=host,
        port=settings.port,
        log_level=args.log_level,
        access_log=False,
        ws_per_message_deflate=False,
        ws_ping_interval=20,
        ws_ping_timeout=20,
        # a client sends only {"max_fps": N}: anything larger is refused as it arrives
        ws_max_size=MAX_CLIENT_MESSAGE_BYTES,
        ws_max_queue=MAX_CLIENT_MESSAGES_QUEUED,
        timeout_graceful_shutdown=3,
        # uvicorn believes X-Forwarded-For from loopback by default: then any local process
        # picks its own address (throttle slot, status); only a proxy the user names is believed
        proxy_headers=bool(trusted),
        forwarded_allow_ips=list(trusted) if trusted else [],
        workers=1,
        backlog=ACCEPT_BATCH,  # accepted per wake-up: at most that many over the cap at once
        http=http,  # a request head must come within 10 s; at most `cap` connections
    )
    return _Server(config)
