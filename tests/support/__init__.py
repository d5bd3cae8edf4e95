"""The test kit: what tests and benchmarks share to build inputs and check outputs.

Not part of the ``pipeline`` package (it ships nothing a user runs):
``demo_run`` (a synthetic run folder for the report tests), ``browser``
(headless Chromium over the DevTools pipe), ``mcap_write`` (hand-made MCAP
recordings, also damaged ones), ``rosbag_writers`` (bags written with rosbags'
own writers), ``robots_dh`` (closed-form DH references of the built-in robots).
"""
