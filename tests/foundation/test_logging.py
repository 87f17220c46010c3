"""What the `tnf` command prints: each of Lightning's notices once, without the advice tnf acts on itself, and
no import-time chatter from PyOpenGL."""

import os
import subprocess
import sys
import textwrap

import pytest

# A `tnf` stage, run by the real command line and Hydra's job logging, that does what a training stage does to
# the loggers: imports PyOpenGL (the capture renderer's), starts a trainer's logging, and has Lightning speak.
STAGE = textwrap.dedent(
    """
    import logging, sys, types
    from tnf.cli import main

    def run(cfg):
        import OpenGL.GL  # noqa: F401
        import lightning  # noqa: F401
        from tnf.generators.training import _quiet_trainer_start

        if cfg.seed == 1:
            _quiet_trainer_start()
        notices = logging.getLogger("lightning.pytorch.utilities.rank_zero")
        notices.info("GPU available: probe-notice")
        notices.info("you should set `torch.set_float32_matmul_precision('medium' | 'high')` probe-advice")

    module = types.ModuleType("tnf.stages.objects")
    module.run = run
    sys.modules["tnf.stages.objects"] = module
    sys.exit(main(["objects", "seed=" + sys.argv[1]]))
    """
)


def _output(tmp_path, seed: int) -> str:
    env = {**os.environ, "TNF_DATA": str(tmp_path / "data")}
    out = subprocess.run([sys.executable, "-c", STAGE, str(seed)], capture_output=True, text=True, env=env)
    assert out.returncode == 0, out.stderr
    return out.stdout + out.stderr


def test_lightning_notices_print_once_without_the_advice_tnf_follows(tmp_path):
    quiet = _output(tmp_path, seed=1)
    assert quiet.count("probe-notice") == 1
    assert "probe-advice" not in quiet
    # the notice also reaches the job's log file, through the root logger
    (log,) = (tmp_path / "data" / "logs").rglob("*.log")
    assert "probe-notice" in log.read_text()
    # as Lightning leaves it, each notice prints twice: its own console handler and the root logger's
    loud = _output(tmp_path, seed=0)
    assert loud.count("probe-notice") == 2 and "probe-advice" in loud


def test_no_pyopengl_import_chatter(tmp_path):
    assert "OpenGL_accelerate" not in _output(tmp_path, seed=1)


def test_warp_starts_without_its_banner_or_module_notices(tmp_path):
    """The simulator and the scenes' kernels print none of Warp's start-up lines or per-module load notices."""
    script = textwrap.dedent(
        """
        import torch
        from tnf.scenes.hash_kernel import hash_encode

        x = torch.rand(5, 3)
        table = torch.rand(2 * 16, 2)
        out = hash_encode(x, table, torch.tensor([4.0, 8.0]), n_dense=1, table_size=16)
        print("features", tuple(out.shape))
        """
    )
    out = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, env=dict(os.environ))
    assert out.returncode == 0, out.stderr
    text = out.stdout + out.stderr
    assert "features (5, 4)" in text
    assert "initialized" not in text and "Module tnf." not in text


def test_warp_keeps_a_log_level_chosen_before():
    import warp as wp

    from tnf.runtime import init_warp

    saved = wp.config.log_level
    try:
        wp.config.log_level = wp.LOG_DEBUG
        init_warp()
        assert wp.config.log_level == wp.LOG_DEBUG
        wp.config.log_level = wp.LOG_INFO  # Warp's default: raised
        init_warp()
        assert wp.config.log_level == wp.LOG_WARNING
    finally:
        wp.config.log_level = saved


def test_warp_on_a_cpu_only_machine_says_nothing_of_the_missing_cuda_driver():
    """Warp's native library warns on stderr that it finds no NVIDIA driver; on a CPU-only machine (where tnf
    runs on the CPU by design) init_warp holds that line back and lets everything else through."""
    env = dict(os.environ)
    warning = "Could not find or load the NVIDIA CUDA driver"
    bare = subprocess.run([sys.executable, "-c", "import warp; warp.init()"], capture_output=True, text=True, env=env)
    assert bare.returncode == 0, bare.stderr
    if warning not in bare.stderr:
        pytest.skip("this machine has an NVIDIA driver: Warp has nothing to warn about")
    script = textwrap.dedent(
        """
        import sys
        from tnf.runtime import init_warp

        print("before", file=sys.stderr)
        init_warp()
        print("after", file=sys.stderr)
        """
    )
    out = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, env=env)
    assert out.returncode == 0, out.stderr
    assert warning not in out.stdout + out.stderr
    assert out.stderr.splitlines() == ["before", "after"]


def test_native_lines_held_back_during_warp_start_are_written_out_after():
    """What else native code writes while Warp starts reaches stderr, in order; only the driver line is dropped."""
    script = textwrap.dedent(
        """
        import os
        from tnf.runtime import _without_native_line

        with _without_native_line("drop me") as dropped:
            os.write(2, b"first\\nplease drop me\\nlast\\n")
        print(len(dropped))
        """
    )
    out = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, env=dict(os.environ))
    assert out.returncode == 0, out.stderr
    assert out.stderr.splitlines() == ["first", "last"]
    assert out.stdout.strip() == "1"


def test_warp_starts_once_however_often_and_from_however_many_threads(monkeypatch):
    """Kernels call init_warp on every launch: only the first call starts Warp (and holds stderr back), however
    many threads call it at once, so no thread can leave another's redirection in place."""
    import threading

    import tnf.runtime as rt

    starts = []
    real = rt._without_native_line

    def counting(text):
        starts.append(text)
        return real(text)

    monkeypatch.setattr(rt, "_without_native_line", counting)
    monkeypatch.setattr(rt, "_warp_started", False)
    threads = [threading.Thread(target=lambda: [rt.init_warp() for _ in range(50)]) for _ in range(8)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert len(starts) == 1
