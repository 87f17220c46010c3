"""Stopping a scene fit at a chosen step, as a kill would, for the resume tests."""


class Stop(Exception):
    """Raised by ``stop_at``'s callback."""


def stop_at(step: int):
    """An ``on_step(step, loss)`` callback that raises ``Stop`` at ``step``."""

    def on_step(s, loss):
        if s == step:
            raise Stop

    return on_step
