# SPDX-License-Identifier: Apache-2.0
"""A :class:`wtopo.io.TimelineWriter` that authors in a child process.

The fit's loop on a GPU is bound by its host's Python; a writer thread beside it shares the GIL (each NumPy call
and each USD binding releases it and waits to take it back), so the loop and the writer take turns. A child
process authors on a core of its own: the caller only pickles each call's arguments into a pipe.

The child is a ``python -c`` that imports this module from the caller's ``wtopo`` package and serves. It is
started with :mod:`subprocess` (not :mod:`multiprocessing`, whose spawn re-runs an unguarded user script), in a
session of its own (a Ctrl-C in the terminal reaches the fit, which stops and closes the timeline, not the
writer), with no CUDA device visible (it never touches the GPU). It reads the calls on a thread of its own into a
queue of :data:`_QUEUE` calls, so a caller blocks only while the child is that far behind. An error in the child
ends it: the caller raises it (same type where it can be rebuilt, the child's traceback as a note) at its next
call or at :meth:`TimelineProcess.close`. Nothing is written before ``close`` (the writer writes atomically); a
child whose caller went away without closing writes nothing.
"""

from __future__ import annotations

import contextlib
import os
import pickle
import queue
import subprocess
import sys
import tempfile
import threading
import traceback
from pathlib import Path

__all__ = ["TimelineProcess", "TimelineWriterError"]

_QUEUE = 2  # calls the child holds read but not yet authored


class TimelineWriterError(RuntimeError):
    """The timeline's writer process ended without saying why (killed, or an error that could not be sent back)."""


def _child_env() -> dict:
    env = dict(os.environ)
    env["CUDA_VISIBLE_DEVICES"] = ""  # the child authors on the CPU: no CUDA context, no GPU memory
    return env


# the child's command: this wtopo package first on its path (not whatever ``wtopo`` the working folder holds)
_CHILD = ("import sys; sys.path.insert(0, {root!r}); from wtopo.io._timeline_process import _serve; "
          "_serve(sys.stdin.buffer, sys.argv[1])")


class TimelineProcess:
    """A :class:`~wtopo.io.TimelineWriter` of ``path`` (its keyword arguments in ``writer_kwargs``) in a child
    process. The same calls (:meth:`add_cameras`, :meth:`add_sample`, :meth:`add_mesh`, :meth:`close`) with the
    same arguments, checked by the writer in the child: an argument error is raised at the next call or at
    ``close``, not at the call that made it. Arrays are copied (pickled) when the call is made, so the caller may
    change them right after. :meth:`abort` ends the child and writes nothing.

    Attributes:
        max_surfels: the writer's ``max_surfels`` (surfels per sample above which it writes a strided subset).
    """

    def __init__(self, path: str | os.PathLike, **writer_kwargs):
        from .usd import TimelineWriter

        self.max_surfels = int(writer_kwargs.get("max_surfels", TimelineWriter.MAX_SURFELS))
        fd, self._error_path = tempfile.mkstemp(prefix="wtopo-timeline-", suffix=".err")
        os.close(fd)
        self._stderr = tempfile.TemporaryFile()  # noqa: SIM115 - the child's stderr, read and closed by _finish
        root = str(Path(__file__).resolve().parents[2])  # the folder holding this wtopo package
        self._proc = subprocess.Popen([sys.executable, "-c", _CHILD.format(root=root), self._error_path],
                                      stdin=subprocess.PIPE, stdout=subprocess.DEVNULL, stderr=self._stderr,
                                      env=_child_env(), start_new_session=True)
        self._done = False
        self._send("open", os.fspath(path), **writer_kwargs)

    def add_cameras(self, cameras, **kwargs) -> None:
        self._send("add_cameras", list(cameras), **kwargs)

    def add_sample(self, iteration: int, **arrays) -> None:
        self._send("add_sample", int(iteration), **arrays)

    def add_mesh(self, name: str, verts, faces, **kwargs) -> None:
        self._send("add_mesh", name, verts, faces, **kwargs)

    def close(self):
        """Author what is left, write the file (atomically) and end the child. Returns the writer's
        :class:`~wtopo.io.TimelineStats`; raises the child's error where it had one."""
        self._send("close")
        self._proc.stdin.close()
        self._proc.wait()
        return self._finish()

    def abort(self) -> None:
        """End the child now; nothing is written. Safe to call more than once and after :meth:`close`."""
        if not self._done:
            self._proc.kill()
            self._proc.wait()
            self._cleanup()

    def _send(self, name: str, *args, **kwargs) -> None:
        if self._done:
            raise RuntimeError("the timeline writer is closed")
        if self._proc.poll() is not None:  # the child ended early: its error
            self._finish()
        try:
            pickle.dump((name, args, kwargs), self._proc.stdin, protocol=pickle.HIGHEST_PROTOCOL)
            self._proc.stdin.flush()
        except (BrokenPipeError, OSError):
            self._proc.wait()
            self._finish()
            raise

    def _finish(self):
        """The child has ended: its result (``close``'s stats), or its error raised."""
        try:
            with open(self._error_path, "rb") as f:
                blob = f.read()
            self._stderr.seek(0)
            err = self._stderr.read().decode(errors="replace")
        finally:
            self._cleanup()
        status = pickle.loads(blob) if blob else None
        if isinstance(status, tuple) and status[0] == "ok":
            return status[1]
        if isinstance(status, tuple) and status[0] == "error":
            exc, text = status[1], status[2]
            if isinstance(exc, BaseException):
                exc.add_note("raised in the timeline's writer process:\n" + text)
                raise exc
            raise TimelineWriterError(f"the timeline's writer process failed:\n{text}")
        raise TimelineWriterError(f"the timeline's writer process ended with exit code {self._proc.returncode}"
                                  + (f":\n{err[-4000:]}" if err.strip() else ""))

    def _cleanup(self) -> None:
        self._done = True
        if self._proc.stdin and not self._proc.stdin.closed:
            with contextlib.suppress(OSError):
                self._proc.stdin.close()
        self._stderr.close()
        with contextlib.suppress(OSError):
            os.unlink(self._error_path)


def _serve(stream, error_path: str) -> None:
    """The child: read calls from ``stream`` on a reader thread, make them on a writer, report to ``error_path``."""
    calls: queue.Queue = queue.Queue(maxsize=_QUEUE)

    def read() -> None:
        while True:
            try:
                call = pickle.load(stream)
            except EOFError:
                call = None
            except BaseException as exc:  # noqa: BLE001 - a broken message ends the child with its error
                call = ("_error", (exc, traceback.format_exc()), {})
            calls.put(call)
            if call is None or call[0] in ("close", "_error"):
                return

    threading.Thread(target=read, daemon=True, name="wtopo-timeline-reader").start()
    writer = None
    try:
        while True:
            call = calls.get()
            if call is None:  # the caller went away without closing: write nothing
                return
            name, args, kwargs = call
            if name == "_error":
                raise args[0]
            if name == "open":
                from .usd import TimelineWriter

                writer = TimelineWriter(*args, **kwargs)
            elif name == "close":
                status = ("ok", writer.close())
                break
            else:
                getattr(writer, name)(*args, **kwargs)
    except BaseException as exc:  # noqa: BLE001 - every error goes back to the caller
        text = traceback.format_exc()
        try:
            status = ("error", exc, text)
            blob = pickle.dumps(status)
        except Exception:  # noqa: BLE001 - an exception that does not pickle goes back as its text
            blob = pickle.dumps(("error", None, text))
        with open(error_path, "wb") as f:
            f.write(blob)
        sys.exit(1)
    with open(error_path, "wb") as f:
        f.write(pickle.dumps(status))
