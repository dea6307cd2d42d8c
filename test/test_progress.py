"""The progress bar (sonar_ring.progress): redrawn in place in a terminal, silent in a log."""

import fcntl
import os
import pty
import struct
import subprocess
import sys
import termios

DRAW = ("import time; from sonar_ring.progress import progress_bar\n"
        "bar = progress_bar(50)\n"
        "for _ in range(50):\n"
        "    time.sleep(0.01); bar.update(1)\n"
        "bar.close()\n")


def run_with_stderr(stderr):
    return subprocess.run([sys.executable, "-c", DRAW], stderr=stderr, timeout=60)


def test_in_a_terminal_the_bar_is_redrawn_in_place():
    controller, terminal = pty.openpty()
    fcntl.ioctl(terminal, termios.TIOCSWINSZ, struct.pack("HHHH", 24, 100, 0, 0))  # a new pty is 0 x 0
    try:
        assert run_with_stderr(terminal).returncode == 0
        os.close(terminal)
        written = b""
        while True:
            try:
                chunk = os.read(controller, 65536)
            except OSError:  # the terminal is closed: everything is read
                break
            if not chunk:
                break
            written += chunk
    finally:
        os.close(controller)
    text = written.decode()
    assert "50/50" in text and text.count("\r") >= 2  # several redraws of one line
    assert text.count("\n") <= 1  # ... and one line when closed


def test_in_a_log_nothing_is_drawn():
    result = run_with_stderr(subprocess.PIPE)
    assert result.returncode == 0 and result.stderr == b""
