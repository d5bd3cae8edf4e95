"""The camera's image as recorded, before detection: what the sensor did to the light.

``response`` (the response curve: grey level for an irradiance), ``response_estimate``
(that curve estimated from the images), ``flat_field`` (the sensor's fixed gain
pattern, PRNU), ``binning`` (images whose target edges are too wide, binned first).
"""
