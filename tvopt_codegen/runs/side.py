"""A process forked beside this one to answer requests, and the pipes' messages.

The drawing process (:mod:`tvopt_codegen.runs.drawing`) talks on the same pipes.

``simulate`` starts one for the constraints' SLSQP check as soon as the derivation
exists (:func:`tvopt_codegen.simulation.constraints.minimiser_process`): it imports
``scipy.optimize`` (0.45 s of CPU, a fifth of a constrained ``simulate``) and lambdifies
the problem while this process integrates and certifies the run, on the machine's other
core. Where no process can be forked (not POSIX, other threads running) or it fails,
:meth:`Side.ask` answers None and the caller does the work itself: the answers are the
same.
"""

from __future__ import annotations

import contextlib
import gc
import os
import pickle
import signal
import struct
import sys
import threading
from collections.abc import Callable
from typing import Any

_LENGTH = struct.Struct("<Q")


def send(fd: int, payload: object) -> None:
    """One message on the pipe ``fd``: its length, then its pickle."""
    data = pickle.dumps(payload, protocol=pickle.HIGHEST_PROTOCOL)
    with os.fdopen(os.dup(fd), "wb") as stream:
        stream.write(_LENGTH.pack(len(data)) + data)


def receive(fd: int) -> Any:
    """One message, or None at the end of the stream (the other side is gone)."""
    with os.fdopen(os.dup(fd), "rb", buffering=0) as stream:
        head = _read_exactly(stream, _LENGTH.size)
        if head is None:
            return None
        body = _read_exactly(stream, _LENGTH.unpack(head)[0])
    return None if body is None else pickle.loads(body)  # noqa: S301 - our own child


def _read_exactly(stream: Any, size: int) -> bytes | None:
    chunks, left = [], size
    while left:
        chunk = stream.read(left)
        if not chunk:
            return None
        chunks.append(chunk)
        left -= len(chunk)
    return b"".join(chunks)


def can_fork() -> bool:
    """Whether a process can be forked safely here (POSIX, no other thread running).

    A fork with threads running could hold one of their locks forever in the child.
    """
    return hasattr(os, "fork") and threading.active_count() == 1


class Side:
    """A forked process: ``start()`` runs in it at once, then it answers :meth:`ask`.

    ``start`` returns the function that answers each request. Use as a context manager
    (or call :meth:`close`): the process is killed when it is no longer needed, whatever
    it is doing (it keeps nothing).
    """

    def __init__(self, start: Callable[[], Callable[[Any], Any]]) -> None:
        self._pid: int | None = None
        self._requests = self._replies = -1
        if not can_fork():
            return
        self._pid, self._requests, self._replies = fork(
            lambda requests, replies: _serve(start, requests, replies)
        )

    @property
    def running(self) -> bool:
        """Whether the process is there (forked, and no request of it has failed)."""
        return self._pid is not None

    def ask(self, request: object) -> Any:
        """The answer to ``request``, or None where the process is not there or failed."""
        if self._pid is None:
            return None
        try:
            send(self._requests, request)
            reply = receive(self._replies)
        except OSError:
            reply = None
        if reply is None or reply[0] != "ok":
            self.close()
            return None
        return reply[1]

    def close(self) -> None:
        """Stop the process (it keeps nothing) and reap it."""
        if self._pid is None:
            return
        pid, self._pid = self._pid, None
        stop(pid, (self._requests, self._replies), kill=True)

    def __enter__(self) -> Side:
        return self

    def __exit__(self, *_exc: object) -> None:
        self.close()


def fork(serve: Callable[[int, int], None]) -> tuple[int, int, int]:
    """Fork a process that runs ``serve(requests, replies)`` on two pipes, then exits.

    Returns its pid, the end to write requests to and the end to read replies from.
    The caller checks :func:`can_fork` first.
    """
    requests_read, requests_write = os.pipe()
    replies_read, replies_write = os.pipe()
    for stream in (sys.stdout, sys.stderr):
        with contextlib.suppress(Exception):
            stream.flush()  # or the child would flush the same buffered text again
    pid = os.fork()
    if pid == 0:  # pragma: no cover - the side process, measured by its answers
        try:
            os.close(requests_write)
            os.close(replies_read)
            serve(requests_read, replies_write)
        finally:
            os._exit(0)
    os.close(requests_read)
    os.close(replies_write)
    return pid, requests_write, replies_read


def stop(pid: int, pipes: tuple[int, ...], kill: bool) -> None:
    """Close a side process's ``pipes``, kill it if asked, and reap it."""
    for fd in pipes:
        with contextlib.suppress(OSError):
            os.close(fd)
    if kill:
        with contextlib.suppress(ProcessLookupError):
            os.kill(pid, signal.SIGKILL)
    with contextlib.suppress(ChildProcessError):
        os.waitpid(pid, 0)


def _serve(
    start: Callable[[], Callable[[Any], Any]], requests: int, replies: int
) -> None:  # pragma: no cover - the side process
    """Set up, then answer each request until the other side closes the pipe."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # the command's Ctrl-C is the parent's
    # What the parent built stays as it is: a collection walking it would copy its pages.
    gc.freeze()
    try:
        answer: Callable[[Any], Any] | None = start()
    except BaseException:  # noqa: BLE001 - every request is then refused; the parent works
        answer = None
    while (request := receive(requests)) is not None:
        try:
            if answer is None:
                raise RuntimeError("the side process failed to start")
            reply: tuple[str, Any] = ("ok", answer(request))
        except BaseException as error:  # noqa: BLE001 - reported; the parent does it itself
            reply = ("error", repr(error))
        send(replies, reply)
