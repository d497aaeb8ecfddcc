"""`fluorosim seal init` and `fluorosim seal serve`: the root helper that alone reads the ledger key.

provisioning/install.sh runs `seal init` once, as root, and installs systemd's
fluorosim-seal.socket (listening where only group fluorosim may connect) and
fluorosim-seal.service (running `seal serve` as root when the first request comes).
"""

from __future__ import annotations

import argparse
import os
import socket
from pathlib import Path

from ..command_options import add_command
from ..errors import FluorosimError

#: systemd passes socket-activated listeners from this descriptor on (sd_listen_fds).
SD_LISTEN_FDS_START = 3


def run_init(args: argparse.Namespace) -> int:
    from .seal import make_key

    key = Path(args.key)
    if key.exists():
        print(f"{key}: a ledger key is already there; kept (a new key would make every sealed entry unverifiable)")
        return 0
    try:
        key.parent.mkdir(parents=True, exist_ok=True)
        make_key(key)
    except OSError as e:
        raise FluorosimError(f"{key}: cannot write the ledger key ({e.strerror or e}); run this as root") from None
    print(f"{key}: new ledger key written (mode 0400); back it up offline, it is what makes the ledger verifiable")
    return 0


def _listener(path: str | None) -> socket.socket:
    if os.environ.get("LISTEN_PID") == str(os.getpid()) and os.environ.get("LISTEN_FDS") == "1":
        return socket.socket(fileno=SD_LISTEN_FDS_START)
    if not path:
        raise FluorosimError("no socket: give --socket PATH, or start this from fluorosim-seal.socket")
    Path(path).unlink(missing_ok=True)
    s = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    s.bind(path)
    os.chmod(path, 0o660)
    s.listen(16)
    return s


def run_serve(args: argparse.Namespace) -> int:
    from .seal import KeySeal, serve

    seal = KeySeal(Path(args.key), Path(args.anchor))
    sock = _listener(args.socket)
    try:
        serve(sock, seal, Path(args.ledger))
    finally:
        sock.close()
    return 0


def register_seal(commands: argparse._SubParsersAction) -> None:
    from ..cli import command_group

    group = command_group(commands, "seal", "the ledger's seal: the key only root reads, and the anchor")
    def key_option(p: argparse.ArgumentParser) -> None:
        p.add_argument("--key", default="/etc/fluorosim-seal/ledger.key", metavar="PATH")

    add_command(group, "init", run_init, "write a new ledger key (root, once)",
                "Write a random 32-byte key, mode 0400, for the seal helper; an existing key is kept.", key_option)
    s = add_command(group, "serve", run_serve, "answer the service's seal requests (root, from fluorosim-seal.socket)",
                    "MAC each new ledger event, move the anchor once the ledger holds it, and verify the ledger for "
                    "`logs verify`; refuses to sign anything at or below the anchor.", key_option)
    s.add_argument("--anchor", default="/var/lib/fluorosim-seal/anchor.json", metavar="PATH")
    s.add_argument("--ledger", default="/var/lib/fluorosim/ledger.sqlite", metavar="PATH",
                   help="the one ledger this helper reads (never one a client names)")
    s.add_argument("--socket", metavar="PATH", help="listen here instead of on systemd's socket")
