"""nox sessions: tests (a small dependency matrix), lint, typecheck, dev, demo, plugins, slow, peers.

torch is installed first and pinned, so that pip never replaces it with a multi-GB CUDA build on a CPU
machine. Set TNF_TORCH to install another torch spec (for example on a GPU machine).
"""

from __future__ import annotations

import os
from pathlib import Path

import nox

ROOT = Path(__file__).parent
PYTHON = os.environ.get("TNF_PYTHON", "3.11")
TORCH = os.environ.get("TNF_TORCH", "torch==2.13.0")
CONSTRAINTS = {
    "pinned": ROOT / ".ci" / "constraints-pinned.txt",
    "lowest": ROOT / ".ci" / "constraints-lowest.txt",
}
ENV = {
    "PYOPENGL_PLATFORM": "egl",
    "PYGLET_HEADLESS": "true",
    "WANDB_MODE": "offline",
    "WARP_CACHE_PATH": str(ROOT / ".warp-cache"),
    "OMP_NUM_THREADS": os.environ.get("OMP_NUM_THREADS", "2"),
}

nox.options.sessions = ["tests"]
nox.options.reuse_existing_virtualenvs = True


def install(session: nox.Session, deps: str = "pinned", extras: str = "test") -> None:
    session.install(TORCH, "-c", str(CONSTRAINTS[deps]))
    session.install("-e", f".[{extras}]", "-c", str(CONSTRAINTS[deps]))


@nox.session(python=PYTHON)
@nox.parametrize("deps", ["pinned", "lowest"])
def tests(session: nox.Session, deps: str) -> None:
    """The default test run (CPU, slow tests left out) against pinned and lowest supported versions.

    Tests run in TNF_TEST_WORKERS processes (pytest-xdist; default 2, 1 runs them in this process), each with one
    thread: on 2 cores about 1.4x faster than one process of two threads."""
    install(session, deps)
    workers_env = os.environ.get("TNF_TEST_WORKERS", "2")
    if not workers_env.isdigit() or int(workers_env) < 1:
        session.error(f"TNF_TEST_WORKERS must be a whole number >= 1, got {workers_env!r}")
    workers = int(workers_env)
    parallel = ["-n", str(workers)] if workers > 1 else []
    env = {**ENV, "OMP_NUM_THREADS": "1"} if workers > 1 else ENV
    session.run("pytest", "-q", "-p", "no:cacheprovider", *parallel, *session.posargs, env=env)


@nox.session(python=PYTHON)
def slow(session: nox.Session) -> None:
    """Tests marked slow (longer end-to-end runs)."""
    install(session)
    session.run("pytest", "-q", "-m", "slow", *session.posargs, env=ENV)


@nox.session(python=PYTHON)
def lint(session: nox.Session) -> None:
    """ruff check and format check."""
    session.install("ruff==0.17.6")
    session.run("ruff", "check", ".")
    session.run("ruff", "format", "--check", ".")


@nox.session(python=PYTHON)
def typecheck(session: nox.Session) -> None:
    """mypy on the tnf package."""
    install(session)
    session.install("mypy==2.4.1")
    session.run("mypy", "tnf")


@nox.session(python=PYTHON)
def demo(session: nox.Session) -> None:
    """The main job: the quick-start pipeline on built-in objects, ending with a report."""
    install(session)
    session.run("tnf", "pipeline", *session.posargs, env=ENV)


@nox.session(python=PYTHON)
def plugins(session: nox.Session) -> None:
    """Install each package under plugins/ next to tnf and run its tests."""
    install(session)
    for plugin in sorted(p for p in (ROOT / "plugins").iterdir() if (p / "pyproject.toml").is_file()):
        session.log(f"plugin {plugin.name}")
        session.install("--no-deps", "-e", str(plugin))
        session.run("pytest", "-q", "-p", "no:cacheprovider", str(plugin / "tests"), env=ENV)


@nox.session(python=False)
def dev(session: nox.Session) -> None:
    """Create .venv at the repository root with tnf (editable) and the test tools."""
    venv = ROOT / ".venv"
    session.run(f"python{PYTHON}", "-m", "venv", str(venv))
    pip = str(venv / "bin" / "pip")
    session.run(pip, "install", "--upgrade", "pip")
    session.run(pip, "install", TORCH, "-c", str(CONSTRAINTS["pinned"]))
    session.run(pip, "install", "-e", ".[test]", "ruff", "mypy", "nox", "-c", str(CONSTRAINTS["pinned"]))
    session.log(f"activate with: source {venv}/bin/activate")


# TACTO 0.0.3 as released: its urdfpy needs networkx 2.2, which imports on Python 3.8 at the latest, and it uses
# np.float, which numpy 1.24 removed.
TACTO = ["tacto==0.0.3", "numpy<1.24", "pyglet<2"]
# The Python 3.8 that TACTO's environment is made with (under pyenv: $(pyenv root)/versions/3.8.18/bin/python3.8).
TACTO_PYTHON = os.environ.get("TNF_TACTO_PYTHON", "python3.8")


@nox.session(python=PYTHON)
def peers(session: nox.Session) -> None:
    """Time tnf's simulator, TACTO and Taxim side by side (bench/peers.py): tnf and Taxim (JAX backend) in this
    session, TACTO in its own Python 3.8 environment (.nox/peers-tacto), run by bench/peers.py in the same run.
    Arguments go to bench/peers.py, e.g. `nox -s peers -- --out results/sim/peers_cpu.md`."""
    install(session, extras="real")
    session.install("jax==0.10.2", "jaxlib==0.10.2")
    tacto = ROOT / ".nox" / "peers-tacto"
    if not (tacto / "bin" / "python").is_file():
        session.run(TACTO_PYTHON, "-m", "venv", str(tacto), external=True)
        session.run(str(tacto / "bin" / "pip"), "install", *TACTO, external=True)
    session.run("python", "bench/peers.py", "--tacto-python", str(tacto / "bin" / "python"), *session.posargs, env=ENV)
