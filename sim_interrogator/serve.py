"""`twin serve PROTOCOL`: a simulated interrogator behind a wire protocol, so any client reads the twin as
hardware.

    twin serve illumisense [--host 127.0.0.1] [--port 2055] [--scenario NAME | --source URL] [--rate HZ]
    twin serve hyperion    [--host 127.0.0.1] [--port 51971]  (peak stream on PORT + 1)
    twin serve fispec      [--cores 0,1,2,3] [--link PATH]    (one pseudo-terminal per core; paths printed)

The frames come from ``--source URL`` (any source URL), or ``--scenario NAME`` (= ``sim://NAME?realtime=1``: the
simulator in real time; ``--scenario 'NAME?key=value…'`` adds setup parameters), or by default the synthetic
forward-model source ``synthetic://?rate=HZ``. ``--rate`` sets the source's rate (100 Hz, the reference
paper's, by default). Servers bind 127.0.0.1 unless told otherwise.

What it prints on stdout, one line per endpoint, flushed at once (scripts may parse them)::

    twin serve: illumisense on tcp://127.0.0.1:2055
    twin serve: hyperion commands on tcp://127.0.0.1:51971, peak stream on tcp://127.0.0.1:51972
    twin serve: fispec core 0 on /dev/pts/7

then serves until Ctrl-C (or SIGTERM, ``--duration``, or the end of the source) and prints a summary. Exit
status 0; 130 when Ctrl-C cut a ``--duration`` short; 1 when the source failed.
"""

from __future__ import annotations

import argparse
import math
import signal
import threading
import time
from urllib.parse import parse_qsl, urlencode, urlsplit

from twin.io.source import open_source

#: one-line help (read by `twin --help` without importing this module)
HELP = "serve a simulated interrogator over illumisense, fispec or hyperion"

__all__ = ["add_arguments", "check_arguments", "run", "source_url"]

PROTOCOLS = ("illumisense", "fispec", "hyperion")


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("protocol", choices=PROTOCOLS, help="wire protocol to serve")
    parser.add_argument("--host", default="127.0.0.1", help="address to listen on (default 127.0.0.1)")
    parser.add_argument("--port", type=int, default=None,
                        help="TCP port (illumisense 2055, hyperion 51971; 0 picks a free one)")
    src = parser.add_mutually_exclusive_group()
    src.add_argument("--source", metavar="URL", help="serve frames from this source URL (default synthetic://)")
    src.add_argument("--scenario", metavar="NAME", help="serve the simulator running this scenario (sim://NAME)")
    parser.add_argument("--rate", type=float, default=None, help="frame rate of the source, Hz (default 100)")
    parser.add_argument("--duration", type=float, default=None, help="stop after this many seconds")
    parser.add_argument("--cores", default=None, help="fispec: cores to serve, one pty each (default all)")
    parser.add_argument("--link", default=None,
                        help="fispec: make a symlink PATH<core> to each pty (stable across restarts)")
    parser.add_argument("--channels", choices=("cores", "single"), default="cores",
                        help="illumisense: one channel per core (default) or all cores on one channel")
    parser.add_argument("--save-fiber", metavar="FILE", default=None,
                        help="write the served fibre model as TOML (for `twin live --fiber FILE`)")
    parser.add_argument("--quiet", action="store_true", help="do not log client connections")


def source_url(args: argparse.Namespace) -> str:
    """The source URL the options ask for, with ``rate`` added to its query when ``--rate`` is given."""
    add: dict[str, str] = {}
    if args.source:
        url = args.source
    elif args.scenario:
        url = f"sim://{args.scenario}"
        add["realtime"] = "1"  # a server plays the simulator in real time (sim:// alone runs flat out)
    else:
        url = "synthetic://"
    rate = args.rate if args.rate is not None else (100.0 if not args.source else None)
    if rate is not None:
        add["rate"] = f"{rate:g}"
    query = dict(parse_qsl(urlsplit(url).query, keep_blank_values=True))
    missing = {k: v for k, v in add.items() if k not in query}
    if missing:
        url = url.split("?", 1)[0] + "?" + urlencode({**query, **missing})
    return url


def check_arguments(args: argparse.Namespace) -> None:
    """Refuse impossible numbers before anything is opened (one line each, through the CLI's ValueError)."""
    if args.rate is not None and not (math.isfinite(args.rate) and args.rate > 0):
        raise ValueError(f"--rate must be a positive frequency in Hz, got {args.rate}")
    if args.port is not None and not 0 <= args.port <= 65535:
        raise ValueError(f"--port must be a TCP port in 0–65535 (0: any free one), got {args.port}")
    if args.duration is not None and not (math.isfinite(args.duration) and args.duration > 0):
        raise ValueError(f"--duration must be a positive, finite number of seconds, got {args.duration}")


def run(args: argparse.Namespace) -> int:
    check_arguments(args)
    url = source_url(args)
    warnings = None
    if url.startswith("sim://"):
        from models.catheter import collect_warnings

        warnings = collect_warnings()
    source = open_source(url)
    if args.save_fiber:
        if source.fiber is None:
            source.close()
            raise ValueError(f"--save-fiber: the source {url} does not know its fibre model")
        source.fiber.save(args.save_fiber)
    try:
        server, lines = _start(args, source)
    except BaseException:
        source.close()
        raise
    stop = threading.Event()
    reason = ["interrupted"]

    def handler(signum, _frame):
        reason[0] = "interrupted" if signum == signal.SIGINT else "terminated"
        stop.set()

    # the handlers are in place before the lines that say the server is up: a Ctrl-C right after them stops it
    # cleanly (with the summary) instead of interrupting it
    previous = {s: signal.signal(s, handler) for s in (signal.SIGINT, signal.SIGTERM)}
    t0 = time.monotonic()
    try:
        for line in lines:
            print(line, flush=True)
        print(f"twin serve: serving {url}; Ctrl-C to stop", flush=True)
        while not stop.wait(0.1):
            if server.pump.ended.is_set():
                reason[0] = "source failed" if server.pump.error else "source ended"
                break
            if args.duration is not None and time.monotonic() - t0 >= args.duration:
                reason[0] = "duration"
                break
    finally:
        for s, h in previous.items():
            signal.signal(s, h)
        server.close()
    stats = ", ".join(f"{k} {v}" for k, v in server.stats().items())
    print(f"twin serve: stopped ({reason[0]}) after {time.monotonic() - t0:.1f} s: {stats}", flush=True)
    if warnings:
        from models.catheter import WARNINGS_NOTE

        print(f"twin serve: {len(warnings)} MuJoCo solver warning(s), {WARNINGS_NOTE}; the first: {warnings[0]}",
              flush=True)
    if reason[0] == "source failed":
        return 1
    from twin.cli import interrupted_status

    # Ctrl-C is how an open-ended server stops (0); a --duration it cut short is 130
    return interrupted_status(reason[0] == "interrupted", args.duration is not None)


def _start(args: argparse.Namespace, source):
    log = not args.quiet
    if args.protocol == "illumisense":
        from sim_interrogator.servers.illumisense_server import IllumisenseServer

        port = 2055 if args.port is None else args.port
        server = IllumisenseServer(source, args.host, port, channels_as=args.channels, log=log).start()
        host, p = server.address
        return server, [f"twin serve: illumisense on tcp://{host}:{p}"]
    if args.protocol == "hyperion":
        from sim_interrogator.servers.hyperion_server import HyperionServer

        port = 51971 if args.port is None else args.port
        server = HyperionServer(source, args.host, port, log=log).start()
        (h, p), (_, sp) = server.address, server.stream_address
        return server, [f"twin serve: hyperion commands on tcp://{h}:{p}, peak stream on tcp://{h}:{sp}"]
    from sim_interrogator.servers.fispec_server import FispecServer

    cores = None
    if args.cores:
        try:
            cores = [int(c) for c in args.cores.split(",") if c.strip()]
        except ValueError:
            raise ValueError(f"--cores: expected comma-separated core numbers, got {args.cores!r}") from None
    fiber = source.fiber
    if fiber is not None and cores and any(not 0 <= c < fiber.n_cores for c in cores):
        raise ValueError(f"--cores {args.cores}: the fibre has cores 0..{fiber.n_cores - 1}")
    server = FispecServer(source, cores=cores, link=args.link).start()
    lines = []
    for p in server.ports:
        link = f" (link {p.link})" if p.link else ""
        lines.append(f"twin serve: fispec core {p.core} on {p.path}{link}")
    return server, lines
