"""A real terminal for `gwc console` when no one sits at it: a tmux server of its own runs
`python -m gwc ARGS`, its screen read back as text and keys sent to it. The console's end-to-end
tests drive it this way, and `gwc bench console` opens the console it measures in one.
"""

from __future__ import annotations

import shlex
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from gwc.errors import GwcError
from gwc.retry import Deadline

# What a terminal sets for what runs in it: never taken from the caller's environment.
TERMINAL_OWN = ("TERM", "COLUMNS", "LINES", "TMUX", "TMUX_PANE", "TERM_PROGRAM", "TERM_PROGRAM_VERSION")
LOOK_EVERY = 0.05  # seconds between two looks at the screen while waiting for a text


def have_tmux() -> bool:
    return shutil.which("tmux") is not None


class Terminal:
    """`python -m gwc ARGS` in a private tmux server of `size`, with exactly the environment `env`
    (env -i: the tmux server's own environment is the caller's, and an operator's GWC_DATABASE_URL or
    GWC_CONFIG must not reach the cell meant). close() ends it (safe twice)."""

    def __init__(self, name: str, env: dict[str, str], *args: str, size: tuple[int, int] = (160, 45)) -> None:
        if not have_tmux():
            raise GwcError("no tmux: install it (bin/setup does, as root) to run the console in a terminal")
        self.name = name
        self.folder = Path(tempfile.mkdtemp(prefix="gwc-term-"))
        self.tmux = ["tmux", "-S", str(self.folder / "tmux")]  # its socket goes with the folder at close()
        self.exit_file = self.folder / "exit"
        keep = {k: v for k, v in env.items() if k not in TERMINAL_OWN}
        pairs = " ".join(shlex.quote(f"{k}={v}") for k, v in sorted(keep.items()))
        gwc_cmd = shlex.join([sys.executable, "-m", "gwc", *args])
        script = self.folder / "run.sh"  # a file: tmux limits a command line to some 16 kB
        script.write_text(f"env -i {pairs} TERM=xterm-256color {gwc_cmd}\necho $? > {self.exit_file}\n")
        width, height = size
        cmd = shlex.join(["sh", str(script)])
        subprocess.run(
            [*self.tmux, "new-session", "-d", "-s", name, "-x", str(width), "-y", str(height), cmd], check=True
        )

    def screen(self) -> str:
        return subprocess.run([*self.tmux, "capture-pane", "-p"], capture_output=True, text=True).stdout

    def wait(self, what: str, *texts: str, timeout: float = 30) -> str:
        """The screen once it shows every one of `texts`; GwcError naming `what` (and the screen) after `timeout`."""
        deadline = Deadline(timeout)
        while True:
            screen = self.screen()
            if all(t in screen for t in texts):
                return screen
            if deadline.expired:
                raise GwcError(f"timed out after {timeout:.1f}s waiting for {what}; the terminal shows:\n{screen}")
            time.sleep(LOOK_EVERY)

    def keys(self, *keys: str) -> None:
        subprocess.run([*self.tmux, "send-keys", *keys], check=True)

    def pid(self) -> int:
        """The gwc process's pid (the pane runs sh, sh runs it)."""
        out = subprocess.run(
            [*self.tmux, "display-message", "-p", "#{pane_pid}"], capture_output=True, text=True, check=True
        )
        shell = int(out.stdout.strip())
        children = Path(f"/proc/{shell}/task/{shell}/children").read_text().split()
        if not children:
            raise GwcError(f"terminal {self.name}: its command is not running")
        return int(children[0])

    def exit_code(self, timeout: float = 10) -> int:
        """The gwc command's exit code once it has ended; GwcError if it has not within `timeout`."""
        deadline = Deadline(timeout)
        while not (said := self._said()):
            if deadline.expired:
                raise GwcError(f"terminal {self.name}: the command did not end within {timeout:.0f}s")
            time.sleep(LOOK_EVERY)
        return int(said)

    def _said(self) -> str:
        try:
            return self.exit_file.read_text().strip()  # empty while sh is writing it
        except FileNotFoundError:
            return ""

    def close(self) -> None:
        subprocess.run([*self.tmux, "kill-server"], capture_output=True)
        shutil.rmtree(self.folder, ignore_errors=True)
