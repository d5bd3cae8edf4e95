"""An image message decoded to grey pixels, on a thread of its own (ingest).

Ingest reads a recording's messages in file order on one thread and hands
the images to the image worker (:mod:`pipeline.stages.ingest.image_worker`),
which detects them in order. Decoding a compressed image (PNG/JPEG,
``cv2.imdecode``) is a third of ingest on the LR Mate-like cells and OpenCV
releases the GIL while it decodes, so each image's :func:`decode_image` is
started on the worker's decoding thread as soon as its message is read
(``ImageWorker.decode``): the next images decode while the worker detects
this one and the reader takes the joint states between them. A decoding error
keeps apart which step failed and surfaces when its image is taken, in file
order. An image whose decoding has not started when the worker takes it (the
other core busy) is taken back and decoded there (``ingest_stream._take_image``),
so a loaded machine waits no longer than without the thread. The results are
the same with or without it (``tests/test_ingest_prefetch.py``).
"""

from __future__ import annotations

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
