"""Start a private Xvfb on a free display: shared by tests/imagej/conftest.py and
scripts/fiji_dialog_screenshots.py (standard library only)."""
import os
import select
import subprocess
import time


class XvfbError(RuntimeError):
    """Xvfb did not start (the message holds the end of its log)."""


def start_xvfb(log_path=None, screen="1280x1024x24", timeout_s=30):
    """Start Xvfb (``-displayfd``: it picks a free display) and return ``(process, ":N")``.

    Its output goes to ``log_path`` (or nowhere). Stop it with :func:`stop_xvfb`.
    """
    read_fd, write_fd = os.pipe()
    log = open(log_path, "wb") if log_path else subprocess.DEVNULL
    try:
        proc = subprocess.Popen(["Xvfb", "-displayfd", str(write_fd), "-screen", "0", screen,
                                 "-nolisten", "tcp"], pass_fds=(write_fd,), stdout=log,
                                stderr=log, start_new_session=True)
    finally:
        os.close(write_fd)
        if log_path:
            log.close()
    data = b""
    deadline = time.monotonic() + timeout_s
    try:
        while not data.endswith(b"\n") and time.monotonic() < deadline:
            if select.select([read_fd], [], [], 0.5)[0]:
                chunk = os.read(read_fd, 64)
                if not chunk:
                    break
                data += chunk
    finally:
        os.close(read_fd)
    if not data.strip().isdigit():
        proc.kill()
        proc.wait()
        text = ""
        if log_path and os.path.isfile(log_path):
            with open(log_path, "rb") as fh:
                text = fh.read().decode("utf-8", "replace")[-2000:]
        raise XvfbError("Xvfb did not report a display number: %s" % text)
    return proc, ":" + data.decode().strip()


def stop_xvfb(proc, timeout_s=10):
    """Terminate the Xvfb started by :func:`start_xvfb` (killed if it does not stop)."""
    proc.terminate()
    try:
        proc.wait(timeout=timeout_s)
    except subprocess.TimeoutExpired:
        proc.kill()
        proc.wait()
