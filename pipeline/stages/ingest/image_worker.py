"""Images taken on a worker thread while the stream is read (ingest).

Ingest reads a recording's messages in file order on one thread; each image
is then decoded (:func:`pipeline.stages.ingest.prefetch.decode_image`), detected
and, at the start, held back for the camera-response estimate
(``ingest_stream._take_image``). Detection steers each image by the last
clean one, so the images are taken one after the other, in order; but they
need nothing the other messages carry, and the other messages nothing they
produce. :class:`ImageWorker` takes the images on one worker thread, in the
order they are handed to it, while the caller goes on reading records and
joint states: the compiled detector (``nogil``), OpenCV and the decoder run
without Python's global lock, so the two overlap on two cores. Each image's
decoding starts on a third thread when its message is read
(:meth:`ImageWorker.decode`), so the next images decode while this one is
detected.

The results are those of taking each image inline, in order (one thread
takes them all, first come first taken). What differs is only when an
error shows, and that is kept as it was: an image's error is raised by the
next :meth:`ImageWorker.submit` or :meth:`ImageWorker.drain` after it
happened, and an error of a later message waits for the images before it
(:meth:`ImageWorker.drain` first), so the first error in file order wins.
After an image failed, the images after it are not taken. At most ``depth``
images wait for the worker: the reader then waits for it (the decoded images
held stay bounded however long the recording: ``tests/test_ingest_memory.py``).
"""

from __future__ import annotations

import threading
from collections import deque
from collections.abc import Callable
from concurrent.futures import Future, ThreadPoolExecutor
from types import TracebackType
from typing import Any, TypeVar

T = TypeVar("T")

#: images handed to the worker and not yet taken, at most
DEPTH = 8


class ImageWorker:
    """One thread taking images in the order given, errors raised in that order.

    Parameters
    ----------
    depth : images waiting for the worker at most; :meth:`submit` blocks beyond it

    Use as a context manager: leaving it (normally or by an error) stops the
    threads, and images not yet taken are dropped.
    """

    def __init__(self, depth: int = DEPTH) -> None:
        self.depth = max(int(depth), 1)
        self._pool = ThreadPoolExecutor(1, thread_name_prefix="vtcal-detect")
        self._decoder = ThreadPoolExecutor(1, thread_name_prefix="vtcal-decode")
        self._pending: deque[Future[None]] = deque()
        self._stop = threading.Event()

    def decode(self, fn: Callable[..., T], *args: Any) -> Future[T]:
        """Start ``fn(*args)`` (an image's decoding) on the decoding thread now."""
        return self._decoder.submit(fn, *args)

    def submit(self, fn: Callable[..., None], *args: Any) -> None:
        """Take an image with ``fn(*args)`` after those submitted before it.

        Raises the error of an earlier image, if one has failed by now.
        """
        while self._pending and (self._pending[0].done() or len(self._pending) >= self.depth):
            self._pending.popleft().result()
        self._pending.append(self._pool.submit(self._take, fn, args))

    def _take(self, fn: Callable[..., None], args: tuple[Any, ...]) -> None:
        if self._stop.is_set():  # an earlier image failed, or the reader stopped
            return
        try:
            fn(*args)
        except BaseException:
            self._stop.set()
            raise

    def drain(self) -> None:
        """Wait until every image submitted is taken; raise the first one's error."""
        while self._pending:
            self._pending.popleft().result()

    def __enter__(self) -> ImageWorker:
        return self

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        self._stop.set()
        self._pool.shutdown(wait=True, cancel_futures=True)
        self._decoder.shutdown(wait=True, cancel_futures=True)
