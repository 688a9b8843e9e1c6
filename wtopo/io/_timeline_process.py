# SPDX-License-Identifier: Apache-2.0
"""A :class:`wtopo.io.TimelineWriter` that authors in a child process.

The fit's loop on a GPU is bound by its host's Python; a writer thread beside it shares the GIL (each NumPy call
and each USD binding releases it and waits to take it back), so the loop and the writer take turns. A child
process authors on a core of its own: the caller only pickles each call's arguments into a pipe.

The child is a ``python -c`` that imports this module from the caller's ``wtopo`` package and serves. It is
started with :mod:`subprocess` (not :mod:`multiprocessing`, whose spawn re-runs an unguarded user script), in a
session of its own (a Ctrl-C in the terminal reaches the fit, which stops and closes the timeline, not the
writer), with no CUDA device visible (it never touches the GPU). Each call is pickled to a file of a private
folder and its number sent down a pipe; the child, single-threaded, loads the file, makes the call and answers
with a line on a pipe of its own (what it prints goes to its stderr file). The data never waits in a pipe for a
reader that is busy authoring (through a 64-KB pipe a 16-MB sample took hundreds of hand-offs, each waiting for
the child's GIL), and the caller blocks only while the calls the child has not answered hold more than
:data:`_UNANSWERED_BYTES` (the child's start, a few seconds of imports, is covered: the first samples wait as
files). An error in the child ends it: the caller raises it (same type where it can be rebuilt, the child's
traceback as a note) at its next call or at :meth:`TimelineProcess.close`. Nothing is written before ``close``
(the writer writes atomically); a child whose caller went away writes nothing and removes the folder.
"""

from __future__ import annotations

import collections
import contextlib
import os
import pickle
import shutil
import subprocess
import sys
import tempfile
import threading
import traceback
from pathlib import Path

__all__ = ["TimelineProcess", "TimelineWriterError"]

_UNANSWERED_BYTES = 256 << 20  # pickled calls the child has not answered yet, above which a caller waits


class TimelineWriterError(RuntimeError):
    """The timeline's writer process could not start, or ended without saying why (killed, or an error that could
    not be sent back)."""


def _child_env() -> dict:
    env = dict(os.environ)
    env["CUDA_VISIBLE_DEVICES"] = ""  # the child authors on the CPU: no CUDA context, no GPU memory
    return env


# the child's command: this wtopo package first on its path (not whatever ``wtopo`` the working folder holds); its
# answers go to a pipe of their own (argv[2]), so nothing it prints (a site hook, an import's greeting) counts as one
_CHILD = ("import os, sys; sys.path.insert(0, {root!r}); from wtopo.io._timeline_process import _serve; "
          "_serve(sys.argv[1], os.fdopen(int(sys.argv[2]), 'w'))")


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
        self._dir = tempfile.mkdtemp(prefix="wtopo-timeline-")
        self._error_path = os.path.join(self._dir, "status")
        self._stderr = open(os.path.join(self._dir, "stderr"), "w+b")  # noqa: SIM115 - read and closed by _finish
        root = str(Path(__file__).resolve().parents[2])  # the folder holding this wtopo package
        read_end, write_end = os.pipe()
        try:
            self._proc = subprocess.Popen([sys.executable, "-c", _CHILD.format(root=root), self._dir, str(write_end)],
                                          stdin=subprocess.PIPE, stdout=self._stderr, stderr=self._stderr,
                                          pass_fds=(write_end,), env=_child_env(), start_new_session=True)
        except OSError as e:
            os.close(read_end)
            self._stderr.close()
            shutil.rmtree(self._dir, ignore_errors=True)
            raise TimelineWriterError(f"could not start the timeline's writer process ({sys.executable!r}): {e}; "
                                      f"a fit runs without a timeline with runtime.usd_every=0") from e
        finally:
            os.close(write_end)  # the child's copy is the only writer: its end is the answers' end of file
        self._answers_pipe = os.fdopen(read_end, "rb")
        self._done = False
        self._calls = 0
        self._sizes: collections.deque = collections.deque()  # bytes of each unanswered call, oldest first
        self._unanswered = 0
        self._answered = threading.Condition()
        self._child_ended = False
        threading.Thread(target=self._answers, daemon=True, name="wtopo-timeline-answers").start()
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

    def _answers(self) -> None:
        """The caller's thread that counts the child's answers (one line per call made); at its end (the child's),
        it frees every waiting caller."""
        for _ in self._answers_pipe:
            with self._answered:
                if self._sizes:
                    self._unanswered -= self._sizes.popleft()
                self._answered.notify_all()
        self._answers_pipe.close()
        with self._answered:
            self._child_ended = True
            self._answered.notify_all()

    def _send(self, name: str, *args, **kwargs) -> None:
        if self._done:
            raise RuntimeError("the timeline writer is closed")
        with self._answered:
            while self._unanswered > _UNANSWERED_BYTES and not self._child_ended:
                self._answered.wait()
        if self._child_ended or self._proc.poll() is not None:  # the child ended early: its error
            self._proc.wait()
            self._finish()
        self._calls += 1
        call = os.path.join(self._dir, f"{self._calls}.call")
        with open(call, "wb") as f:  # read by the child only once its number is sent
            pickle.dump((name, args, kwargs), f, protocol=pickle.HIGHEST_PROTOCOL)
            size = f.tell()
        with self._answered:
            self._sizes.append(size)
            self._unanswered += size
        try:
            self._proc.stdin.write(f"{self._calls}\n".encode())
            self._proc.stdin.flush()
        except OSError:  # a broken pipe: the child ended
            self._proc.wait()
            self._finish()
            raise

    def _finish(self):
        """The child has ended: its result (``close``'s stats), or its error raised."""
        try:
            blob = b""
            if os.path.exists(self._error_path):
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
        shutil.rmtree(self._dir, ignore_errors=True)


def _serve(folder: str, answers) -> None:
    """The child: for each call number read from stdin, load ``folder/N.call``, make the call on a writer and answer
    with a line on ``answers`` (a text stream); the result of ``close`` or the first error goes to
    ``folder/status``. A caller that goes away without closing leaves nothing: no file, no folder."""
    writer = None
    status = None
    try:
        for line in sys.stdin:
            path = os.path.join(folder, f"{int(line)}.call")
            with open(path, "rb") as f:
                name, args, kwargs = pickle.load(f)
            os.unlink(path)
            if name == "open":
                from .usd import TimelineWriter

                writer = TimelineWriter(*args, **kwargs)
            elif name == "close":
                status = ("ok", writer.close())
                break
            else:
                getattr(writer, name)(*args, **kwargs)
            answers.write("\n")
            answers.flush()
        else:  # the caller went away without closing: write nothing, leave nothing
            shutil.rmtree(folder, ignore_errors=True)
            return
    except BaseException as exc:  # noqa: BLE001 - every error goes back to the caller
        text = traceback.format_exc()
        try:
            blob = pickle.dumps(("error", exc, text))
        except Exception:  # noqa: BLE001 - an exception that does not pickle goes back as its text
            blob = pickle.dumps(("error", None, text))
        with open(os.path.join(folder, "status"), "wb") as f:
            f.write(blob)
        sys.exit(1)
    with open(os.path.join(folder, "status"), "wb") as f:
        f.write(pickle.dumps(status))
