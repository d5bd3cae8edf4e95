"""The camera's image as recorded, before detection: what the sensor did to the light.

The estimators that need the detector: ``response_estimate`` (the response
curve estimated from the images), ``flat_field`` (the sensor's fixed gain
pattern, PRNU), ``binning`` (images whose target edges are too wide, binned
first). The response curve itself and its edge fit are :mod:`pipeline.stages.response`,
below the detector.
"""
