"""What a lot script forked by the agent keeps of the agent's descriptors (gwc.lot.run.shed): none of
the agent's, but what a fork handler opened for the child (libuv's signal lock pipe, under uvloop)."""

from __future__ import annotations

import ast
import subprocess
import sys

CHILD = r"""
import os, sys, tempfile
import uvloop
from gwc.lot.run import open_files, shed

loop = uvloop.new_event_loop()  # the agent's kind of loop: libuv registers its fork handler
kept = tempfile.TemporaryFile()  # a file of the parent's
parent = open_files()
r, w = os.pipe()  # the answer's way back, opened after the snapshot: not inherited as far as shed knows
pid = os.fork()
if pid == 0:
    made = {fd for fd, what in open_files().items() if parent.get(fd) != what and fd not in (r, w)}
    shed(parent)
    now = open_files()
    os.write(w, repr((sorted(made), sorted(now), kept.fileno(), [r, w])).encode())
    os._exit(0)
os.close(w)
print(os.read(r, 65536).decode())
os.waitpid(pid, 0)
"""


def test_a_forked_script_closes_the_agents_descriptors_and_keeps_its_own() -> None:
    out = subprocess.run([sys.executable, "-c", CHILD], capture_output=True, text=True, timeout=30, check=True)
    made, now, parents_file, answer = ast.literal_eval(out.stdout)
    assert parents_file not in now, "the parent's file is still open in the child"
    assert made, "uvloop's fork handler made no descriptor of the child's own: the test shows nothing"
    assert set(made) <= set(now), f"shed closed what the fork made for the child: {made} vs {now}"
    assert set(now) - {0, 1, 2} == set(made) | set(answer), "the child kept a descriptor of the parent's"
