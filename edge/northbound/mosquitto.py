"""A mosquitto broker started as a child process on 127.0.0.1, for the tests and the benchmark.

Debian's ``mosquitto`` (``make test`` installs it). The broker listens on a loopback port chosen
at run time, is stopped and restarted by its PID only (``stop``, ``start`` again on the same port:
a broker outage), and keeps its sessions across such a restart (persistence in ``workdir``), so a
test's subscriber with a persistent session misses nothing the broker accepted.
"""
from __future__ import annotations

import os
import shutil
import signal
import socket
import subprocess
import time
from pathlib import Path

DEFAULT_EXE = "mosquitto"


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def find_mosquitto() -> str:
    """The mosquitto executable, or FileNotFoundError naming how to install it."""
    for cand in (os.environ.get("HP_EDGE_MOSQUITTO"), shutil.which(DEFAULT_EXE),
                 "/usr/sbin/mosquitto"):
        if cand and Path(cand).is_file() and os.access(cand, os.X_OK):
            return cand
    raise FileNotFoundError("mosquitto not found: apt-get install mosquitto (make test does it)")


class Mosquitto:
    """One broker. ``start()`` (bounded), ``stop()`` (SIGTERM, then SIGKILL, by PID).

    workdir : config, log and persistence go here
    port : 0 -> a free loopback port, chosen at the first start and kept for restarts
    extra : more lines for mosquitto.conf (e.g. 'password_file ...', TLS settings)
    anonymous : allow clients without a username
    """

    def __init__(self, workdir: str | Path, port: int = 0, *, extra: str = "",
                 anonymous: bool = True) -> None:
        self.workdir = Path(workdir)
        self.workdir.mkdir(parents=True, exist_ok=True)
        self.port = port
        self.extra = extra
        self.anonymous = anonymous
        self.exe = find_mosquitto()
        self.proc: subprocess.Popen | None = None
        self.log = self.workdir / "mosquitto.log"

    @property
    def pid(self) -> int | None:
        return self.proc.pid if self.proc is not None else None

    def _conf(self) -> Path:
        conf = self.workdir / "mosquitto.conf"
        conf.write_text(
            f"listener {self.port} 127.0.0.1\n"
            f"allow_anonymous {'true' if self.anonymous else 'false'}\n"
            f"persistence true\npersistence_location {self.workdir}/\n"
            "autosave_interval 0\nqueue_qos0_messages true\nmax_queued_messages 0\n"
            "max_inflight_messages 0\n"
            f"log_dest file {self.log}\nlog_type error\nlog_type warning\nlog_type notice\n"
            # as root, mosquitto would switch to the user 'mosquitto', who may not write here
            + ("user root\n" if os.geteuid() == 0 else "")
            + self.extra, encoding="utf-8")
        return conf

    def start(self, timeout: float = 10.0) -> Mosquitto:
        if self.proc is not None and self.proc.poll() is None:
            return self
        for attempt in range(3):
            if not self.port or attempt:
                self.port = free_port()
            self.proc = subprocess.Popen([self.exe, "-c", str(self._conf())],
                                         stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
            if self._wait_listening(timeout):
                return self
            self._reap()
        raise RuntimeError(f"mosquitto did not start on 127.0.0.1:{self.port}: "
                           f"{self._tail()}")

    def restart(self, timeout: float = 10.0) -> Mosquitto:
        """Start again on the same port (after ``stop``)."""
        self.proc = subprocess.Popen([self.exe, "-c", str(self._conf())],
                                     stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
        if not self._wait_listening(timeout):
            self._reap()
            raise RuntimeError(f"mosquitto did not restart on 127.0.0.1:{self.port}: "
                               f"{self._tail()}")
        return self

    def _wait_listening(self, timeout: float) -> bool:
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            if self.proc is None or self.proc.poll() is not None:
                return False
            try:
                with socket.create_connection(("127.0.0.1", self.port), timeout=0.5):
                    return True
            except OSError:
                time.sleep(0.05)
        return False

    def stop(self, timeout: float = 5.0) -> None:
        """Stop this broker by its PID (SIGTERM: it saves its sessions; SIGKILL after
        ``timeout``)."""
        p = self.proc
        if p is None or p.poll() is not None:
            self._reap()
            return
        os.kill(p.pid, signal.SIGTERM)
        try:
            p.wait(timeout)
        except subprocess.TimeoutExpired:
            os.kill(p.pid, signal.SIGKILL)
            p.wait(timeout)
        self._reap()

    def _reap(self) -> None:
        p, self.proc = self.proc, None
        if p is not None:
            if p.poll() is None:
                os.kill(p.pid, signal.SIGKILL)
                p.wait(5)
            if p.stderr is not None:
                p.stderr.close()

    def _tail(self) -> str:
        try:
            return self.log.read_text(encoding="utf-8", errors="replace")[-500:]
        except OSError:
            return "(no log)"

    def __enter__(self) -> Mosquitto:
        return self.start()

    def __exit__(self, *exc) -> None:
        self.stop()
