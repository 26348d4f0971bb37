"""SIGINT around the child processes a command starts (standard library only).

A terminal's Ctrl-C sends SIGINT to every process of its foreground group: to ``replay --workers
N``'s pool workers and the embedded Dask cluster's workers too, which then died with a traceback
each while the command itself was still stopping them.

- ``held``: the parent blocks SIGINT in the thread that starts the children; a child inherits the
  blocked signal through fork and exec, so it never sees the terminal's Ctrl-C (a pool worker then
  ignores it and unblocks it, ``edge.commands.analysis_cmds.pool_worker``), and the parent takes a
  Ctrl-C that came meanwhile, held back, as the block ends. ``replay --workers N`` uses it.
- ``ignored``: SIGINT ignored in the parent while the children start; they inherit that. A Ctrl-C
  in those seconds is lost to the parent. The embedded Dask cluster needs it: distributed forks its
  worker processes from threads whose signal mask is clear (measured: the IO-loop thread started
  inside ``held`` has SIGINT unblocked), so a blocked SIGINT does not reach them.
"""
from __future__ import annotations

import signal
from contextlib import contextmanager


def block_sigint(block: bool) -> bool:
    """Block (or unblock) SIGINT in this thread; False where the platform cannot."""
    try:
        signal.pthread_sigmask(signal.SIG_BLOCK if block else signal.SIG_UNBLOCK, {signal.SIGINT})
        return True
    except (AttributeError, OSError, ValueError):
        return False


@contextmanager
def held():
    """SIGINT blocked in this thread for the block (the processes and threads it starts inherit
    it); a Ctrl-C that came meanwhile is raised (KeyboardInterrupt) as it ends."""
    blocked = block_sigint(True)
    try:
        yield
    finally:
        if blocked:
            block_sigint(False)


@contextmanager
def ignored():
    """SIGINT ignored in this process for the block: the processes it starts inherit that (an
    ignored signal stays ignored through fork and exec, and neither Python nor asyncio installs its
    KeyboardInterrupt handler over it). A Ctrl-C meanwhile is lost. Outside the main thread (where
    signals cannot be set) nothing changes."""
    try:
        old = signal.signal(signal.SIGINT, signal.SIG_IGN)
    except ValueError:
        yield
        return
    try:
        yield
    finally:
        signal.signal(signal.SIGINT, old)
