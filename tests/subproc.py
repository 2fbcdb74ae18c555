"""Helpers for tests that talk to a peer in another process: start it, read
its JSON-lines stdout on a thread, wait for conditions with a deadline."""

from __future__ import annotations

import json
import os
import queue
import signal
import socket
import subprocess
import sys
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

REPO = Path(__file__).resolve().parents[1]


def free_port(kind: int = socket.SOCK_DGRAM) -> int:
    """A port free on 127.0.0.1 right now (the peer binds it soon after)."""
    with socket.socket(socket.AF_INET, kind) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


class JsonLinesProcess:
    """A child process whose stdout lines are JSON objects, collected in
    `lines` by a reader thread; other stdout lines land in `text`."""

    def __init__(self, argv: list[str], env: dict[str, str] | None = None,
                 cwd: Path | None = None) -> None:
        self.argv = argv
        self.proc = subprocess.Popen(
            argv, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
            env={**os.environ, **(env or {})}, cwd=cwd,
        )
        self.lines: list[dict[str, Any]] = []
        self.text: list[str] = []
        self.stderr = ""
        self._cond = threading.Condition()
        self._out = threading.Thread(target=self._read, daemon=True)
        self._err = threading.Thread(target=self._read_err, daemon=True)
        self._out.start()
        self._err.start()

    def _read(self) -> None:
        assert self.proc.stdout is not None
        for raw in self.proc.stdout:
            try:
                item = json.loads(raw)
            except ValueError:
                item = None
            with self._cond:
                if isinstance(item, dict):
                    self.lines.append(item)
                else:
                    self.text.append(raw.rstrip("\n"))
                self._cond.notify_all()
        with self._cond:
            self._cond.notify_all()

    def _read_err(self) -> None:
        assert self.proc.stderr is not None
        self.stderr = self.proc.stderr.read()

    def wait_for(self, pred: Callable[[list[dict[str, Any]]], bool], timeout: float,
                 what: str = "condition") -> list[dict[str, Any]]:
        """Block until pred(lines) holds; AssertionError with the child's
        output after `timeout` or when the child has exited."""
        deadline = time.monotonic() + timeout
        with self._cond:
            while not pred(self.lines):
                left = deadline - time.monotonic()
                if left <= 0 or (self.proc.poll() is not None and not self._out.is_alive()):
                    raise AssertionError(
                        f"{what} not met within {timeout} s by {self.argv}: rc={self.proc.poll()} "
                        f"lines={len(self.lines)} last={self.lines[-3:]} text={self.text[-5:]} "
                        f"stderr={self.stderr[-2000:]}"
                    )
                self._cond.wait(min(left, 0.2))
            return list(self.lines)

    def of_type(self, kind: str, key: str = "type") -> list[dict[str, Any]]:
        with self._cond:
            return [m for m in self.lines if m.get(key) == kind]

    def stop(self, sig: int = signal.SIGTERM, timeout: float = 20.0) -> int:
        if self.proc.poll() is None:
            self.proc.send_signal(sig)
        try:
            rc = self.proc.wait(timeout)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            rc = self.proc.wait(5)
        self._out.join(5)
        self._err.join(5)
        return rc


def python_script(path: Path, *args: str) -> list[str]:
    return [sys.executable, str(path), *args]


class LinePeer:
    """A peer in another process that speaks plain text lines: commands on
    its stdin, one line per event on its stdout (read on a thread)."""

    def __init__(self, argv: list[str], wait_s: float) -> None:
        self.wait_s = wait_s
        self.proc = subprocess.Popen(argv, stdin=subprocess.PIPE, stdout=subprocess.PIPE,
                                     text=True, bufsize=1)
        self.lines: queue.Queue[str] = queue.Queue()
        threading.Thread(target=self._read, daemon=True).start()

    def _read(self) -> None:
        for line in self.proc.stdout:
            self.lines.put(line.strip())

    def expect(self, prefix: str) -> str:
        """The next line starting with `prefix` (earlier lines are skipped)."""
        deadline = time.monotonic() + self.wait_s
        while True:
            try:
                line = self.lines.get(timeout=max(0.0, deadline - time.monotonic()))
            except queue.Empty:
                raise AssertionError(f"peer never said {prefix!r}") from None
            if line.startswith(prefix):
                return line

    def send(self, text: str, reply: str) -> str:
        self.proc.stdin.write(text + "\n")
        self.proc.stdin.flush()
        return self.expect(reply)

    def close(self) -> None:
        if self.proc.poll() is None:
            try:
                self.proc.stdin.write("quit\n")
                self.proc.stdin.flush()
                self.proc.wait(10)
            except (BrokenPipeError, subprocess.TimeoutExpired):
                self.proc.kill()
                self.proc.wait(10)
