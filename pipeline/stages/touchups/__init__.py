"""Touch-up extraction: from frames and detections to the touch-up table.

``stage`` (the stage and its steps), ``segments`` (steps 1-2), ``jacobian`` (step 3: the
image Jacobian and the camera it implies), ``targets`` (step 4: which touch-ups share a
target), ``rows`` (step 5: averaged final captures, the row), ``tilt`` (a tilted
target's bias), ``settle`` / ``swing`` / ``noise`` (the repeated final captures:
settling weights, the camera's swing, the detection noise), ``types`` (the records the
steps share).
``node`` (the stage's node: the function the runner calls, data in, data out).
"""
