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
- ``term_as_interrupt``: SIGTERM taken as Ctrl-C for the block (``hp-edge fleet replay``: the table
  of the plants finished is written and the cluster closed; Python's default ends the process at
  once, without them).
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
def _handler(signum: int, handler):
    """``handler`` for ``signum`` in this process for the block, the previous one after it; yields
    False (and changes nothing) outside the main thread, where signals cannot be set."""
    try:
        old = signal.signal(signum, handler)
    except ValueError:
        yield False
        return
    try:
        yield True
    finally:
        signal.signal(signum, old)


@contextmanager
def term_as_interrupt():
    """SIGTERM raises KeyboardInterrupt for the block; yields a list that holds the signal once it
    came (to tell it from a Ctrl-C)."""
    got: list = []

    def on_term(signum, frame):
        got.append(signum)
        raise KeyboardInterrupt
    with _handler(signal.SIGTERM, on_term):
        yield got


@contextmanager
def ignored():
    """SIGINT ignored in this process for the block: the processes it starts inherit that (an
    ignored signal stays ignored through fork and exec, and neither Python nor asyncio installs its
    KeyboardInterrupt handler over it). A Ctrl-C meanwhile is lost. Outside the main thread (where
    signals cannot be set) nothing changes."""
    with _handler(signal.SIGINT, signal.SIG_IGN):
        yield
