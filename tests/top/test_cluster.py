"""Scale-out on Dask: chunks with warm-up equal the unchunked run; a 2-worker LocalCluster
gives the single-process files; a worker killed mid-chunk loses and repeats no frame; an
interrupted cluster render keeps files that agree. Access: the local cluster listens on
loopback only and authenticates with TLS; ``--scheduler`` values are checked, a remote
plain-tcp scheduler is warned about, and a server that is not Dask or says nothing is
refused in bounded bytes and time; cluster option errors exit 2; Dask is optional."""

from __future__ import annotations

import csv
import json
import os
import signal
import socket
import sys
import threading
import time
from pathlib import Path

import dask
import numpy as np
import psutil
import pytest
from scenes import mirror_gallery_stage
from typer.testing import CliRunner

from phrt_usd import cluster_client
from phrt_usd.api import run_render
from phrt_usd.cluster import (
    DEFAULT_WARMUP_FRAMES,
    plan_chunks,
    render_chunk,
    run_render_on_cluster,
    run_sweep_on_cluster,
)
from phrt_usd.cluster_client import (
    SchedulerAddress,
    dask_client,
    parse_scheduler_address,
    scheduler_warning,
    tls_client_configured,
)
from phrt_usd.engine.renderer import RenderOptions
from phrt_usd.errors import BadOption, PhrtError
from phrt_usd.evaluate.sweep import SweepSpec, run_sweep
from phrt_usd.run.render_job import RenderJob
from phrt_usd.run.selection_layer import read_selection_record

#: Deterministic budgets (rays) that fit only some of the gallery's five mirrors.
BUDGET_RAYS = 600
SWEEP_BUDGETS = [BUDGET_RAYS]
#: Sweeps cover the first 12 frames (FLIP, ~50 ms a call, dominates a sweep frame).
SWEEP_FRAMES = "1:12"
WIDTH, HEIGHT = 64, 48

#: CSV columns measured in wall time: they differ between any two runs.
TIMING_COLUMNS = {
    "frame_ms", "gbuffer_ms", "shade_ms", "select_ms", "trace_ms", "predicted_trace_ms",
}  # fmt: skip


def _rows_without_timings(path: Path) -> list[dict]:
    with open(path, newline="") as fh:
        return [{k: v for k, v in r.items() if k not in TIMING_COLUMNS} for r in csv.DictReader(fh)]


def _render_job(stage: Path, out: Path, frames: str | None = None) -> RenderJob:
    options = RenderOptions(
        heuristic="heu1", width=WIDTH, height=HEIGHT, budget_ms=None, budget_rays=BUDGET_RAYS
    )
    return RenderJob(stage_path=stage, out_dir=out, options=options, frames=frames)


def _sweep_spec(stage: Path, out: Path) -> SweepSpec:
    return SweepSpec(
        stages=[stage], heuristics=["heu1", "heu2"], budgets_rays=SWEEP_BUDGETS,
        frames=SWEEP_FRAMES, width=WIDTH, height=HEIGHT, out=out,
    )  # fmt: skip


def _same_selection_layer(a: Path, b: Path) -> None:
    ra, rb = read_selection_record(a), read_selection_record(b)
    np.testing.assert_array_equal(ra.times, rb.times)
    assert ra.reflectors == rb.reflectors
    np.testing.assert_array_equal(ra.selected, rb.selected)
    np.testing.assert_array_equal(ra.visible, rb.visible)
    assert ra.stats["rays"] == rb.stats["rays"]


def _frames_of(out: Path) -> list[dict]:
    return json.loads((out / "stats.json").read_text())["frames"]


# --------------------------------------------------------------------------- chunks


def test_plan_chunks_cover_every_frame_once():
    chunks = plan_chunks("s.usda", 23, chunk_frames=5, warmup=3)
    recorded = [i for c in chunks for i in range(c.start, c.stop)]
    assert recorded == list(range(23))
    assert [c.first_rendered for c in chunks] == [0, 2, 7, 12, 17]
    assert [c.index for c in chunks] == list(range(5))
    with pytest.raises(PhrtError):
        plan_chunks("s.usda", 10, chunk_frames=0, warmup=1)


@pytest.fixture(scope="module")
def gallery(tmp_path_factory) -> Path:
    folder = tmp_path_factory.mktemp("gallery")
    return mirror_gallery_stage(folder / "gallery.usda", frames=24, width=WIDTH, height=HEIGHT)


@pytest.mark.slow
def test_chunked_render_equals_unchunked_after_warmup(gallery, tmp_path):
    """HEU1 with a rays budget: chunks of 6 frames after DEFAULT_WARMUP_FRAMES warm-up
    frames select exactly what one uninterrupted run selects, frame by frame, with the
    same rays and the same per-reflector figures (V, C, R, Q, S)."""
    job = _render_job(gallery, tmp_path / "whole")
    job.write_images = False
    run_render(job)
    whole = _frames_of(tmp_path / "whole")
    chunks = plan_chunks(str(gallery), len(whole), 6, DEFAULT_WARMUP_FRAMES)
    chunked = [f for c in chunks for f in render_chunk(c, job).frames]
    assert [f.time for f in chunked] == [f["time"] for f in whole]
    for mine, theirs in zip(chunked, whole, strict=True):
        assert mine.selected == theirs["selected"], mine.time
        assert mine.rays == theirs["rays"], mine.time
        for path, m in mine.metrics.items():
            for name in ("V", "C", "R", "Q", "S"):
                assert getattr(m, name) == pytest.approx(theirs["metrics"][path][name], rel=1e-9)


@pytest.mark.slow
def test_a_chunk_sends_back_what_the_render_warned_of(tmp_path):
    """The clipping warning is found while rendering, on the worker: the chunk's result
    carries it (the client's stage never renders), and only it (not the reading's)."""
    from pxr import Usd, UsdGeom, UsdLux

    stage = Usd.Stage.CreateNew(str(tmp_path / "sun.usda"))
    quad = UsdGeom.Mesh.Define(stage, "/World/Quad")
    quad.CreatePointsAttr([(-1, -1, 0), (1, -1, 0), (1, 1, 0), (-1, 1, 0)])
    quad.CreateFaceVertexCountsAttr([4])
    quad.CreateFaceVertexIndicesAttr([0, 1, 2, 3])
    UsdGeom.Camera.Define(stage, "/World/Cam").AddTranslateOp().Set((0, 0, 3))
    UsdLux.DistantLight.Define(stage, "/World/Sun")  # UsdLux's fallback 50000: clips
    stage.GetRootLayer().Save()
    job = _render_job(tmp_path / "sun.usda", tmp_path / "out", frames="0:1")
    job.write_images = False
    [chunk] = plan_chunks(str(tmp_path / "sun.usda"), 2, 6, 0)
    result = render_chunk(chunk, job)
    [warning] = result.warnings
    assert "clipped" in warning and "/World/Sun" in warning and "--exposure" in warning


# --------------------------------------------------------------------------- cluster


@pytest.mark.slow
def test_two_worker_cluster_matches_single_process(gallery, tmp_path):
    """On a 2-worker LocalCluster: the sweep's CSV rows (timings aside) and timeline, and
    a render's selection layer and stats, equal a single-process run's. Sweep chunks run
    every configuration together; transitions and the temporal FLIP of a chunk's first
    frame come from its warm-up frames."""
    single = tmp_path / "single"
    run_sweep(_sweep_spec(gallery, single / "sweep"))
    run_render(_render_job(gallery, single / "render"))
    multi = tmp_path / "multi"
    with dask_client(workers=2) as client:
        assert len(client.scheduler_info()["workers"]) == 2
        summary = run_sweep_on_cluster(
            _sweep_spec(gallery, multi / "sweep"), client, chunk_frames=4
        )
        rendered = run_render_on_cluster(
            _render_job(gallery, multi / "render"), client, chunk_frames=6
        )
    # How the workers ran, as a one-process render reports it.
    assert rendered["kernels"] in ("cached", "compiled") and rendered["gl"] in ("egl", "osmesa")
    assert rendered["threads"] >= 1
    assert summary["rows"] == 12 * 5  # raster, heu1, heu2, all, rt
    assert len(set(summary["chunk_pids"])) == 2  # both workers took part
    assert _rows_without_timings(multi / "sweep" / "sweep.csv") == _rows_without_timings(
        single / "sweep" / "sweep.csv"
    )
    timeline = json.loads((multi / "sweep" / "timeline.json").read_text())
    assert timeline == json.loads((single / "sweep" / "timeline.json").read_text())
    for name in ("summary.md", "report.html", "error_vs_time.png"):
        assert (multi / "sweep" / name).stat().st_size > 0
    _same_selection_layer(multi / "render" / "selection.usda", single / "render" / "selection.usda")
    assert len(list((multi / "render" / "frames").glob("*.exr"))) == 24
    assert not list(multi.rglob(".*.tmp*"))  # no partial file left behind


@pytest.mark.slow
def test_killed_worker_chunk_is_retried_without_losing_or_repeating_frames(gallery, tmp_path):
    """SIGKILL one worker process while it renders a chunk: the chunk runs again on a
    live worker, and the result equals the single-process render exactly once per frame."""
    run_render(_render_job(gallery, tmp_path / "single"))
    job = _render_job(gallery, tmp_path / "multi")
    with dask_client(workers=2) as client:
        pids = client.run(os.getpid)  # worker address → process id
        outcome: dict = {}

        def render() -> None:
            try:
                outcome["summary"] = run_render_on_cluster(job, client, chunk_frames=4, warmup=3)
            except Exception as exc:  # noqa: BLE001 - handed to the test thread
                outcome["error"] = exc

        thread = threading.Thread(target=render)
        thread.start()
        victim, killed_keys = None, []
        deadline = time.monotonic() + 60
        while victim is None and time.monotonic() < deadline:
            for address, keys in client.processing().items():
                if keys and address in pids:
                    victim, killed_keys = address, list(keys)
                    break
            time.sleep(0.05)
        assert victim is not None, "no chunk ever started"
        time.sleep(0.3)  # well inside the chunk (4 frames + warm-up take seconds)
        os.kill(pids[victim], signal.SIGKILL)
        thread.join(timeout=240)
        assert not thread.is_alive()
    assert "error" not in outcome, outcome.get("error")
    frames = _frames_of(tmp_path / "multi")
    times = [f["time"] for f in frames]
    assert len(times) == len(set(times)) == 24  # every frame once
    assert times == [f["time"] for f in _frames_of(tmp_path / "single")]
    _same_selection_layer(
        tmp_path / "multi" / "selection.usda", tmp_path / "single" / "selection.usda"
    )
    # The chunks the killed worker held came back from a live process.
    killed_chunks = {int(key.rsplit("-", 1)[1]) for key in killed_keys}
    assert killed_chunks
    for index in killed_chunks:
        assert outcome["summary"]["chunk_pids"][index] != pids[victim]


# --------------------------------------------------------------------------- security


def _listening(process: psutil.Process) -> list[tuple[str, int]]:
    return [
        (c.laddr.ip, c.laddr.port)
        for c in process.net_connections(kind="inet")
        if c.status == psutil.CONN_LISTEN
    ]


def _run_security(client) -> dict:
    """Dask configuration that gives another client the run's certificate and key."""
    security = client.security
    return {
        "distributed.comm.tls.ca-file": security.tls_ca_file,
        "distributed.comm.tls.client.cert": security.tls_client_cert,
        "distributed.comm.tls.client.key": security.tls_client_key,
    }


@pytest.mark.slow
def test_local_cluster_listens_on_loopback_only(capsys):
    """Scheduler, nanny and worker addresses are 127.0.0.1, and no socket of this process
    (the scheduler runs here) or of the worker processes listens on another address; a
    client of that scheduler holding the run's certificate (``--scheduler``, loopback,
    TLS) gets no warning."""
    with dask_client(workers=1) as client:
        address = client.scheduler.address
        assert parse_scheduler_address(address).host == "127.0.0.1"
        workers = client.scheduler_info()["workers"]
        assert len(workers) == 1
        for worker_address, info in workers.items():
            assert parse_scheduler_address(worker_address).host == "127.0.0.1"
            assert parse_scheduler_address(info["nanny"]).host == "127.0.0.1"
        me = psutil.Process()
        sockets = _listening(me) + [s for p in me.children(recursive=True) for s in _listening(p)]
        assert ("127.0.0.1", parse_scheduler_address(address).port) in sockets
        assert len(sockets) >= 3  # scheduler, its HTTP endpoint, nanny / worker
        assert all(ip == "127.0.0.1" for ip, _ in sockets), sockets
        with dask.config.set(_run_security(client)), dask_client(scheduler=address) as remote:
            assert remote.scheduler_info()["workers"].keys() == workers.keys()
    assert capsys.readouterr().err == ""


#: How long a refused connection may try (seconds): distributed retries a failed
#: connection until its timeout, so this bounds each refusal's cost in the test.
REFUSED_TIMEOUT = "1s"


@pytest.mark.slow
def test_probe_local_cluster_authenticates_workers():
    """The --workers cluster speaks mutual TLS on certificates made for the run: a plain
    tcp client and a TLS client holding another certificate (another user's, say) are
    both refused, so neither can run code in the workers; the run's own client can."""
    from distributed import Client, Security

    with dask_client(workers=1) as client:
        address = client.scheduler.address
        assert address.startswith("tls://127.0.0.1:")
        ran = []
        for intruder in (
            {"address": address.replace("tls://", "tcp://", 1)},
            {"address": address, "security": Security.temporary()},
        ):
            with pytest.raises(OSError):  # refused during the handshake
                with Client(**intruder, timeout=REFUSED_TIMEOUT) as other:
                    ran.append(other.submit(os.getpid).result())
        assert ran == []
        for worker in client.scheduler_info()["workers"]:
            assert worker.startswith("tls://")
        assert client.submit(sum, [1, 2]).result() == 3


def test_probe_local_cluster_without_cryptography_refuses(monkeypatch):
    """Without the package that makes the certificates the local cluster does not start
    unauthenticated: one line naming the package and the extra, before any process."""
    import distributed

    monkeypatch.setitem(sys.modules, "cryptography", None)  # import fails
    started = []
    monkeypatch.setattr(distributed, "LocalCluster", lambda *a, **k: started.append(k))
    with pytest.raises(BadOption) as raised:
        with dask_client(workers=1):
            pass
    message = str(raised.value)
    assert "cryptography" in message and "pip install 'phrt-usd[cluster]'" in message
    assert "\n" not in message
    assert started == []


@pytest.mark.parametrize(
    ("given", "expected"),
    [
        ("tcp://10.0.0.5:8786", SchedulerAddress("tcp", "10.0.0.5", 8786)),
        ("tls://sched.example:8786", SchedulerAddress("tls", "sched.example", 8786)),
        ("TCP://node-1.lan.:9000", SchedulerAddress("tcp", "node-1.lan.", 9000)),
        ("localhost:8786", SchedulerAddress("tcp", "localhost", 8786)),  # bare: tcp
        ("tcp://[::1]:8786", SchedulerAddress("tcp", "::1", 8786)),
        ("tls://[2001:db8::7]:443", SchedulerAddress("tls", "2001:db8::7", 443)),
    ],
)
def test_scheduler_address_good_forms(given, expected):
    assert parse_scheduler_address(given) == expected
    assert parse_scheduler_address(str(expected)) == expected  # str() round-trips


@pytest.mark.parametrize(
    "given",
    [
        "", "tcp://", "tcp://host", "host", "tcp://:8786", "http://host:8786",
        "inproc://127.0.0.1/1/1", "ucx://host:8786", "tcp://host:0", "tcp://host:65536",
        "tcp://host:port", "tcp://host:8786/path", "tcp://user@host:8786", "tcp://a b:8786",
        "tcp://::1:8786", "tcp://[::1]", "tcp://[1.2.3.4]:8786", "tcp://10.0.0.300:8786",
        "tcp://-host:8786",
    ],
)  # fmt: skip
def test_scheduler_address_bad_forms_are_one_line_option_errors(given):
    with pytest.raises(BadOption) as raised:
        parse_scheduler_address(given)
    message = str(raised.value)
    assert message.startswith(f"--scheduler {given!r}: ")
    assert "\n" not in message
    with pytest.raises(BadOption):  # dask_client checks before connecting
        with dask_client(scheduler=given):
            pass


@pytest.mark.parametrize(
    "address",
    ["tcp://127.0.0.1:8786", "tcp://127.1.2.3:8786", "tcp://[::1]:8786",
     "tcp://[::ffff:127.0.0.1]:8786", "localhost:8786", "tcp://LOCALHOST.:8786",
     "tls://10.0.0.5:8786"],
)  # fmt: skip
def test_no_warning_for_loopback_or_tls_scheduler(address):
    assert scheduler_warning(address) is None


@pytest.mark.parametrize(
    "address",
    ["tcp://10.0.0.5:8786", "192.168.1.20:8786", "tcp://203.0.113.9:8786",
     "tcp://[2001:db8::7]:8786", "tcp://0.0.0.0:8786", "tcp://cluster.lan:8786",
     "tcp://localhost.example:8786"],
)  # fmt: skip
def test_one_line_warning_for_remote_plain_tcp_scheduler(address):
    warning = scheduler_warning(address)
    assert warning is not None and "\n" not in warning
    assert warning.startswith(f"warning: --scheduler {parse_scheduler_address(address)} ")
    assert "runs the code sent to it" in warning
    assert "tls://" in warning and "docs/cluster.md" in warning


def test_dask_client_prints_the_warning_once_before_connecting(monkeypatch, capsys):
    """No remote scheduler is contacted: the probe is made to fail."""

    def refuse(address, timeout, security):
        raise BadOption(f"--scheduler {address}: cannot connect (refused)")

    monkeypatch.setattr(cluster_client, "probe_scheduler", refuse)
    with pytest.raises(BadOption, match=r"^--scheduler tcp://10\.0\.0\.5:8786: cannot connect"):
        with dask_client(scheduler="10.0.0.5:8786"):
            pass
    err = capsys.readouterr().err
    assert err.count("\n") == 1
    assert err.startswith("warning: --scheduler tcp://10.0.0.5:8786 ")


def test_tls_scheduler_without_tls_configuration_is_refused(tmp_path):
    """distributed cannot open a tls:// connection without a CA file and a client
    certificate (it raises a TypeError); phrt says which configuration keys to set."""
    unset = {
        "distributed.comm.tls.ca-file": None,
        "distributed.comm.tls.client.cert": None,
        "distributed.comm.tls.client.key": None,
    }
    with dask.config.set(unset):
        assert not tls_client_configured()
        with pytest.raises(BadOption, match=r"distributed\.comm\.tls\.ca-file"):
            with dask_client(scheduler="tls://10.0.0.5:8786"):
                pass
    configured = {
        "distributed.comm.tls.ca-file": str(tmp_path / "ca.pem"),
        "distributed.comm.tls.client.cert": str(tmp_path / "client.pem"),
    }
    with dask.config.set(configured):
        assert tls_client_configured()


# --------------------------------------------------------------------------- --scheduler probe


class _FakeServer:
    """A server on a loopback port that is not Dask: on each connection it sends
    ``greeting`` (nothing: a silent server) and holds the connection until closed.
    Bounded: it serves until the ``with`` block ends."""

    def __init__(self, greeting: bytes) -> None:
        self.greeting = greeting
        self.listener = socket.create_server(("127.0.0.1", 0))
        self.listener.settimeout(0.1)
        self.port = self.listener.getsockname()[1]
        self.done = threading.Event()
        self.thread = threading.Thread(target=self._serve, daemon=True)

    def _serve(self) -> None:
        held = []
        while not self.done.is_set():
            try:
                conn, _ = self.listener.accept()
            except TimeoutError:
                continue
            conn.sendall(self.greeting)
            held.append(conn)
        for conn in held:
            conn.close()

    def __enter__(self) -> _FakeServer:
        self.thread.start()
        return self

    def __exit__(self, *exc) -> None:
        self.done.set()
        self.thread.join(timeout=5)
        self.listener.close()


#: What an HTTP server answers first: read as a Dask frame length, its first 8 bytes
#: announce ~3 EiB.
HTTP_GREETING = b"HTTP/1.1 400 Bad Request\r\nContent-Length: 0\r\n\r\n"


def test_probe_scheduler_not_dask_is_one_line_exit_2(gallery, tmp_path):
    """``--scheduler`` at a server that is not Dask: exit 2, one line saying so, no
    traceback, in well under the scheduler timeout (distributed alone tried to allocate
    the ~3 EiB the HTTP text announces); nothing rendered."""
    from phrt_usd.cli import app

    with _FakeServer(HTTP_GREETING) as server:
        start = time.monotonic()
        result = CliRunner().invoke(
            app,
            ["render", str(gallery), "--out", str(tmp_path / "out"), "--frames", "1:2",
             "--scheduler", f"tcp://127.0.0.1:{server.port}"],
        )  # fmt: skip
        elapsed = time.monotonic() - start
    assert result.exit_code == 2, result.output
    assert "Traceback" not in result.output
    assert result.exception is None or isinstance(result.exception, SystemExit)
    [line] = [x for x in result.output.splitlines() if x.startswith("error:")]
    assert f"--scheduler tcp://127.0.0.1:{server.port}: not a Dask scheduler" in line
    # Opening the stage and the probe take well under a second; 10 s is far below the
    # 20 s timeout, so the refusal came from the first bytes, not a timeout.
    assert elapsed < 10
    assert not (tmp_path / "out" / "stats.json").exists()


@pytest.mark.slow
def test_probe_scheduler_silent_server_keeps_the_timeout(monkeypatch):
    """A server that accepts and never answers: refused when the scheduler timeout ends
    (distributed alone waits for its handshake without a limit)."""
    monkeypatch.setattr(cluster_client, "SCHEDULER_TIMEOUT_SECONDS", 1.0, raising=False)
    outcome: dict = {}

    def connect(port: int) -> None:
        try:
            with dask_client(scheduler=f"tcp://127.0.0.1:{port}"):
                outcome["connected"] = True
        except Exception as exc:  # noqa: BLE001 - handed to the test thread
            outcome["error"] = exc

    with _FakeServer(b"") as server:
        start = time.monotonic()
        thread = threading.Thread(target=connect, args=(server.port,), daemon=True)
        thread.start()
        thread.join(timeout=10)  # 10x the 1 s timeout: room for a loaded machine
        elapsed = time.monotonic() - start
    assert not thread.is_alive(), "still waiting for a silent server after 10 s"
    error = outcome.get("error")
    assert isinstance(error, BadOption), outcome
    assert "no Dask handshake within 1 s" in str(error) and "\n" not in str(error)
    assert elapsed >= 0.9  # it did wait for the timeout (1 s, less timer slack)


def test_unreachable_scheduler_is_an_option_error():
    """Nothing listening at the address: exit 2's BadOption, one line."""
    with socket.create_server(("127.0.0.1", 0)) as free:
        port = free.getsockname()[1]  # closed again below: nothing listens there
    with pytest.raises(BadOption, match=rf"^--scheduler tcp://127\.0\.0\.1:{port}: cannot connect"):
        with dask_client(scheduler=f"tcp://127.0.0.1:{port}", timeout=2):
            pass


@pytest.mark.slow
def test_a_dask_scheduler_passes_the_probe_quietly(caplog):
    """The probe answers a real scheduler's handshake with its own: the scheduler logs
    no broken connection, and the client then connects."""
    import logging

    with dask_client(workers=1) as client, dask.config.set(_run_security(client)):
        address = parse_scheduler_address(client.scheduler.address)
        from distributed import Security

        with caplog.at_level(logging.INFO, logger="distributed"):
            cluster_client.probe_scheduler(address, 5.0, Security())
            time.sleep(0.2)  # the scheduler reads the handshake on its own thread
        assert not [r for r in caplog.records if "handshake" in r.getMessage()]


# --------------------------------------------------------------------------- options


def test_probe_workers_bound_exit_2(gallery, tmp_path, monkeypatch):
    """``--workers 10000`` is refused with exit 2 before any process starts, the bound
    and its reasons in the one line (each worker costs file descriptors; 10000 exhausted
    them)."""
    import distributed

    from phrt_usd.cli import app

    started = []
    monkeypatch.setattr(distributed, "LocalCluster", lambda *a, **k: started.append(k))
    result = CliRunner().invoke(
        app, ["render", str(gallery), "--out", str(tmp_path / "o"), "--workers", "10000"]
    )
    assert result.exit_code == 2, result.output
    bound, why = cluster_client.max_local_workers()
    assert f"--workers 10000: give 1 to {bound} (the cores this process may use" in result.output
    assert started == []
    # A low open-file limit lowers the bound: (300 - 256 reserved) // 16 per worker = 2.
    monkeypatch.setattr(cluster_client.resource, "getrlimit", lambda what: (300, 300))
    assert cluster_client.max_local_workers()[0] == min(2, cluster_client.DEFAULT_THREADS)
    assert "the open-file limit 300 allows 2" in cluster_client.max_local_workers()[1]


@pytest.mark.parametrize(
    ("options", "says"),
    [
        (["--workers", "1", "--resume"], "--resume is not available with --workers"),
        (["--scheduler", "tcp://127.0.0.1:9", "--resume"], "--resume is not available"),
        (["--workers", "1", "--chunk-frames", "0"], "--chunk-frames must be >= 1"),
        (["--workers", "1", "--warmup", "-1"], "--warmup must be >= 0"),
        (["--chunk-frames", "4"], "apply to --workers / --scheduler only"),
        (["--workers", "1", "--scheduler", "tcp://127.0.0.1:9"], "exactly one of"),
    ],
)
def test_probe_cluster_options_exit_2(gallery, tmp_path, options, says):
    """Cluster options that cannot go together or are out of range: exit 2 (the contract's
    bad option), one line, before any frame renders or any cluster starts."""
    from phrt_usd.cli import app

    out = tmp_path / "out"
    result = CliRunner().invoke(app, ["render", str(gallery), "--out", str(out), *options])
    assert result.exit_code == 2, result.output
    assert says in result.output and result.output.count("error:") == 1
    assert not out.exists()


@pytest.mark.slow
def test_probe_cluster_extra_missing_names_it(gallery, tmp_path, monkeypatch):
    """Without Dask (the ``cluster`` extra), ``--workers`` and ``--scheduler`` are one line
    naming the extra, exit 2; a render without them does not need Dask."""
    from phrt_usd.cli import app

    for name in ("dask", "distributed"):
        monkeypatch.setitem(sys.modules, name, None)  # import fails
    for option in (["--workers", "1"], ["--scheduler", "tcp://127.0.0.1:9"]):
        result = CliRunner().invoke(
            app, ["render", str(gallery), "--out", str(tmp_path / "o"), *option]
        )
        assert result.exit_code == 2, result.output
        [line] = [x for x in result.output.splitlines() if x.startswith("error:")]
        assert f"{option[0]} needs Dask" in line and "pip install 'phrt-usd[cluster]'" in line
    result = CliRunner().invoke(
        app, ["render", str(gallery), "--out", str(tmp_path / "plain"), "--frames", "1:1",
              "--resolution", "16x12", "--no-images"],
    )  # fmt: skip
    assert result.exit_code == 0, result.output


#: Imported at the top of phrt_usd's modules, Dask would make the extra required.
_DASK_MODULES = ("dask", "distributed")


@pytest.mark.slow
def test_probe_no_module_imports_dask_at_import_time():
    """No module of phrt_usd imports Dask when it is imported (only inside the functions
    of a cluster run), read from the source of every module; and the package, its CLI
    and its cluster module import in a Python where Dask cannot be imported."""
    import ast
    import subprocess

    import phrt_usd

    package = Path(phrt_usd.__file__).parent
    eager = []
    for path in package.rglob("*.py"):
        tree = ast.parse(path.read_text())
        for node in tree.body:  # module level only; imports inside functions are lazy
            names = []
            if isinstance(node, ast.Import):
                names = [a.name for a in node.names]
            elif isinstance(node, ast.ImportFrom) and node.module:
                names = [node.module]
            eager += [f"{path.name}: {n}" for n in names if n.split(".")[0] in _DASK_MODULES]
    assert eager == []
    blocked = (
        "import sys\n"
        "class Block:\n"
        "    def find_spec(self, name, path=None, target=None):\n"
        f"        if name.split('.')[0] in {_DASK_MODULES!r}:\n"
        "            raise ImportError(name)\n"
        "sys.meta_path.insert(0, Block())\n"
        "import phrt_usd, phrt_usd.cli, phrt_usd.api, phrt_usd.cluster\n"
        "from typer.testing import CliRunner\n"
        "r = CliRunner().invoke(phrt_usd.cli.app, ['render', '--workers', '1'])\n"
        "print(r.exit_code, r.output.strip())\n"
    )
    done = subprocess.run(
        [sys.executable, "-c", blocked], capture_output=True, text=True, timeout=120
    )
    assert done.returncode == 0, done.stderr[-2000:]
    assert done.stdout.startswith("2 error: --workers needs Dask"), done.stdout


# --------------------------------------------------------------------------- interrupts


@pytest.mark.slow
def test_probe_cluster_interrupt_keeps_agreeing_files(gallery, tmp_path):
    """SIGINT (Ctrl-C) while a 2-worker render runs, right after its first chunk is in:
    RenderInterrupted saying how many frames were kept, and stats.json, the selection
    layer and the images hold exactly those frames (a running chunk's images of frames
    not kept are gone, no temp file is left)."""
    from phrt_usd.run.products import default_plan
    from phrt_usd.run.render_job import RenderInterrupted

    out = tmp_path / "run"
    job = _render_job(gallery, out)
    signalled = []

    def interrupt(done: int, total: int) -> None:
        if not signalled:
            signalled.append(done)
            signal.raise_signal(signal.SIGINT)  # as Ctrl-C: to this (the main) thread

    with dask_client(workers=2) as client:
        try:
            with pytest.raises(RenderInterrupted) as raised:
                run_render_on_cluster(job, client, chunk_frames=4, warmup=2, on_frame=interrupt)
        except KeyboardInterrupt:
            pytest.fail("the interrupt escaped as KeyboardInterrupt: nothing reconciled")
        assert client.submit(sum, [1, 1]).result() == 2  # the cluster still serves
    kept = [f["time"] for f in _frames_of(out)]
    assert f"stopped after {len(kept)} of 24 frames" in str(raised.value)
    # The first chunk is kept; the 24 frames need 6 chunks on 2 workers, so a stop after
    # the first left some unfinished.
    assert 4 <= len(kept) < 24 and len(kept) % 4 == 0
    layer = read_selection_record(out / "selection.usda")
    assert sorted(layer.times) == sorted(kept)
    expected = {p for t in kept for p in default_plan().files(out, t)}
    written = {p for p in (out / "frames").iterdir()}
    assert written == expected
    assert not list(out.rglob(".*.tmp*"))
