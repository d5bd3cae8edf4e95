"""The camera's response, pure: a leaf below detection.

``curve`` (the response curve, grey level for an irradiance, and the frozen
:class:`~pipeline.stages.response.curve.Response` the stages carry), ``edge_fit``
(a target edge's profile fitted through a response: the measure of the response
the estimators use, compiled by ``_edge_jit``). Nothing here imports the
detector; ``detect`` imports it, and ``image`` (the estimators of the response
and of the sensor that need the detector) sits above both.
"""
