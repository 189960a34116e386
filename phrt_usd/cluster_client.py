"""The client side of scale-out: who phrt lets its chunks run on, and how it connects.

Dask is an optional extra (``phrt-usd[cluster]``): nothing here imports ``dask`` or
``distributed`` until a cluster is asked for, and then its absence is one line naming the
extra (``require_distributed``). See ``docs/cluster.md``, "Security".

* ``--workers N`` (``dask_client(workers=N)``): a ``LocalCluster`` of N single-threaded
  worker processes listening on loopback only (``LOOPBACK_HOST``), whose scheduler,
  nannies, workers and this client authenticate each other with mutual TLS on
  certificates made for the run, in memory (``distributed.Security.temporary()``, which
  needs the ``cryptography`` package): a process on this machine that has not got them,
  another user's included, cannot connect, and so cannot run code in the workers.
  Without ``cryptography`` the local cluster refuses to start. N is bounded
  (``max_local_workers``: the cores, and what the open-file limit allows).
* ``--scheduler ADDRESS``: the value's form is checked (``parse_scheduler_address``), a
  plain-tcp scheduler on another machine is warned about (``scheduler_warning``), and
  before distributed touches the address it is *probed* (``probe_scheduler``): a
  connection and a read of the peer's first message, bounded in bytes
  (``HANDSHAKE_MAX_BYTES``) and in time (``SCHEDULER_TIMEOUT_SECONDS``), which must be a
  Dask handshake. distributed itself reads a peer's announced frame size and allocates
  it, and waits for a handshake without a time limit; a server that is not Dask (an
  HTTP server on the port) or says nothing is refused with one line (exit 2) instead.
  A peer that does speak Dask is trusted as any Dask peer must be: the client unpickles
  what it sends.
"""

from __future__ import annotations

import ipaddress
import pickle
import re
import resource
import socket
import ssl
import struct
import sys
import time
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from typing import TYPE_CHECKING

from phrt_usd.errors import BadOption
from phrt_usd.threads import DEFAULT_THREADS

if TYPE_CHECKING:
    from distributed import Client

#: What installs the optional cluster dependencies (Dask, and ``cryptography`` for the
#: local cluster's certificates).
CLUSTER_EXTRA_INSTALL = "pip install 'phrt-usd[cluster]'"

#: Where the local cluster listens: scheduler, nannies, workers and the scheduler's HTTP
#: endpoint bind this loopback address only (port 0: any free port), so no other machine
#: can reach them; their comms are TLS with the run's own certificates (module docstring).
LOOPBACK_HOST = "127.0.0.1"

#: File descriptors this process holds per local worker: measured 10 (its nanny's pipes
#: and the scheduler's, nanny's and client's connections, distributed 2026.8, Linux), with
#: room to spare.
FDS_PER_WORKER = 16
#: File descriptors kept for everything else a render opens (stage layers, textures,
#: images, libraries, the scheduler's own listeners).
FDS_RESERVED = 256

#: How long ``--scheduler`` may take to answer: the probe's connection and handshake,
#: then distributed's own connection (its ``timeout``), each.
SCHEDULER_TIMEOUT_SECONDS = 20.0
#: Largest first message a scheduler may announce. A Dask handshake (compression, Python
#: version, pickle protocol) is 58 bytes with distributed 2026.8; an HTTP or other server
#: read as Dask announces exabytes (its first 8 bytes of text taken as a length).
HANDSHAKE_MAX_BYTES = 64 * 1024
#: distributed's framing: every message starts with its byte count, an unsigned 64-bit
#: integer in the machine's byte order (``distributed.comm.tcp``).
_LENGTH = struct.Struct("Q")
#: Keys every Dask handshake holds (``Comm.handshake_info``).
_HANDSHAKE_KEYS = ("python", "pickle-protocol")

#: Schemes ``--scheduler`` accepts (a bare ``host:port`` is ``tcp://``, Dask's default).
#: ``inproc://`` is left out: it names a scheduler inside the same process, which a new
#: ``phrt`` process never has.
SCHEDULER_SCHEMES = ("tcp", "tls")

_HOSTNAME_LABEL = re.compile(r"(?!-)[A-Za-z0-9_-]{1,63}(?<!-)", re.ASCII)


def require_distributed(option: str):
    """The ``distributed`` module, or a BadOption naming ``option`` and the extra that
    installs it."""
    try:
        import distributed
    except ImportError:
        raise BadOption(
            f"{option} needs Dask, which is not installed: {CLUSTER_EXTRA_INSTALL}"
        ) from None
    return distributed


def max_local_workers() -> tuple[int, str]:
    """The most local workers this process may start, and why (for the message): the
    cores it may use (``threads.DEFAULT_THREADS``; a worker is one process rendering one
    chunk at a time, more than the cores only wait for each other), and what its
    open-file limit leaves after ``FDS_RESERVED`` at ``FDS_PER_WORKER`` each."""
    soft, _ = resource.getrlimit(resource.RLIMIT_NOFILE)
    by_cores = DEFAULT_THREADS
    why = f"the cores this process may use: {by_cores}"
    if soft == resource.RLIM_INFINITY:
        return by_cores, why
    by_files = max(0, (soft - FDS_RESERVED) // FDS_PER_WORKER)
    why += f"; the open-file limit {soft} allows {by_files}"
    return min(by_cores, by_files), why


def check_workers(workers: int) -> None:
    """BadOption unless ``1 <= workers <= max_local_workers()`` (the bound in the message)."""
    bound, why = max_local_workers()
    if not 1 <= workers <= bound:
        raise BadOption(f"--workers {workers}: give 1 to {bound} ({why})")


# --------------------------------------------------------------------------- --scheduler


@dataclass(frozen=True)
class SchedulerAddress:
    """A parsed ``--scheduler`` value: ``scheme://host:port`` (IPv6 hosts without the
    brackets)."""

    scheme: str
    host: str
    port: int

    def __str__(self) -> str:
        host = f"[{self.host}]" if ":" in self.host else self.host
        return f"{self.scheme}://{host}:{self.port}"

    @property
    def is_loopback(self) -> bool:
        """True for ``localhost`` and literals in 127.0.0.0/8 or ::1; any other name is
        taken as another machine (no name is looked up)."""
        if self.host.lower().rstrip(".") == "localhost":
            return True
        try:
            ip = ipaddress.ip_address(self.host)
        except ValueError:
            return False
        if isinstance(ip, ipaddress.IPv6Address) and ip.ipv4_mapped is not None:
            ip = ip.ipv4_mapped
        return ip.is_loopback


def _is_host_name_or_ipv4(host: str) -> bool:
    """An IPv4 literal, or a name of dot-separated labels whose last is not all digits
    (``10.0.0.300`` is a mistyped address, not a name)."""
    try:
        ipaddress.IPv4Address(host)
        return True
    except ValueError:
        labels = host.removesuffix(".").split(".")
        return all(_HOSTNAME_LABEL.fullmatch(label) for label in labels) and not (
            labels[-1].isdigit()
        )


def parse_scheduler_address(address: str) -> SchedulerAddress:
    """Check the form of a ``--scheduler`` value: ``tcp://host:port``, ``tls://host:port``
    or ``host:port`` (tcp); host a name, an IPv4 literal or a bracketed IPv6 literal.
    Anything else is a ``BadOption`` naming the option and the value. No name is
    resolved here."""

    def bad(why: str) -> BadOption:
        return BadOption(
            f"--scheduler {address!r}: {why}; expected tcp://HOST:PORT or tls://HOST:PORT"
        )

    scheme, sep, rest = address.strip().partition("://")
    if not sep:
        scheme, rest = "tcp", address.strip()
    scheme = scheme.lower()
    if scheme not in SCHEDULER_SCHEMES:
        raise bad(f"scheme {scheme!r} not supported")
    if rest.startswith("["):
        host, bracket, tail = rest[1:].partition("]")
        if not bracket or not tail.startswith(":"):
            raise bad("an IPv6 host needs brackets and a port, like [::1]:8786")
        port_text = tail[1:]
        try:
            if not isinstance(ipaddress.ip_address(host), ipaddress.IPv6Address):
                raise ValueError(host)
        except ValueError:
            raise bad(f"{host!r} is not an IPv6 address") from None
    else:
        host, colon, port_text = rest.rpartition(":")
        if not colon:
            raise bad("missing :PORT")
        if not host:
            raise bad("missing host")
        if ":" in host:
            raise bad("an IPv6 host needs brackets, like [::1]:8786")
        if not _is_host_name_or_ipv4(host):
            raise bad(f"{host!r} is not a host name or IP address")
    if not re.fullmatch(r"[0-9]{1,5}", port_text) or not 1 <= int(port_text) <= 65535:
        raise bad(f"port {port_text!r} is not a number in 1..65535")
    return SchedulerAddress(scheme, host, int(port_text))


def tls_client_configured(security=None) -> bool:
    """True when Dask's configuration (or ``security``, a ``distributed.Security``) gives
    the client a CA file and a certificate: without them distributed cannot open a
    ``tls://`` connection at all."""
    if security is None:
        from distributed import Security

        security = Security()
    return bool(security.tls_ca_file and security.tls_client_cert)


def scheduler_warning(address: SchedulerAddress | str) -> str | None:
    """The one-line warning printed before connecting to ``address``, or ``None``: a
    loopback scheduler and a ``tls://`` one (mutual TLS: only holders of a certificate
    of the cluster's CA can connect) get none."""
    if isinstance(address, str):
        address = parse_scheduler_address(address)
    if address.is_loopback or address.scheme == "tls":
        return None
    return (
        f"warning: --scheduler {address} is not on this machine and not encrypted: a Dask "
        "scheduler runs the code sent to it, and anyone who can reach it can run code as "
        "its workers' user; connect only to a cluster you control, over TLS (tls://, "
        "see docs/cluster.md)"
    )


def _read_exactly(sock: socket.socket, n: int, deadline: float) -> bytes:
    """``n`` bytes from ``sock`` before ``deadline`` (``time.monotonic``); TimeoutError
    past it, ConnectionError if the peer closes first."""
    data = bytearray()
    while len(data) < n:
        left = deadline - time.monotonic()
        if left <= 0:
            raise TimeoutError
        sock.settimeout(left)
        part = sock.recv(min(n - len(data), HANDSHAKE_MAX_BYTES))
        if not part:
            raise ConnectionError("closed the connection before a Dask handshake")
        data += part
    return bytes(data)


def _handshake_message() -> bytes:
    """This side's handshake in distributed's framing, so the scheduler sees a whole
    connection (and logs nothing about a broken one)."""
    import msgpack
    from distributed.protocol.utils import pack_frames

    info = {
        "compression": None,
        "python": tuple(sys.version_info[:3]),
        "pickle-protocol": pickle.HIGHEST_PROTOCOL,
    }
    body = pack_frames([msgpack.dumps(info, use_bin_type=True)])
    return _LENGTH.pack(len(body)) + body


def _is_dask_handshake(body: bytes) -> bool:
    """Whether ``body`` (the bytes announced by a first message) is a Dask handshake:
    one msgpack frame holding a map with the handshake's keys. Nothing in it is
    unpickled."""
    import msgpack
    from distributed.protocol.utils import unpack_frames

    try:
        frames = unpack_frames(body)
        message = msgpack.loads(frames[0], raw=False, use_list=False) if len(frames) == 1 else 0
    except (ValueError, struct.error, IndexError, TypeError, msgpack.UnpackException):
        return False
    return isinstance(message, dict) and all(key in message for key in _HANDSHAKE_KEYS)


def probe_scheduler(
    address: SchedulerAddress, timeout: float = SCHEDULER_TIMEOUT_SECONDS, security=None
) -> None:
    """Check that ``address`` is a Dask endpoint before distributed connects to it: open
    a connection (TLS with the client's certificate for ``tls://``), read the peer's first
    message, at most ``HANDSHAKE_MAX_BYTES`` and within ``timeout`` seconds overall, and
    require a Dask handshake; answer it with this side's and close. BadOption (one line,
    exit 2) when the address cannot be reached, does not answer in time or is not Dask."""
    where = f"--scheduler {address}"
    deadline = time.monotonic() + timeout
    try:
        with socket.create_connection((address.host, address.port), timeout=timeout) as raw:
            sock = raw
            if address.scheme == "tls":
                context = security.get_connection_args("client")["ssl_context"]
                sock = context.wrap_socket(raw, server_hostname=address.host)
            (size,) = _LENGTH.unpack(_read_exactly(sock, _LENGTH.size, deadline))
            if size > HANDSHAKE_MAX_BYTES:
                raise BadOption(
                    f"{where}: not a Dask scheduler (its first message announces {size} "
                    f"bytes; a Dask handshake is under {HANDSHAKE_MAX_BYTES})"
                )
            if not _is_dask_handshake(_read_exactly(sock, size, deadline)):
                raise BadOption(f"{where}: not a Dask scheduler (its first message is not a "
                                "Dask handshake)")  # fmt: skip
            sock.settimeout(max(deadline - time.monotonic(), 0.001))
            sock.sendall(_handshake_message())
    except TimeoutError:
        raise BadOption(
            f"{where}: no Dask handshake within {timeout:g} s (not a Dask scheduler, or "
            "not answering)"
        ) from None
    except ssl.SSLError as exc:
        raise BadOption(f"{where}: TLS failed ({exc.reason or exc})") from None
    except OSError as exc:
        raise BadOption(f"{where}: cannot connect ({exc.strerror or exc})") from None


def _connect(address: SchedulerAddress, timeout: float) -> Client:
    """A client of the scheduler at ``address``: warning first (``scheduler_warning``),
    then ``probe_scheduler``, then distributed's connection with the same timeout."""
    from distributed import Client, Security

    if address.scheme == "tls" and not tls_client_configured():
        raise BadOption(
            f"--scheduler {address}: TLS is not configured: set Dask's "
            "distributed.comm.tls.ca-file and distributed.comm.tls.client.cert (and .key) "
            "(see docs/cluster.md)"
        )
    warning = scheduler_warning(address)
    if warning is not None:
        print(warning, file=sys.stderr)
    probe_scheduler(address, timeout, Security())
    try:
        return Client(str(address), timeout=f"{timeout}s")
    except OSError as exc:
        raise BadOption(f"--scheduler {address}: cannot connect ({exc})") from None


# --------------------------------------------------------------------------- --workers


def local_security(workers: int):
    """The local cluster's ``distributed.Security``: mutual TLS on a certificate and key
    made for this run, in memory only (``Security.temporary``); BadOption naming the
    extra when ``cryptography``, which makes them, is missing."""
    from distributed import Security

    try:
        return Security.temporary()
    except ImportError:
        raise BadOption(
            f"--workers {workers}: the local cluster authenticates its workers with TLS "
            "certificates made for the run, which needs the 'cryptography' package: "
            f"{CLUSTER_EXTRA_INSTALL}"
        ) from None


def _worker_setup_plugin(ignore_interrupts: bool):
    """The Dask worker plugin every worker (present and future) runs: it imports
    phrt_usd, which registers the Phrt schema plugin before any stage is opened there
    (each chunk's render then activates its ``--gl`` platform before OpenGL loads).
    With ``ignore_interrupts`` (the local cluster's own workers, which share this
    terminal) SIGINT is ignored there: Ctrl-C stops the run through the client, which
    lets the chunks stop between frames and keeps what finished
    (``cluster.run_render_on_cluster``). Defined on first use: the module
    imports no Dask."""
    from distributed.diagnostics.plugin import WorkerPlugin

    class PhrtWorkerSetup(WorkerPlugin):
        name = "phrt-usd-setup"
        idempotent = True

        def __init__(self, ignore_interrupts: bool) -> None:
            self.ignore_interrupts = ignore_interrupts

        def setup(self, worker) -> None:  # noqa: ARG002 - the plugin's signature
            import signal
            import threading

            import phrt_usd  # noqa: F401

            if self.ignore_interrupts and threading.current_thread() is threading.main_thread():
                signal.signal(signal.SIGINT, signal.SIG_IGN)

    return PhrtWorkerSetup(ignore_interrupts)


@contextmanager
def dask_client(
    workers: int | None = None,
    scheduler: str | None = None,
    timeout: float | None = None,
) -> Iterator[Client]:
    """A ``distributed.Client``: connected to ``scheduler`` (``tcp://host:8786``,
    ``tls://host:8786``; checked by ``parse_scheduler_address``, warned about by
    ``scheduler_warning``, probed by ``probe_scheduler`` within ``timeout`` seconds, by default
    ``SCHEDULER_TIMEOUT_SECONDS``), or to
    a ``LocalCluster`` of ``workers`` single-threaded worker processes on this machine
    (bounded by ``max_local_workers``), on loopback only and mutual TLS with the run's own
    certificates (``local_security``), no dashboard. The Phrt worker plugin is registered
    either way. Closed on exit (the local cluster's workers end with it)."""
    if (workers is None) == (scheduler is None):
        raise BadOption("give exactly one of --workers N or --scheduler ADDRESS")
    if scheduler is not None:
        address = parse_scheduler_address(scheduler)
        require_distributed("--scheduler")
        timeout = SCHEDULER_TIMEOUT_SECONDS if timeout is None else timeout
        client, cluster = _connect(address, timeout), None
    else:
        check_workers(workers)
        require_distributed("--workers")
        from distributed import Client, LocalCluster

        security = local_security(workers)
        cluster = LocalCluster(
            n_workers=workers,
            threads_per_worker=1,  # one chunk at a time per process (OpenGL, Embree)
            processes=True,
            host=LOOPBACK_HOST,  # scheduler, nannies and workers, tls:// (the security)
            security=security,
            dashboard_address=None,  # no dashboard; the workers' HTTP endpoints on host
            # The scheduler's HTTP endpoint (metrics, no dashboard): loopback, any port.
            scheduler_kwargs={"dashboard": False, "dashboard_address": f"{LOOPBACK_HOST}:0"},
        )
        client = Client(cluster, security=security)
    try:
        client.register_plugin(_worker_setup_plugin(ignore_interrupts=cluster is not None))
        yield client
    finally:
        client.close()
        if cluster is not None:
            cluster.close()

