"""Images decoded ahead of the stream in a second thread (ingest, issue 38).

Ingest takes a recording's messages one at a time, in file order
(:func:`pipeline.stages.ingest.stream.take_message`). Decoding a compressed
image (PNG/JPEG, ``cv2.imdecode``) is a third of it on the LR Mate-like cells
and OpenCV releases the GIL while it decodes, so :func:`prefetch_images` reads
the stream a little ahead and hands the next images' decoding to one worker
thread while the current image is detected (on the image worker,
:mod:`pipeline.stages.ingest.image_worker`) and the joint states between them
are taken. The messages still come out in file order, each image with its
decoded result (:func:`decode_image`), and an error (of the decoding or of
reading the file) surfaces where it would have without the read-ahead: a
decoding error when its message is taken, a read error after every message
read before it. An image whose decoding has not started when its message is
taken by the image worker (the other core busy) is taken back and decoded
there (``ingest_stream._take_image``), so a loaded machine waits no longer than
without the thread. The results are the same with or without it; there is no
switch (``tests/test_ingest_prefetch.py``).
"""

from __future__ import annotations

from collections import deque
from collections.abc import Callable, Iterator
from concurrent.futures import Future, ThreadPoolExecutor
from typing import Any

import numpy as np

from pipeline.io.mcap import EncodedImage, decode_image_message, image_to_gray

#: what :func:`decode_image` hands back: ``(encoded, grey, message error, pixel error)``
Decoded = tuple[EncodedImage | None, np.ndarray | None, Exception | None, ValueError | None]


def decode_image(sname: str, menc: str, data: bytes) -> Decoded:
    """An image message to grey pixels, with the step that failed kept apart.

    Returns ``(encoded, grey, None, None)``; ``(None, None, exc, None)`` when the
    message does not decode (bad bytes); ``(encoded, None, None, exc)`` when its
    pixels do not (``image_to_gray``'s ``ValueError``). Any other error of the
    pixel step is raised.
    """
    try:
        enc = decode_image_message(sname, menc, data)
    except Exception as exc:  # noqa: BLE001 - struct/json/protobuf errors: bad bytes
        return None, None, exc, None
    try:
        return enc, image_to_gray(enc), None, None
    except ValueError as exc:
        return enc, None, None, exc


def prefetch_images(
    messages: Iterator[Any],
    wants: Callable[[Any], tuple[str, str] | None],
    ahead: int = 2,
    max_buffer: int = 50_000,
) -> Iterator[tuple[Any, Future[Decoded] | None]]:
    """``messages`` in order, each image's decoding started ``ahead`` images early.

    Parameters
    ----------
    messages : the stream (mcap ``Message``-like: ``.data``)
    wants : ``(schema name, message encoding)`` of a message to decode ahead, else None
    ahead : images decoding (or decoded) ahead of the one being taken
    max_buffer : at most this many messages read ahead (joint states between images)

    Yields
    ------
    (message, future of :func:`decode_image` or None)
    """
    pending = 0  # futures in the buffer
    buf: deque[tuple[Any, Future[Decoded] | None]] = deque()
    error: BaseException | None = None
    done = False
    with ThreadPoolExecutor(1, thread_name_prefix="vtcal-decode") as pool:
        while True:
            while not done and pending < ahead and len(buf) < max_buffer:
                try:
                    msg = next(messages)
                except StopIteration:
                    done = True
                    break
                except Exception as exc:  # noqa: BLE001 - raised after the messages before it
                    error, done = exc, True
                    break
                kind = wants(msg)
                if kind is None:
                    buf.append((msg, None))
                else:
                    buf.append((msg, pool.submit(decode_image, kind[0], kind[1], msg.data)))
                    pending += 1
            if not buf:
                break
            msg, fut = buf.popleft()
            if fut is not None:
                pending -= 1
            yield msg, fut
    if error is not None:
        raise error
