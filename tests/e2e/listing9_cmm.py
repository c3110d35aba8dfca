"""An independent Listing 9 CMM: the thesis's RS232 program (11.8) written again in Python, no gwc code.

It holds the device end of a pty (the line /dev/tty2a was), reads records ended by `!`, and does what
Listing 9 does: ` DOWNLD !` -> `kermit` receive then `tar -xvf *.tar` in its part folder; ` UPLD !`
`<part>!` -> `tar -cvf <part>.tar <part>/*` and `kermit` send of `<part>.tar`; `SETUP RUN !` `1!`
`<part>!` -> passed to SUP (the part remembered); `START RUN !` -> the verdict after a second, sent as
Listing 9's output() sends it, without its `!`; anything else to SUP. Kermit is Debian's G-Kermit,
its bytes carried to and from the line, as `system("kermit ilbr /dev/tty2a 9600")` ran it there.

It looks at the line's termios on the first record and says what it finds (Listing 9 sets 8E1:
PARENB, CS8, not PARODD, not CSTOPB); a Linux pty forces CS8 and clears PARENB whatever its ends ask,
so on a pty that says "NOT 8E1" and the ME's own log says what it opened the line with.

A file `mode` in its folder makes the upload hostile, for the ME's tests: `name:<as-name>` sends the
part program under that name (`../../x`, `/etc/x`); `tar:<member>`
sends a `<part>.tar` whose member is that path.

    python listing9_cmm.py FD SLAVE FOLDER
"""

from __future__ import annotations

import glob
import io
import os
import select
import subprocess
import sys
import tarfile
import termios
import time


def log(text: str) -> None:
    print(f"{time.strftime('%H:%M:%S')} {text}", flush=True)


def line_is_8e1(slave: str) -> bool:
    fd = os.open(slave, os.O_RDWR | os.O_NOCTTY)
    try:
        cflag = termios.tcgetattr(fd)[2]
    finally:
        os.close(fd)
    return (
        bool(cflag & termios.PARENB)
        and not cflag & termios.PARODD
        and not cflag & termios.CSTOPB
        and (cflag & termios.CSIZE) == termios.CS8
    )


class Listing9:
    def __init__(self, fd: int, slave: str, folder: str) -> None:
        self.fd, self.slave, self.folder = fd, slave, folder
        self.buf = b""
        self.part = ""
        self.checked = False

    def record(self) -> str:
        while b"!" not in self.buf:  # a byte at a time: what follows the record is Kermit's, not ours
            self.buf += os.read(self.fd, 1)
        rec, _, self.buf = self.buf.partition(b"!")
        return rec.decode("ascii", "replace") + "!"

    def kermit(self, *args: str) -> int:
        """G-Kermit, as system("kermit ...") ran it (the records' reader pauses). Not on the pty itself:
        a pty's two ends share one termios, so a Kermit that sets its end raw (and restores it after)
        would change the ME's line too; a real line has one per end. Its bytes are carried instead."""
        proc = subprocess.Popen(
            ["gkermit", "-X", "-q", "-i", "-P", "-b", "5", *args],
            cwd=self.folder,
            stdin=subprocess.PIPE,
            stdout=subprocess.PIPE,
        )
        assert proc.stdin is not None and proc.stdout is not None
        out = proc.stdout.fileno()
        deadline = time.monotonic() + 60
        while time.monotonic() < deadline:
            ready, _, _ = select.select([out, self.fd], [], [], 0.05)
            if out in ready:
                data = os.read(out, 65536)
                if not data:
                    break
                os.write(self.fd, data[:-2] if data.endswith(b"\r\n") else data)  # its goodbye CR LF
            if self.fd in ready:
                try:
                    proc.stdin.write(os.read(self.fd, 65536))
                    proc.stdin.flush()
                except BrokenPipeError:
                    pass
            if proc.poll() is not None and out not in ready:
                break
        if proc.poll() is None:
            proc.kill()
        code = proc.wait()
        proc.stdin.close()
        proc.stdout.close()
        return code

    def serve(self) -> None:
        log(f"Listing 9 CMM on {self.slave}, part folder {self.folder}")
        while True:
            rec = self.record()
            if not self.checked:
                self.checked = True
                log("line 8E1" if line_is_8e1(self.slave) else "line NOT 8E1")
            log(f"record {rec!r}")
            if rec == " DOWNLD !":
                rc = self.kermit("-r", "-w")
                tars = glob.glob(os.path.join(self.folder, "*.tar"))
                for t in tars:
                    subprocess.run(["tar", "-xf", t], cwd=self.folder, check=False)
                    os.unlink(t)
                log(f"download: kermit {rc}, untarred {[os.path.basename(t) for t in tars]}")
            elif rec == " UPLD !":
                self.upload(self.record()[:-1])
            elif rec == "SETUP RUN !":
                self.record()
                self.part = self.record()[:-1]
                log(f"to SUP: set up {self.part}")
            elif rec == "START RUN !":
                time.sleep(1.0)
                os.write(self.fd, b"PASS")  # output(): strlen(buffer)-1 bytes, the '!' left off
                log(f"measured {self.part}: PASS")
            else:
                log(f"to SUP: {rec!r}")

    def upload(self, part: str) -> None:
        mode = ""
        try:
            with open(os.path.join(self.folder, "mode")) as f:
                mode = f.read().strip()
        except FileNotFoundError:
            pass
        if mode.startswith("name:"):  # hostile: the program under a name of the device's choosing
            program = os.path.join(part, part)
            rc = self.kermit("-s", program, "-a", mode[len("name:") :])
            log(f"upload {part} as {mode[len('name:') :]!r}: kermit {rc}")
            return
        tar_name = f"{part}.tar"
        if mode.startswith("tar:"):  # hostile: a member outside the part directory
            data = io.BytesIO()
            with tarfile.open(fileobj=data, mode="w", format=tarfile.GNU_FORMAT) as tar:
                info = tarfile.TarInfo(mode[len("tar:") :])
                info.size = 6
                tar.addfile(info, io.BytesIO(b"owned\n"))
            with open(os.path.join(self.folder, tar_name), "wb") as f:
                f.write(data.getvalue())
        else:  # tar -cvf <part>.tar <part>/*
            files = sorted(os.path.relpath(p, self.folder) for p in glob.glob(os.path.join(self.folder, part, "*")))
            subprocess.run(["tar", "-cf", tar_name, *files], cwd=self.folder, check=False)
        rc = self.kermit("-s", tar_name)
        log(f"upload {tar_name} ({mode or 'the part directory'}): kermit {rc}")
        os.unlink(os.path.join(self.folder, tar_name))


if __name__ == "__main__":
    fd, slave, folder = int(sys.argv[1]), sys.argv[2], sys.argv[3]
    os.makedirs(folder, exist_ok=True)
    Listing9(fd, slave, folder).serve()
