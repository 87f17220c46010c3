"""data_seed: the seed of the data stages, so that a sweep over seeds can train every model on one dataset."""

from __future__ import annotations

import json
import subprocess
import sys
import time

import pytest

from tests.reliability.helpers import QUIET, run_tnf
from tnf.artifacts import data_seed_claim
from tnf.errors import TnfError
from tnf.testing import compose

TOUCH = [*QUIET, "object_names=[ball]"]


def touch_manifest(root) -> dict:
    return json.loads((root / "touch" / "digit" / "builtin" / "ball" / "manifest.json").read_text())


def test_a_fixed_data_seed_keeps_the_data_of_another_seed(capsys, data_root):
    assert run_tnf(capsys, "touch", *TOUCH, "seed=0")[0] == 0
    made = touch_manifest(data_root)
    # seed 1 with the data stages at seed 0: the touches of seed 0 are the ones it wants
    assert run_tnf(capsys, "touch", *TOUCH, "seed=1", "data_seed=0")[0] == 0
    assert touch_manifest(data_root) == made
    # seed 1 alone (data_seed null): its own touches, under the same item
    assert run_tnf(capsys, "touch", *TOUCH, "seed=1")[0] == 0
    remade = touch_manifest(data_root)
    assert remade["config_hash"] != made["config_hash"] and remade["config"]["seed"] == 1


def test_sim_digit_makes_its_data_once_for_every_seed():
    """The committed sim_digit runs trained seeds 0-2 on one dataset, made at seed 0."""
    for seed in (0, 1, 2):
        cfg = compose("pipeline", ["experiment=sim_digit", f"seed={seed}"])
        assert cfg.seed == seed and cfg.data_seed == 0
    assert compose("pipeline", ["seed=3"]).data_seed is None  # the quick start: each seed its own data


HOLD = """
import sys
from tnf.artifacts import data_seed_claim
with data_seed_claim(sys.argv[1], 3, "tnf pipeline seed=3"):
    print("held", flush=True)
    sys.stdin.read()  # until the test closes stdin
"""


def test_a_run_of_another_data_seed_stops_while_a_run_holds_the_store(capsys, data_root):
    """Seeds whose data stages run at once in one store would replace each other's items under each other."""
    holder = subprocess.Popen(
        [sys.executable, "-c", HOLD, str(data_root)], stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True
    )
    try:
        started = holder.stdout.readline()
        assert started.strip() == "held", f"the holding process did not start: {started!r}"
        # A run that joined the claim and has gone since is not named.
        gone = _exited_pid()
        record = data_root / ".data_seed" / "claim.json"
        claim = json.loads(record.read_text())
        claim["runs"].append({**claim["runs"][0], "pid": gone, "command": "tnf capture seed=3"})
        record.write_text(json.dumps(claim))
        rc, err = run_tnf(capsys, "touch", *TOUCH, "seed=4")
        assert rc == 1
        assert f"data seed 4: another run in {data_root} uses the data items of data seed 3" in err
        assert f"(`tnf pipeline seed=3` (pid {holder.pid} on " in err and "give each seed its own data_root" in err
        assert "tnf capture" not in err
        assert not (data_root / "touch").exists()  # stopped before any work
        # The data seed of the holder: its items are this run's too.
        assert run_tnf(capsys, "touch", *TOUCH, "seed=4", "data_seed=3")[0] == 0
        # Stages that make no data items are not held back: train reads whatever pairs the store holds (none
        # here, so it stops for want of them, not for the claim).
        assert run_tnf(capsys, "objects", *QUIET, "seed=4")[0] == 0
        rc, err = run_tnf(capsys, "train", *QUIET, "seed=4")
        assert rc == 1 and "another run" not in err and "pair" in err
        # So is a pipeline of those stages alone (paper_runs.sh trains its seeds side by side so); with a data stage
        # it is not.
        rc, err = run_tnf(capsys, "pipeline", *QUIET, "seed=4", "pipeline.stages=[train,evaluate]")
        assert rc == 1 and "another run" not in err
        rc, err = run_tnf(capsys, "pipeline", *QUIET, "seed=4", "pipeline.stages=[pair,train]")
        assert rc == 1 and "data seed 4: another run" in err
    finally:
        holder.stdin.close()
        code = holder.wait(timeout=60)
    assert code == 0
    assert run_tnf(capsys, "touch", *TOUCH, "seed=4")[0] == 0  # the holder has gone: the store is free


def _exited_pid() -> int:
    """The pid of a process that has exited."""
    proc = subprocess.Popen([sys.executable, "-c", "pass"])
    proc.wait()
    return proc.pid


def test_claims_of_one_data_seed_share_the_store_and_another_seed_waits_for_none(tmp_path):
    with data_seed_claim(tmp_path, 0, "tnf touch seed=1"):
        with data_seed_claim(tmp_path, 0, "tnf touch seed=2"):
            with pytest.raises(TnfError, match=r"\(`tnf touch seed=1` \(pid \d+ on .*\), `tnf touch seed=2` "):
                with data_seed_claim(tmp_path, 5, "tnf touch seed=5"):
                    pass
    with data_seed_claim(tmp_path, 5, "tnf touch seed=5"):  # every claim released: seed 5 takes the store
        record = json.loads((tmp_path / ".data_seed" / "claim.json").read_text())
        assert record["seed"] == 5 and [r["command"] for r in record["runs"]] == ["tnf touch seed=5"]


def test_a_claim_is_released_for_processes_forked_while_it_was_held(tmp_path):
    """A DataLoader's worker processes are forked: the lock they share must not outlive the claim."""
    import os

    with data_seed_claim(tmp_path, 0, "tnf pipeline seed=0"):
        child = os.fork()
        if child == 0:  # the child sleeps on, holding a copy of the claim's descriptor
            time.sleep(30)
            os._exit(0)
    try:
        with data_seed_claim(tmp_path, 1, "tnf pipeline seed=1"):
            pass
    finally:
        os.kill(child, 9)
        os.waitpid(child, 0)


def test_a_claim_whose_record_cannot_be_written_holds_no_run_up(tmp_path, monkeypatch):
    """The lock taken, the record not written (a failing disk): the claim shares the store, the next run joins it
    at once (it once waited, holding the decision's lock, until the first run ended)."""
    import threading

    import tnf.artifacts

    def fail(path, data):
        raise PermissionError(13, "Permission denied", str(path))

    with monkeypatch.context() as m:
        m.setattr(tnf.artifacts, "write_json", fail)
        first = data_seed_claim(tmp_path, 0, "tnf touch seed=0")
        first.__enter__()
    try:
        joined = threading.Event()

        def second():
            with data_seed_claim(tmp_path, 0, "tnf touch seed=0"):
                joined.set()

        threading.Thread(target=second, daemon=True).start()
        assert joined.wait(timeout=30), "a run of the same data seed waited for the first to end"
    finally:
        first.__exit__(None, None, None)
