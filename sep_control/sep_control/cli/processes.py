"""Child processes of `sep demo`: the nodes, resolved like `ros2 run` does, each in its own
process group with its output in a log file; every one is stopped on exit, Ctrl-C or error.
ROS-free (the nodes are separate processes)."""
from __future__ import annotations

import os
import signal
import subprocess
import time
from pathlib import Path


def executable(pkg: str, exe: str) -> str | None:
    """ros2run's lookup: <prefix of pkg in the ament index>/lib/<pkg>/<exe>, or None."""
    try:
        from ament_index_python import get_package_prefix
        prefix = get_package_prefix(pkg)
    # not installed; package not found (PackageNotFoundError is a LookupError); a bad name;
    # AMENT_PREFIX_PATH unset (OSError)
    except (ImportError, LookupError, ValueError, OSError):
        return None
    path = Path(prefix) / 'lib' / pkg / exe
    return str(path) if path.is_file() and os.access(path, os.X_OK) else None


class Children:
    """Child processes, each in its own process group; `stop_all` always reaps them."""

    def __init__(self, log_dir: Path, env: dict):
        self.log_dir, self.env = log_dir, env
        self.procs: dict[str, subprocess.Popen] = {}
        self.logs: dict[str, Path] = {}

    def start(self, name: str, argv: list[str]) -> subprocess.Popen:
        log = self.log_dir / f'{name}.log'
        fh = open(log, 'wb')
        p = subprocess.Popen(argv, env=self.env, stdout=fh, stderr=subprocess.STDOUT,
                             stdin=subprocess.DEVNULL, start_new_session=True)
        fh.close()
        self.procs[name], self.logs[name] = p, log
        return p

    def wait(self, name: str, timeout: float | None) -> int | None:
        try:
            return self.procs[name].wait(timeout=timeout)
        except subprocess.TimeoutExpired:
            return None

    def stop(self, name: str, grace: float = 5.0) -> int | None:
        p = self.procs[name]
        if p.poll() is None:
            try:
                os.killpg(p.pid, signal.SIGINT)
                p.wait(timeout=grace)
            except (ProcessLookupError, subprocess.TimeoutExpired):
                pass
        if p.poll() is None:
            try:
                os.killpg(p.pid, signal.SIGKILL)
            except ProcessLookupError:
                pass
            p.wait(timeout=10)
        return p.returncode

    def stop_all(self) -> None:
        for name in reversed(list(self.procs)):
            self.stop(name, grace=3.0)

    def dump_stacks(self, settle_s: float = 1.0) -> None:
        """Ask every running child for its Python stacks (SIGUSR1: the nodes' faulthandler writes
        them to their logs and they go on), so that the log tails show where each one is."""
        running = [p for p in self.procs.values() if p.poll() is None]
        for p in running:
            try:
                os.kill(p.pid, signal.SIGUSR1)
            except (ProcessLookupError, PermissionError):
                pass
        if running:
            time.sleep(settle_s)

    def tails(self, n: int = 15) -> str:
        """The last lines of every child's log (what a failure report needs)."""
        return '\n'.join(f'--- {name} ({"running" if p.poll() is None else f"exit {p.returncode}"}), '
                         f'{self.logs[name]}:\n{self.tail(name, n)}' for name, p in self.procs.items())

    def tail(self, name: str, n: int = 15) -> str:
        try:
            return '\n'.join(self.logs[name].read_text(errors='replace').splitlines()[-n:])
        except OSError:
            return ''
