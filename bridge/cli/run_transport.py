"""The link between the processes of an `ambhil run` on this host: Unix-domain sockets where they
work, else TCP on loopback (``--transport``), TLS on loopback for ``--secure``, or the plant's
endpoint as given (``--endpoint``).  zenoh is imported inside the functions (`ambhil --help`
stays quick)."""
from __future__ import annotations

import os
import socket
import sys

from ambhil.loop.scene import SceneError
from ambhil.bridge.cli.convention import CliError
from ambhil.bridge.process.security import SecurityError, files

TRANSPORTS = ("auto", "unix", "tcp")


def choose_transport(kind: str, run_id: str) -> tuple[dict, str, str]:
    """The run's zenoh link between its processes on this host, and the plant's and recorder's
    listening endpoints.  ``auto`` (the default) = ``unix`` where Unix-domain sockets work,
    else ``tcp`` on loopback, saying why; ``unix`` refuses to fall back.  Multi-host runs
    start the processes themselves (``ambhil plant --listen tcp/HOST:PORT`` ...).  Returns
    (``{"kind", "auto", "text"}``, plant endpoint, recorder endpoint)."""
    from ambhil.bridge.process import transport as tr
    why = None
    if kind in ("auto", "unix"):
        try:
            if not hasattr(socket, "AF_UNIX"):
                raise tr.TransportError("no Unix-domain sockets on this platform")
            tag = f"{run_id[:40]}-{os.getpid()}"
            ep_p, ep_r = tr.unix_endpoint(f"{tag}-plant"), tr.unix_endpoint(f"{tag}-rec")
            gone = tr.remove_stale_sockets(os.path.dirname(tr.endpoint_path(ep_p)))
            if gone:                        # left by a run killed before it could clean up
                print(f"ambhil run: note: removed {len(gone)} socket or key file(s) of runs whose process is gone: "
                      f"{', '.join(os.path.basename(g) for g in gone)}", file=sys.stderr)
            probe = tr.endpoint_path(ep_r) + ".probe"
            with socket.socket(socket.AF_UNIX, socket.SOCK_STREAM) as sk:   # the folder takes sockets
                sk.bind(probe)
            os.unlink(probe)
            return ({"kind": "unix", "auto": kind == "auto",
                     "text": f"unix socket {os.path.dirname(tr.endpoint_path(ep_p))} (same host"
                             f"{', auto' if kind == 'auto' else ''}; --transport tcp for TCP loopback)"},
                    ep_p, ep_r)
        except (OSError, tr.TransportError) as e:
            if kind == "unix":
                raise SceneError(f"--transport unix: {e}") from None
            why = str(e)
            print(f"ambhil run: note: Unix-domain sockets unusable ({why}); using TCP on loopback",
                  file=sys.stderr)
    ep_p, ep_r = tr.tcp_endpoint(tr.free_port()), tr.tcp_endpoint(tr.free_port())
    return ({"kind": "tcp", "auto": kind == "auto",
             "text": "tcp loopback 127.0.0.1" + (f" (auto: fallback, {why})" if why else "")},
            ep_p, ep_r)


def run_transport(args, run_id: str) -> tuple[dict, str, str]:
    """:func:`choose_transport`, then ``--secure DIR`` (mutual TLS + access control on loopback,
    bridge/process/security.py; the certificates checked first) and ``--endpoint`` (the plant's
    endpoint, given, e.g. to attach a tool)."""
    from ambhil.bridge.process import transport as tr
    transport, ep_p, ep_r = choose_transport(args.transport, run_id)
    if args.secure:
        try:
            for role in ("plant", "controller", "recorder"):
                files(args.secure, role)
        except SecurityError as e:
            raise CliError(str(e)) from None
        ep_p, ep_r = (f"tls/127.0.0.1:{tr.free_port()}" for _ in range(2))
        transport = {"kind": "tls", "auto": False,
                     "text": f"TLS on loopback, mutual, certificates {args.secure}, access control on"}
    if args.endpoint:
        ep_p = args.endpoint
        transport = dict(transport, kind=ep_p.split("/", 1)[0], text=f"{ep_p} (--endpoint)")
    return transport, ep_p, ep_r
