"""Ingest: one streaming pass over a recording -> frames, detections, recording info.

``stage`` (the stage), ``stream`` (the pass over every message once), ``joints`` (the
joint states at every image), ``types`` (its settings and what it learns about a
recording), ``row_buffer`` (the growable tables it fills), ``image_worker`` (the thread
that decodes and detects the images, in order, while the pass reads on) and ``prefetch``
(an image message to grey pixels).
``node`` (the stage's node: the function the runner calls, data in, data out).
"""
