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
import json
import os
import pickle
import shutil
import signal
import subprocess
import sys
import tempfile
import threading
import traceback
import weakref
from pathlib import Path

__all__ = ["TimelineProcess", "TimelineWriterError"]

_UNANSWERED_BYTES = 256 << 20  # pickled calls the child has not answered yet, above which a caller waits
_POLL_S = 1.0  # a waiting caller checks this often whether the child is still there
_ADVICE = "a fit runs without a timeline with runtime.usd_every=0"


class TimelineWriterError(RuntimeError):
    """The timeline's writer process could not start or take a call, or it ended without saying why (killed, or
    an error that could not be sent back)."""


# the child's command: the caller's module path (so the child imports what the caller would), its answers on a pipe
# of their own (argv[2], not inherited further), so nothing it prints (a site hook, an import's greeting) counts as one
_CHILD = ("import json, os, sys; sys.path[:] = json.loads(os.environ.pop('WTOPO_TIMELINE_PATH')); "
          "fd = int(sys.argv[2]); os.set_inheritable(fd, False); "
          "from wtopo.io._timeline_process import _serve; _serve(sys.argv[1], os.fdopen(fd, 'w'))")


def _child_env() -> dict:
    env = dict(os.environ)
    env["CUDA_VISIBLE_DEVICES"] = ""  # the child authors on the CPU: no CUDA context, no GPU memory
    # this process's module path, with its working folder made explicit (the child's is the same), and the folder
    # of this wtopo package first where the path does not hold it
    paths = [os.path.abspath(p) if p else os.getcwd() for p in sys.path]
    root = str(Path(__file__).resolve().parents[2])
    if root not in paths:
        paths.insert(0, root)
    env["WTOPO_TIMELINE_PATH"] = json.dumps(paths)
    return env


class _Pending:
    """What the caller and its answer-counting thread share: the bytes of each unanswered call, oldest first."""

    def __init__(self):
        self.sizes: collections.deque = collections.deque()
        self.unanswered = 0
        self.ended = False
        self.cond = threading.Condition()


def _count_answers(pipe, pending: _Pending) -> None:
    """The caller's thread: one line from the child per call made; at the child's end, every waiting caller is
    freed. A plain function: the thread holds no reference to the :class:`TimelineProcess`."""
    with pipe:
        for _ in pipe:
            with pending.cond:
                if pending.sizes:
                    pending.unanswered -= pending.sizes.popleft()
                pending.cond.notify_all()
    with pending.cond:
        pending.ended = True
        pending.cond.notify_all()


def _release(proc, folder: str, stderr) -> None:
    """End ``proc`` (killed if it still runs), close its stdin and ``stderr``, remove ``folder``: a writer's end,
    whether closed, aborted or dropped."""
    with contextlib.suppress(OSError):
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    with contextlib.suppress(OSError):
        if proc.stdin and not proc.stdin.closed:
            proc.stdin.close()
    stderr.close()
    shutil.rmtree(folder, ignore_errors=True)


class TimelineProcess:
    """A :class:`~wtopo.io.TimelineWriter` of ``path`` (its keyword arguments in ``writer_kwargs``) in a child
    process. The same calls (:meth:`add_cameras`, :meth:`add_sample`, :meth:`add_mesh`, :meth:`close`) with the
    same arguments, and :meth:`carry_over` (an earlier file's samples), checked by the writer in the child: an
    argument error is raised at the next call or at ``close``, not at the call that made it. Arrays are copied
    (pickled) when the call is made, so the caller may change them right after (torch tensors: pass NumPy arrays;
    the child sees no CUDA device). :meth:`abort` ends the child and writes nothing; so does dropping the object.
    Also a context manager (``close`` on success, ``abort`` on an error).

    Attributes:
        max_surfels: the writer's ``max_surfels`` (surfels per sample above which it writes a strided subset).
    """

    def __init__(self, path: str | os.PathLike, **writer_kwargs):
        from .usd import TimelineWriter

        if getattr(sys, "frozen", False):
            raise TimelineWriterError(f"the timeline's writer process needs a Python interpreter, and this is a frozen "
                                      f"application ({sys.executable!r}); {_ADVICE}")
        self.max_surfels = int(writer_kwargs.get("max_surfels", TimelineWriter.MAX_SURFELS))
        self._dir = tempfile.mkdtemp(prefix="wtopo-timeline-")
        self._error_path = os.path.join(self._dir, "status")
        self._stderr = open(os.path.join(self._dir, "stderr"), "w+b")  # noqa: SIM115 - closed by _cleanup
        self._done = False
        self._calls = 0
        self._pending = _Pending()
        read_end, write_end = os.pipe()
        self._proc = None
        try:
            cmd = [sys.executable, *subprocess._args_from_interpreter_flags(), "-c", _CHILD,  # noqa: SLF001
                   self._dir, str(write_end)]
            self._proc = subprocess.Popen(cmd, stdin=subprocess.PIPE, stdout=self._stderr, stderr=self._stderr,
                                          pass_fds=(write_end,), env=_child_env(), start_new_session=True)
            os.close(write_end)  # the child's copy is the only writer: its end is the answers' end of file
            write_end = None
            answers = os.fdopen(read_end, "rb")
            read_end = None
            threading.Thread(target=_count_answers, args=(answers, self._pending), daemon=True,
                             name="wtopo-timeline-answers").start()
            self._finalizer = weakref.finalize(self, _release, self._proc, self._dir, self._stderr)
        except BaseException as e:
            for fd in (read_end, write_end):
                if fd is not None:
                    os.close(fd)
            if self._proc is not None:
                _release(self._proc, self._dir, self._stderr)
            else:
                self._stderr.close()
                shutil.rmtree(self._dir, ignore_errors=True)
            if isinstance(e, (OSError, TypeError, ValueError, AssertionError)):
                raise TimelineWriterError(f"could not start the timeline's writer process ({sys.executable!r}): "
                                          f"{e}; {_ADVICE}") from e
            raise
        self._send("open", os.fspath(path), **writer_kwargs)

    def __enter__(self) -> TimelineProcess:
        return self

    def __exit__(self, exc_type, exc, tb) -> None:
        if exc_type is None:
            self.close()
        else:
            self.abort()

    def add_cameras(self, cameras, **kwargs) -> None:
        self._send("add_cameras", list(cameras), **kwargs)

    def add_sample(self, iteration: int, **arrays) -> None:
        self._send("add_sample", int(iteration), **arrays)

    def add_mesh(self, name: str, verts, faces, **kwargs) -> None:
        self._send("add_mesh", name, verts, faces, **kwargs)

    def carry_over(self, path: str | os.PathLike, until: int) -> None:
        """Author the samples of an earlier timeline file at iterations up to ``until`` (a resumed fit's, before its
        own samples; :func:`wtopo.io._usd_read.earlier_samples`). The file is read before anything is written, so
        it may be the one this writer will replace."""
        self._send("carry_over", os.fspath(path), int(until))

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
            self._cleanup()

    def _send(self, name: str, *args, **kwargs) -> None:
        if self._done:
            raise RuntimeError("the timeline writer is closed")
        pending = self._pending
        with pending.cond:  # wait while the child is far behind, and notice when it is gone
            while (pending.sizes and pending.unanswered > _UNANSWERED_BYTES and not pending.ended
                   and self._proc.poll() is None):
                pending.cond.wait(timeout=_POLL_S)
        if pending.ended or self._proc.poll() is not None:  # the child ended early: its error
            self._proc.wait()
            self._finish()
        number = self._calls + 1
        call = os.path.join(self._dir, f"{number}.call")
        try:
            with open(call, "wb") as f:  # read by the child only once its number is sent
                pickle.dump((name, args, kwargs), f, protocol=pickle.HIGHEST_PROTOCOL)
                size = f.tell()
        except BaseException as e:
            with contextlib.suppress(OSError):
                os.unlink(call)
            if isinstance(e, OSError):
                raise TimelineWriterError(f"could not hand the timeline's {name} call to its writer process through "
                                          f"{self._dir}: {e}; {_ADVICE}") from e
            raise
        with pending.cond:
            pending.sizes.append(size)
            pending.unanswered += size
        try:
            self._proc.stdin.write(f"{number}\n".encode())
            self._proc.stdin.flush()
        except OSError:  # a broken pipe: the child ended
            self._proc.wait()
            self._finish()
            raise
        except BaseException:  # interrupted before the number went out: the call was not made
            with pending.cond:
                pending.sizes.pop()
                pending.unanswered -= size
            with contextlib.suppress(OSError):
                os.unlink(call)
            raise
        self._calls = number

    def _finish(self):
        """The child has ended: its result (``close``'s stats), or its error raised."""
        try:
            blob = b""
            if os.path.exists(self._error_path):
                with open(self._error_path, "rb") as f:
                    blob = f.read()
            self._stderr.seek(max(0, self._stderr.seek(0, os.SEEK_END) - 4000))
            err = self._stderr.read().decode(errors="replace")
        finally:
            self._cleanup()
        try:
            status = pickle.loads(blob) if blob else None
        except Exception:  # noqa: BLE001 - a status cut short, or an exception that does not rebuild
            status = None
        if isinstance(status, tuple) and status[0] == "ok":
            return status[1]
        if isinstance(status, tuple) and status[0] == "error":
            exc, text = status[1], status[2]
            note = "raised in the timeline's writer process:\n" + text
            if isinstance(exc, BaseException) and hasattr(exc, "add_note"):
                exc.add_note(note)
                raise exc
            if isinstance(exc, BaseException):  # Python 3.10: the child's traceback as the cause
                raise exc from TimelineWriterError(note)
            raise TimelineWriterError(f"the timeline's writer process failed:\n{text}")
        code = self._proc.returncode
        how = f"exit code {code}"
        if code is not None and code < 0:
            with contextlib.suppress(ValueError):
                how = f"killed by {signal.Signals(-code).name} (exit code {code})"
        raise TimelineWriterError(f"the timeline's writer process ended: {how}"
                                  + (f":\n{err}" if err.strip() else ""))

    def _cleanup(self) -> None:
        """The child ended (killed first if it still runs), the folder removed: the finalizer's work, run now."""
        self._done = True
        self._finalizer()


class _CallerGone(Exception):
    """The caller's end of the answers pipe is closed: its process went away."""


def _serve(folder: str, answers) -> None:
    """The child: for each call number read from stdin, load ``folder/N.call``, make the call on a writer and answer
    with a line on ``answers`` (a text stream); the result of ``close`` or the first error goes to
    ``folder/status``. A caller that goes away without closing (its stdin or its answers pipe closed) leaves
    nothing: no file, no folder."""
    writer = None
    status = None

    def answer() -> None:
        try:
            answers.write("\n")
            answers.flush()
        except OSError as e:
            raise _CallerGone from e

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
            elif name == "carry_over":
                from ._usd_read import earlier_samples

                for iteration, arrays in earlier_samples(*args):
                    writer.add_sample(iteration, **arrays)
            else:
                getattr(writer, name)(*args, **kwargs)
            answer()
        else:  # the caller closed stdin without closing the writer
            raise _CallerGone
    except _CallerGone:
        shutil.rmtree(folder, ignore_errors=True)
        return
    except BaseException as exc:  # noqa: BLE001 - every error goes back to the caller
        text = traceback.format_exc()
        try:  # the exception itself where it comes back whole, else its text alone
            pickle.loads(pickle.dumps(exc))
            status = ("error", exc, text)
        except Exception:  # noqa: BLE001
            status = ("error", None, text)
    with open(os.path.join(folder, "status"), "wb") as f:
        f.write(pickle.dumps(status))
    if status[0] == "error":
        sys.exit(1)
