"""The serial line to the CMM, a part the CMM's machine side holds (gwc/me/cmm.py): opening it (in the
background when a probe must not hold the ME's loop), closing it, and resynchronising it before each
exchange, so that nothing an earlier exchange left behind is read as the answer to a later one.

What the machine does over the line (downloads, runs, probes and their backoff) stays in CmmMachine;
this object knows the port, the line's settings and the STATUS/READY numbering, nothing of runs but
the number of the last one given up (whose late verdict it recognises and drops).
"""

from __future__ import annotations

import logging
import os
import threading
import time
from concurrent.futures import Future
from typing import Any

import serial

from gwc.config import Config
from gwc.me.cmm_sim import sim_link
from gwc.me.line import LineLost, LineTimeout, RecordStream, open_serial, serial_stream
from gwc.retry import Deadline

QUIET = 0.1  # resynchronising without STATUS (Kermit devices): the line must be quiet this long


class CmmLine:
    """The ME's end of the CMM's serial line: `open()` for an exchange, `open_for_probe()` for a probe,
    `resync()` before each exchange, `drop()` when it is gone."""

    def __init__(
        self,
        cfg: Config,
        machine_id: str,
        settings: dict[str, Any],
        log: logging.Logger,
        probe: bool,
    ) -> None:
        self.cfg, self.machine_id, self.settings, self.log = cfg, machine_id, settings, log
        self.probe = probe  # resync by STATUS/READY (else drain until quiet: Kermit devices)
        self.answer_timeout = float(settings.get("timeout", 5.0))
        self.open_timeout = float(settings.get("open_timeout", self.answer_timeout))
        self.given_up = 0  # the last run given up without a verdict: its verdict may still come
        self.stream: RecordStream | None = None  # the open line, if it is open
        self._ser: serial.SerialBase | None = None
        self._opening: tuple[str, Future[serial.SerialBase]] | None = None  # a probe's open (open_for_probe)
        self._status_no = 0

    def _port(self, wait: bool) -> str:
        port = str(self.settings["port"])
        if port != "sim":
            return port
        link = sim_link(self.cfg, self.machine_id)
        deadline = Deadline(self.open_timeout if wait else 0.0)
        while not link.exists():  # the simulator may still be starting, or its line is down
            if deadline.expired:
                raise LineLost(f"no CMM simulator: {link} does not exist (is `gwc run cmmsim` running?)")
            time.sleep(0.05)
        return os.path.realpath(link)

    def open(self) -> RecordStream:
        """The open line to the CMM, opened now if it is not (waiting for the simulator's pty to appear)."""
        if self.stream is None:
            if self._opening is not None:  # a probe's open under way: its outcome first
                port, opening = self._opening
                self._opening = None
                self._adopt(port, opening.result())
            else:
                port = self._port(wait=True)
                self._adopt(port, open_serial(self.settings, port))
        assert self.stream is not None
        return self.stream

    def open_for_probe(self) -> RecordStream | None:
        """The line for a probe, opened without holding the ME's loop: None while the open is under way.

        Opening a device server's port can take seconds: pyserial's TCP connect waits up to 5 s for a
        host that is off (its SYN unanswered), and rfc2217:// negotiates Telnet options for up to 3 s
        with a server that accepted but does not speak. The WC's pings (1.5 s) must be answered
        meanwhile, or the ME is taken for dead. LineLost if the open failed."""
        if self.stream is not None:
            return self.stream
        if self._opening is None:
            port = self._port(wait=False)
            self._opening = (port, self._open_in_background(port))
        port, opening = self._opening
        if not opening.done():
            return None
        self._opening = None
        self._adopt(port, opening.result())
        return self.stream

    def _open_in_background(self, port: str) -> Future[serial.SerialBase]:
        """open_serial in a daemon thread (one at a time: _opening), so a stopping ME never waits for it."""
        opening: Future[serial.SerialBase] = Future()

        def run() -> None:
            try:
                opening.set_result(open_serial(self.settings, port))
            except Exception as e:  # handed to the ME's loop, which takes the outcome
                opening.set_exception(e)

        threading.Thread(target=run, name=f"open-{self.machine_id}", daemon=True).start()
        return opening

    def _adopt(self, port: str, ser: serial.SerialBase) -> None:
        self._ser = ser
        self.stream = serial_stream(ser, f"CMM line {port}")
        self.log.info(
            "serial line to the CMM open: %s at %s %s%s%s (%s)",
            port,
            ser.baudrate,
            ser.bytesize,
            ser.parity,
            ser.stopbits,
            ", ".join(f"{k}={v}" for k, v in self.settings.items() if k != "port"),
        )

    @property
    def is_open(self) -> bool:
        return self._ser is not None

    def drop(self, why: str) -> None:
        """Close the line (it is opened again at the next exchange or probe)."""
        if self._ser is not None:
            self.log.warning("closing the serial line to the CMM: %s", why)
            try:
                self._ser.close()
            except (OSError, serial.SerialException):
                pass
        self._ser, self.stream = None, None

    def stale(self, rec: str, when: str) -> None:
        """A record nobody asked for: a late verdict of a run given up, or garbage. Logged, dropped."""
        if rec.rstrip("!") in ("PASS", "FAIL") and self.given_up:
            self.log.warning("late verdict %s for run %d (given up) %s: dropped", rec, self.given_up, when)
        elif rec.startswith("READY "):
            self.log.info("answer %s to an earlier STATUS %s: dropped", rec, when)
        else:
            self.log.warning("unexpected record from the CMM %s: %r dropped", when, rec)

    def resync(self, line: RecordStream) -> None:
        """Nothing from an earlier exchange may answer the next one: STATUS until READY!, or drain."""
        if not self.probe:
            junk = line.drain(QUIET, self.answer_timeout)
            if junk:
                self.stale(junk.decode("ascii", "backslashreplace"), "before the exchange")
            return
        ready = self.ask_status(line)
        deadline = Deadline(self.answer_timeout)
        while True:
            rec = line.next_record(deadline.left(), bare_verdict=True)
            if rec is None:
                raise LineTimeout(f"the CMM did not answer STATUS within {self.answer_timeout:.1f}s")
            if rec == ready:
                return
            self.stale(rec, f"before {ready}")

    def ask_status(self, line: RecordStream) -> str:
        """`STATUS <n>!`, numbered so that an answer to an earlier one (a CMM that read several at once
        after a measurement) is not taken for this one's; returns the answer due, `READY <n>!`."""
        self._status_no = self._status_no % 99999 + 1
        line.write_record(f"STATUS {self._status_no}!")
        return f"READY {self._status_no}!"
