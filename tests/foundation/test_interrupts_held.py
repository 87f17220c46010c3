"""A Ctrl-C during an import that catches BaseException (trimesh's optional parts) is held, not swallowed."""

from __future__ import annotations

import signal

import pytest

from tnf.runtime import interrupts_held


def _swallowing_import() -> str:
    """What trimesh does around an optional import: any exception, Ctrl-C included, means 'not available'."""
    try:
        signal.raise_signal(signal.SIGINT)  # Ctrl-C pressed while the import runs
        return "imported"
    except BaseException:
        return "swallowed"


def test_without_holding_a_ctrl_c_in_such_an_import_is_lost():
    assert signal.getsignal(signal.SIGINT) is signal.default_int_handler
    assert _swallowing_import() == "swallowed"


def test_a_ctrl_c_while_held_arrives_when_the_body_ends():
    done = []
    with pytest.raises(KeyboardInterrupt):
        with interrupts_held():
            done.append(_swallowing_import())
    assert done == ["imported"]
    with interrupts_held():  # and nothing is left pending
        done.append("again")
    assert done == ["imported", "again"]
