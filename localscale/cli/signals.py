"""SIGTERM in the commands: raised as :class:`Terminated` (files being written are cleaned up),
or, where a command stops by itself between units of work, deferred until it does."""

from __future__ import annotations


class Terminated(KeyboardInterrupt):
    """SIGTERM, raised in the main thread so that files being written are cleaned up."""


class _SigtermState:
    """Whether the running command stops by itself between units of work (``predict --pairs``
    finishes the pair it is on): then a first SIGTERM only sets :attr:`requested`, and the
    command stops after the current pair; otherwise, or on a second SIGTERM, it is raised as
    :class:`Terminated`."""

    def __init__(self):
        self.deferred = False
        self.requested = False

    def defer(self) -> None:
        self.deferred, self.requested = True, False

    def reset(self) -> None:
        self.deferred = self.requested = False


SIGTERM_STATE = _SigtermState()


def _on_sigterm(signum, frame):
    if SIGTERM_STATE.deferred and not SIGTERM_STATE.requested:
        SIGTERM_STATE.requested = True
        return
    raise Terminated()
