"""Where `cubecloud view` listens, and how: the address and port checked before anything is
loaded (a one-line error rather than a traceback or a server on another port), and the viser
server, whose share button would relay the patient's scan through a public tunnel, started
without it.
"""

from __future__ import annotations

import contextlib
import io
import socket
import sys

from cubecloud_cli.core.errors import CubecloudError


def check_address(host: str, port: int) -> None:
    """A one-line error for a port outside 1–65535 or a host name that resolves to no address."""
    if not 1 <= port <= 65535:
        raise CubecloudError(f"--port {port} is not a port: choose one from 1 to 65535, e.g. 8080")
    try:
        socket.getaddrinfo(host, port, type=socket.SOCK_STREAM)
    except (socket.gaierror, UnicodeError) as exc:
        raise CubecloudError(f"--host {host} does not resolve to an address ({exc}): use 127.0.0.1") from None


def check_port_free(host: str, port: int) -> None:
    """A one-line error now, rather than a server that quietly takes another port. A port whose
    last connections are closing (TIME_WAIT, a minute after a viewer stopped) is free: viser's
    server reuses it, and so does this probe (on Windows the option would let two listen at once)."""
    with socket.socket(socket.AF_INET6 if ":" in host else socket.AF_INET, socket.SOCK_STREAM) as probe:
        if sys.platform != "win32":
            probe.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        try:
            probe.bind((host, port))
        except OSError as exc:
            raise CubecloudError(f"cannot listen on {host}:{port} ({exc.strerror}): choose another --port") from None


def start_server(host: str, port: int):
    """A viser server that serves the scene and nothing else. Its share button would relay the
    scene (the patient's scan) through a public tunnel, so it is hidden and its request refused.
    viser's own banner is dropped: the command prints the address in its own words."""
    import viser  # imported here: every other command starts without it
    from viser import _messages

    with contextlib.redirect_stdout(io.StringIO()):
        server = viser.ViserServer(host=host, port=port, verbose=False)
    server.gui.configure_theme(dark_mode=True, show_share_button=False)
    server._websock_server.unregister_handler(_messages.ShareUrlRequest)
    return server
