"""``--dask tcp://host:port`` where no Dask scheduler answers is one line within a deadline."""

from __future__ import annotations

import socket
import threading
import time

import pytest

from colmap_miho.errors import UserError
from colmap_miho.pipeline import scheduler_probe
from colmap_miho.pipeline.scheduler_probe import check_dask_scheduler


class PlainServer:
    """A TCP server on 127.0.0.1 that accepts connections and sends ``greeting`` (or nothing)."""

    def __init__(self, greeting: bytes = b"") -> None:
        self.sock = socket.socket()
        self.sock.bind(("127.0.0.1", 0))
        self.sock.listen()
        self.greeting = greeting
        self.conns: list[socket.socket] = []
        self.thread = threading.Thread(target=self._serve, daemon=True)
        self.thread.start()

    @property
    def address(self) -> str:
        return f"tcp://127.0.0.1:{self.sock.getsockname()[1]}"

    def _serve(self) -> None:
        while True:
            try:
                conn, _ = self.sock.accept()
            except OSError:
                return
            self.conns.append(conn)
            if self.greeting:
                conn.sendall(self.greeting)

    def close(self) -> None:
        for c in self.conns:
            c.close()
        self.sock.close()


@pytest.fixture
def mute_server():
    server = PlainServer()
    yield server
    server.close()


def test_a_mute_service_is_not_a_scheduler(mute_server):
    t0 = time.monotonic()
    with pytest.raises(UserError, match="sent no Dask handshake within 1 s: it is not a Dask scheduler"):
        check_dask_scheduler(mute_server.address, handshake_timeout=1.0)
    assert time.monotonic() - t0 < 10


def test_a_talking_service_is_not_a_scheduler():
    server = PlainServer(b"SSH-2.0-OpenSSH_9.6\r\n")
    try:
        with pytest.raises(UserError, match="answered b'SSH-2.0-', not a Dask handshake"):
            check_dask_scheduler(server.address, handshake_timeout=5.0)
    finally:
        server.close()


def test_refine_on_a_mute_service_is_one_line(mute_server, tmp_path, monkeypatch, capsys):
    from colmap_miho.cli import main
    from miho_bench.synthetic import make_synthetic_scene

    scene = make_synthetic_scene(tmp_path / "s", num_images=3, num_points=40, render_images=False, seed=2)
    monkeypatch.setattr(scheduler_probe, "HANDSHAKE_TIMEOUT_S", 1.0)
    out = tmp_path / "o.db"
    t0 = time.monotonic()
    assert main(["refine", "--database", str(scene.database), "--images", str(scene.image_dir), "--output",
                 str(out), "--dask", mute_server.address, "-q"]) == 2
    err = [line for line in capsys.readouterr().err.splitlines() if line.strip()]
    assert len(err) == 1 and "not a Dask scheduler" in err[0] and mute_server.address in err[0], err
    assert time.monotonic() - t0 < 60 and not out.exists()


def test_a_dask_scheduler_passes():
    distributed = pytest.importorskip("distributed")
    with distributed.LocalCluster(n_workers=0, processes=False, protocol="tcp", dashboard_address=None) as cluster:
        check_dask_scheduler(cluster.scheduler_address, handshake_timeout=20.0)


def test_other_schemes_and_bad_addresses():
    check_dask_scheduler("inproc://x")  # not probed
    with pytest.raises(UserError, match="give a scheduler address like"):
        check_dask_scheduler("tcp://nohost")
    with pytest.raises(UserError, match="cannot reach the Dask scheduler"):
        check_dask_scheduler("tcp://127.0.0.1:1", connect_timeout=2)


def test_dask_noise_is_silenced_and_interrupts_quiet_its_loggers():
    import logging
    import warnings

    from colmap_miho.pipeline.executor import _quiet_dask

    with warnings.catch_warnings(record=True) as seen:
        warnings.simplefilter("always")
        with _quiet_dask():
            warnings.warn("Sending large graph of size 12.5 MiB.\nThis may cause some slowdown.", UserWarning,
                          stacklevel=1)
            warnings.warn("another warning", UserWarning, stacklevel=1)
    assert [str(w.message) for w in seen] == ["another warning"]
    saved = {name: logging.getLogger(name).level for name in ("distributed", "tornado", "asyncio")}
    try:
        with pytest.raises(KeyboardInterrupt):
            with _quiet_dask():
                raise KeyboardInterrupt
        assert all(logging.getLogger(name).level > logging.CRITICAL for name in saved)
    finally:
        for name, level in saved.items():
            logging.getLogger(name).setLevel(level)
