"""The child processes of `ambhil run` (bridge/cli/run.py): started as ``python -m
ambhil.bridge.cli ARGS`` (or a command of the user's, ``--controller CMD``) in a session of
their own, tied to the parent's life, their output read by threads, stopped with signals."""
from __future__ import annotations

import ctypes
import json
import os
import signal
import subprocess
import sys
import threading


def _die_with_parent() -> None:
    """In the child, before exec: the kernel sends it SIGTERM when the process that started it
    dies (Linux ``PR_SET_PDEATHSIG``), so `ambhil run` killed from outside (SIGKILL, a
    ``timeout`` wrapper) does not leave its plant, controller and recorder running; SIGTERM
    lets each end as on Ctrl-C (the recorder closes its file).  And SIGINT is not ignored in
    the child (below).  No-op elsewhere."""
    if sys.platform.startswith("linux"):
        libc = ctypes.CDLL(None, use_errno=True)
        libc.prctl(1, signal.SIGTERM, 0, 0, 0)  # PR_SET_PDEATHSIG = 1
        # `ambhil run` stops its plant with SIGINT (Ctrl-C's path: summary, RUN_END, file
        # closed).  Started with SIGINT ignored (a background job of a script, nohup), the
        # children would inherit the ignore and never stop that way: give them the default
        # disposition (Python then installs its KeyboardInterrupt handler).  libc's signal():
        # Python's signal.signal refuses to run outside the main thread.
        libc.signal.argtypes, libc.signal.restype = [ctypes.c_int, ctypes.c_void_p], ctypes.c_void_p
        libc.signal(signal.SIGINT, None)        # SIG_DFL


def child_env(extra: dict | None = None) -> dict:
    """The caller's environment with ``extra`` (a value None removes the variable, e.g. a
    ``$AMBHIL_KEY_FILE`` of the user's shell that is not this run's key)."""
    env = dict(os.environ, PYTHONUNBUFFERED="1")
    for k, v in (extra or {}).items():
        if v is None:
            env.pop(k, None)
        else:
            env[k] = v
    return env


def spawn_cli(argv: list[str], extra_env: dict | None = None) -> subprocess.Popen:
    # the children inherit the caller's environment unchanged (BLAS threads included): the plan
    # matrices are built with BLAS, whose rounding depends on its thread count, and a lockstep
    # run must reproduce an in-process run of the same environment bit for bit
    env = child_env(extra_env)
    return subprocess.Popen([sys.executable, "-m", "ambhil.bridge.cli"] + argv, stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True, env=env, start_new_session=True,
                            preexec_fn=_die_with_parent)


def stop_process(p: subprocess.Popen, sig=signal.SIGTERM):
    if p.poll() is None:
        try:
            os.killpg(p.pid, sig)
        except ProcessLookupError:
            pass


def exit_text(code: int | None) -> str:
    """How a process ended, from its exit code: ``killed by SIGKILL`` / ``exited with code 1``."""
    if code is None:
        return "still running when stopped"
    if code < 0:
        try:
            return f"killed by {signal.Signals(-code).name}"
        except ValueError:
            return f"killed by signal {-code}"
    return f"exited with code {code}"


def startup_step(line: str) -> bool:
    """A peer's start-up progress line (``<role>: <step>``, bridge/process/startup.py) that only ``-v``
    shows: all but a kernel compilation (minutes, first run only) and the plant's start."""
    role, sep, text = line.partition(": ")
    return (bool(sep) and role in ("plant", "controller", "recorder") and not text.startswith("compiling")
            and not line.startswith("plant: running"))


class Child:
    """A child process whose output is read by threads: stdout kept (its last JSON line is the
    summary), stderr kept and echoed to our stderr while ``echo`` is set (the start-up progress
    lines, ``<role>: <step>``; the plant's ``plant: running`` line ends the start-up)."""

    def __init__(self, name: str, argv: list[str], echo: threading.Event, external: bool = False,
                 env: dict | None = None):
        self.name, self.echo, self.external = name, echo, external
        self.argv = list(argv)
        self.verbose = getattr(echo, "verbose", False)     # -v: every start-up step
        if external:   # a command of the user's (e.g. a controller in another language)
            self.p = subprocess.Popen(argv, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                                      env=child_env(env), start_new_session=True, preexec_fn=_die_with_parent)
        else:
            self.p = spawn_cli(argv, env)
        self.out: list[str] = []
        self.err: list[str] = []
        self._threads = [threading.Thread(target=self._read, args=(self.p.stdout, self.out, False), daemon=True),
                         threading.Thread(target=self._read, args=(self.p.stderr, self.err, True), daemon=True)]
        for t in self._threads:
            t.start()

    def _read(self, stream, sink, is_err):
        for line in stream:
            sink.append(line)
            if is_err and self.echo.is_set() and (self.verbose or not startup_step(line)):
                sys.stderr.write(line)
                sys.stderr.flush()
                if self.name == "plant" and line.startswith("plant: running"):
                    self.echo.clear()

    def result(self, timeout: float) -> tuple[dict | None, str, int | None]:
        """(summary or None, stderr, exit code) once the process ended (stopped after
        ``timeout`` s: SIGTERM, then SIGKILL)."""
        for sig, wait in ((None, timeout), (signal.SIGTERM, 5.0), (signal.SIGKILL, 5.0)):
            if sig is not None:
                stop_process(self.p, sig)
            try:
                self.p.wait(wait)
                break
            except subprocess.TimeoutExpired:
                continue
        for t in self._threads:
            t.join(2.0)
        lines = [ln for ln in self.out if ln.startswith("{")]
        try:
            s = json.loads(lines[-1]) if lines else None
        except ValueError:
            s = None
        if self.external and (not isinstance(s, dict) or "fault" not in s) and self.p.returncode is not None:
            # a command of the user's need not print our summary: its exit code says how it ended
            s = {"role": self.name, "external": True, "exit_code": self.p.returncode,
                 "fault": None if self.p.returncode == 0 else f"exited with code {self.p.returncode}"}
        return s, "".join(self.err), self.p.returncode
